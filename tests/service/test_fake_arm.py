"""The service's real-robot path end to end: the REST flow drives ur_rtde against the fake UR
controller (its own process on a free loopback address), as an integrator's dry run would."""

from __future__ import annotations

import time

import numpy as np
import pytest
from fastapi.testclient import TestClient

from recon import kinematics
from service.app import create_app
from tests.drivers import fake_ur_fixture
from tests.service.conftest import AUTH, make_settings, planned_session, wait

fake_ur_process = fake_ur_fixture.fake_ur_process
fake_ur = fake_ur_fixture.fake_ur

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def arm(tmp_path_factory, scene_files, fake_ur_process):
    """A service whose real arm is the fake, with a trajectory that passed its dry run."""
    settings = make_settings(
        tmp_path_factory.mktemp("fake_arm"),
        ur_host=fake_ur_process.host,
        ur_robot="ur5e",
        max_speed_m_s=0.1,
        ur_watchdog_hz=fake_ur_fixture.SERVICE_WATCHDOG_HZ,
        ur_stale_after_s=fake_ur_fixture.SERVICE_STALE_AFTER_S,
    )
    with TestClient(create_app(settings), headers=AUTH) as client:
        sid, trajectories = planned_session(client, scene_files, (0.1,), name="fake arm")
        trajectory_id = trajectories[0.1]
        dry = client.post(f"/sessions/{sid}/executions", json={"trajectory_id": trajectory_id})
        assert wait(client, dry.json())["result"]["completed"]
        csv = client.get(f"/sessions/{sid}/trajectories/{trajectory_id}/csv").text
        q_start = np.array(csv.splitlines()[2].split(",")[1:7], dtype=float)
        yield client, sid, trajectory_id, q_start


def _execute(client, sid, trajectory_id):
    response = client.post(
        f"/sessions/{sid}/executions",
        json={"trajectory_id": trajectory_id, "backend": "ur_rtde", "confirm": True},
    )
    assert response.status_code == 202, response.text
    return response.json()


def _execute_until(client, sid, trajectory_id, *, progress: float) -> dict:
    """Start an execution on the arm and return its job once past ``progress``."""
    job = _execute(client, sid, trajectory_id)
    deadline = time.monotonic() + 60
    while client.get(f"/jobs/{job['id']}").json()["progress"] < progress:
        assert time.monotonic() < deadline, "the execution did not get going"
        time.sleep(0.05)
    return job


def test_an_arm_moved_away_from_the_plans_start_is_refused_with_the_distance(arm, fake_ur):
    client, sid, trajectory_id, q_start = arm
    # Jogged away after planning: nothing moves, the operator is told to plan again.
    fake_ur.control("reset", q_rad=(q_start + [0.1, 0, 0, 0, 0, 0]).tolist())
    response = client.post(
        f"/sessions/{sid}/executions",
        json={"trajectory_id": trajectory_id, "backend": "ur_rtde", "confirm": True},
    )
    assert response.status_code == 409 and response.json()["code"] == "start_moved"
    detail = response.json()["detail"]
    assert detail["max_joint_deg"] == pytest.approx(np.degrees(0.1), abs=0.05)
    assert detail["flange_distance_m"] > 0.02
    q_now = np.array(fake_ur.control("status")["q_rad"])
    assert np.abs(q_now - (q_start + [0.1, 0, 0, 0, 0, 0])).max() < 1e-9


def test_a_plan_of_inputs_no_longer_the_sessions_is_shown_outdated_and_refused(
    arm, fake_ur, scene_files
):
    """A new trace left the old plan ready to run (its dry run passed, "Run on arm" offered).
    Now the plan lists what changed, the gate refuses it (outdated_inputs, naming the change)
    and runs it only when the request picks it explicitly; the record keeps what was accepted."""
    from tests.service.conftest import T_BASE_TRACKER

    client = arm[0]
    sid, trajectories = planned_session(client, scene_files, (0.1,), name="outdated")
    trajectory_id = trajectories[0.1]
    dry = client.post(f"/sessions/{sid}/executions", json={"trajectory_id": trajectory_id})
    assert wait(client, dry.json())["result"]["completed"]
    plan_url = f"/sessions/{sid}/trajectories/{trajectory_id}"
    assert client.get(plan_url).json()["outdated"] == []
    csv = client.get(f"{plan_url}/csv").text
    q_start = np.array(csv.splitlines()[2].split(",")[1:7], dtype=float)
    fake_ur.control("reset", q_rad=q_start.tolist())

    # A different trace (the last sample left out) becomes the session's.
    lines = scene_files["trace"].decode().rstrip("\n").split("\n")
    new_trace = ("\n".join(lines[:-1]) + "\n").encode()
    uploaded = client.put(f"/sessions/{sid}/recording", files={"file": ("t2.csv", new_trace)})
    assert uploaded.status_code == 201, uploaded.text
    new_id = client.get(f"/sessions/{sid}").json()["recording_id"]
    (reason,) = client.get(plan_url).json()["outdated"]
    assert reason.startswith("the trace") and new_id in reason
    recon_id = client.get(plan_url).json()["inputs"]["reconstruction_id"]
    assert client.get(f"/sessions/{sid}/reconstructions/{recon_id}").json()["outdated"] == [reason]
    # And the calibration moved 2 mm.
    moved = [row[:] for row in T_BASE_TRACKER]
    moved[0][3] += 0.002
    assert client.put(f"/sessions/{sid}/calibration", json={"T_base_tracker": moved}).is_success
    outdated = client.get(plan_url).json()["outdated"]
    assert len(outdated) == 2 and "2.0 mm" in outdated[1]

    run = {"trajectory_id": trajectory_id, "backend": "ur_rtde", "confirm": True}
    refused = client.post(f"/sessions/{sid}/executions", json=run)
    assert refused.status_code == 409 and refused.json()["code"] == "outdated_inputs"
    assert refused.json()["detail"]["changed"] == outdated
    assert "Reconstruct and plan again" in refused.json()["message"]
    assert np.abs(np.array(fake_ur.control("status")["q_rad"]) - q_start).max() < 1e-9
    for bad in ("true", 1, None):
        response = client.post(f"/sessions/{sid}/executions", json={**run, "accept_outdated": bad})
        assert response.status_code == 422, (bad, response.text)

    # Picked explicitly: a calibration change is still refused (the cell would be misplaced:
    # the gate checks the plan in this session's frames); an older trace may be run.
    accepted = client.post(f"/sessions/{sid}/executions", json={**run, "accept_outdated": True})
    assert accepted.status_code == 409 and accepted.json()["code"] == "cell_unknown"
    assert client.put(
        f"/sessions/{sid}/calibration", json={"T_base_tracker": T_BASE_TRACKER}
    ).is_success
    outdated = client.get(plan_url).json()["outdated"]
    assert outdated == [reason]
    # The approval names the file: another checksum is refused, a malformed one is a 422.
    sha = client.get(plan_url).json()["sha256"]
    wrong = client.post(
        f"/sessions/{sid}/executions",
        json={**run, "accept_outdated": True, "approved_sha256": "0" * 64},
    )
    assert wrong.status_code == 409 and wrong.json()["code"] == "approval_mismatch"
    assert wrong.json()["detail"] == {"approved_sha256": "0" * 64, "stored_sha256": sha}
    for bad in ("abc", sha.upper(), sha + "0", 5):
        response = client.post(f"/sessions/{sid}/executions", json={**run, "approved_sha256": bad})
        assert response.status_code == 422, (bad, response.text)
    job = client.post(
        f"/sessions/{sid}/executions",
        json={**run, "accept_outdated": True, "approved_sha256": sha},
    )
    assert job.status_code == 202, job.text
    job = wait(client, job.json(), timeout_s=120)
    assert job["state"] == "succeeded", job
    execution = client.get(f"/sessions/{sid}/executions/{job['result']['execution_id']}").json()
    assert execution["params"]["accepted_outdated"] == outdated
    assert execution["params"]["approved_sha256"] == sha


def test_a_confirmed_execution_runs_on_the_controller(arm, fake_ur):
    client, sid, trajectory_id, q_start = arm
    # The arm stands where the plan starts (where it stood when it was planned).
    fake_ur.control("reset", q_rad=q_start.tolist())
    # The installation's payload (a 2 kg gripper): a plan that sets none must keep it. It was
    # overwritten with 0 kg before every run.
    program = "def installation():\n  set_payload(2.0, [0, 0, 0.05])\nend\n"
    assert fake_ur.wait_program(fake_ur.send_program(program))["state"] == "finished"
    deadline = time.monotonic() + 10  # the arm is read every robot_poll_s
    while (shown := client.get("/robot").json())["payload_kg"] != 2.0:
        assert time.monotonic() < deadline, shown
        time.sleep(0.05)
    assert shown["payload_cog_m"] == [0, 0, 0.05]
    plan = client.get(f"/sessions/{sid}/trajectories/{trajectory_id}").json()
    assert plan["summary"]["payload_kg"] is None
    job = wait(client, _execute(client, sid, trajectory_id), timeout_s=120)
    assert job["state"] == "succeeded", job
    execution_id = job["result"]["execution_id"]
    execution = client.get(f"/sessions/{sid}/executions/{execution_id}").json()
    assert execution["params"]["backend"] == "ur_rtde"
    assert execution["params"]["host"] == fake_ur.host
    summary = execution["summary"]
    assert summary["completed"] and summary["n_samples"] > 100 and not summary["dry_run"]
    # A real run is measured against its plan as a dry run is (one record shape). The fake's arm
    # follows the stream a lookahead behind and cuts the box's corner a little (3.2 mm measured
    # with both cores busy, 6.8 mm with two test processes beside it; the sim's dry run of the
    # same plan stays within 1 mm).
    assert summary["backend"] == "ur_rtde" and 0 < summary["max_path_deviation_m"] < 10e-3
    # The servoJ loop's timing is in the record: how it was scheduled (this test runs as root:
    # realtime; elsewhere it says why not), its longest period and the overruns counted.
    assert summary["realtime"].startswith(("realtime priority 80", "normal priority: realtime"))
    assert summary["max_period_s"] >= 0.002 and summary["period_overruns"] >= 0
    assert any(line.startswith("servoJ periods: longest") for line in summary["report"])
    print(
        f"\nservoJ on the fake: {summary['realtime']}; longest period "
        f"{summary['max_period_s'] * 1e3:.2f} ms, {summary['period_overruns']} overruns of "
        f"{summary['n_samples']}"
    )
    # The controller's arm ended where the plan ends.
    csv = client.get(f"/sessions/{sid}/trajectories/{trajectory_id}/csv").text
    q_end = np.array(csv.strip().splitlines()[-1].split(",")[1:7], dtype=float)
    status = fake_ur.control("status")
    assert np.abs(np.array(status["q_rad"]) - q_end).max() < 2e-3
    assert status["payload_kg"] == 2.0  # the installation's, kept
    # The service's watchdog setting reached the controller (the fixture's, not the default).
    assert "RTDE watchdog set: 0.5 Hz" in fake_ur.log_text()


def test_a_session_that_owns_the_arm_is_not_deleted_until_its_run_ends(arm, fake_ur):
    """Deleting under a running arm crashed the runner (job "running" until restart, journal
    unrecoverable): now refused, named, and possible once the run has ended."""
    client, sid, trajectory_id, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    job = _execute_until(client, sid, trajectory_id, progress=0.3)
    execution_id = job["params"]["execution_id"]
    refused = client.delete(f"/sessions/{sid}")
    assert refused.status_code == 409 and refused.json()["code"] == "session_owns_arm"
    assert execution_id in refused.json()["message"]
    assert client.get(f"/sessions/{sid}").status_code == 200  # still there, nothing changed
    running = client.get(f"/jobs/{job['id']}").json()["progress"]
    assert client.post(f"/executions/{execution_id}/stop").status_code == 200
    job = wait(client, job, timeout_s=60)
    # A stopped run's progress stays where it was shown while it ran: it never goes back.
    assert job["state"] == "cancelled" and running <= job["progress"] < 1.0, (running, job)
    execution = client.get(f"/sessions/{sid}/executions/{execution_id}").json()
    assert execution["summary"]["n_samples"] > 0  # the record of what moved is kept
    assert client.get("/health").json()["jobs_running"] == 0


def test_a_protective_stop_fails_the_job_with_its_code_and_keeps_the_record(arm, fake_ur):
    client, sid, trajectory_id, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    job = _execute_until(client, sid, trajectory_id, progress=0.4)
    fake_ur.control("protective_stop")
    job = wait(client, job, timeout_s=60)
    assert job["state"] == "failed" and job["error"]["code"] == "protective_stop", job
    execution_id = job["result"]["execution_id"]
    execution = client.get(f"/sessions/{sid}/executions/{execution_id}").json()
    assert not execution["summary"]["completed"]
    assert "protective stop" in " ".join(execution["summary"]["faults"]).lower()
    # What the arm did is the record (from the journal: the backend's own record of a run a
    # protective stop ended was empty, and it was stored as "before moving", 0 samples).
    assert execution["summary"]["n_samples"] > 100
    assert not job["result"]["stopped_in"].startswith("before moving")
    # The service stayed responsive throughout, and reports healthy.
    assert client.get("/health").json()["status"] == "ok"


def test_a_busy_database_loses_nothing_the_arm_did(arm, fake_ur, monkeypatch):
    """The database refuses writes while the arm runs and for a while after: the motion goes on
    (progress is for showing), the record is stored once the database takes it, and until then
    the journal is the record."""
    import sqlalchemy.exc

    from service import arm_runner

    client, sid, trajectory_id, q_start = arm
    services = client.app.state.services
    store = services.store
    refusals = {"progress": 0, "record": 0}
    real_update, real_add = store.update_job, store.add_arrays_artifact

    def locked(*_args, **_kwargs):
        raise sqlalchemy.exc.OperationalError("UPDATE jobs", {}, Exception("database is locked"))

    def update_job(job_id, **fields):
        if set(fields) == {"progress"}:
            refusals["progress"] += 1
            locked()
        return real_update(job_id, **fields)

    def add_arrays_artifact(**kwargs):
        if refusals["record"] < 2:  # two refusals, then the database is free again
            refusals["record"] += 1
            locked()
        return real_add(**kwargs)

    monkeypatch.setattr(store, "update_job", update_job)
    monkeypatch.setattr(store, "add_arrays_artifact", add_arrays_artifact)
    monkeypatch.setattr(arm_runner, "RECORD_RETRY_S", 30.0)
    fake_ur.control("reset", q_rad=q_start.tolist())
    job = client.post(
        f"/sessions/{sid}/executions",
        json={"trajectory_id": trajectory_id, "backend": "ur_rtde", "confirm": True},
    ).json()
    # Progress cannot be stored: watch the arm itself, and stop it once it has gone a way.
    deadline = time.monotonic() + 60
    while np.abs(np.array(fake_ur.control("status")["q_rad"]) - q_start).max() < 0.05:
        assert time.monotonic() < deadline, "the arm did not move"
        time.sleep(0.05)
    execution_id = job["params"]["execution_id"]
    assert client.post(f"/executions/{execution_id}/stop").status_code == 200
    job = wait(client, job, timeout_s=120)
    assert job["state"] == "cancelled", (job["error"], job["result"])  # stopped, not failed
    assert refusals["progress"] > 0 and refusals["record"] == 2
    execution = client.get(f"/sessions/{sid}/executions/{execution_id}").json()
    assert execution["summary"]["n_samples"] > 100
    from service.executions import journal_path

    journal = journal_path(client.app.state.services, execution_id)
    assert not journal.exists()  # deleted only once the record was stored


def test_a_database_that_stays_locked_leaves_the_journal_for_the_next_start(
    arm, fake_ur, monkeypatch
):
    import sqlalchemy.exc

    from service import arm_runner, executions

    client, sid, trajectory_id, q_start = arm
    services = client.app.state.services
    store = services.store
    real_add = store.add_arrays_artifact

    def locked(**_kwargs):
        raise sqlalchemy.exc.OperationalError("INSERT", {}, Exception("database is locked"))

    monkeypatch.setattr(store, "add_arrays_artifact", locked)
    monkeypatch.setattr(arm_runner, "RECORD_RETRY_S", 1.0)
    fake_ur.control("reset", q_rad=q_start.tolist())
    job = _execute_until(client, sid, trajectory_id, progress=0.3)
    execution_id = job["params"]["execution_id"]
    assert client.post(f"/executions/{execution_id}/stop").status_code == 200
    job = wait(client, job, timeout_s=120)
    journal = executions.journal_path(services, execution_id)
    assert journal.exists() and journal.stat().st_size > 1000  # the record, until stored
    assert client.get(f"/sessions/{sid}/executions/{execution_id}").status_code == 404
    # The database is free again; the next start (recover) stores the journal as the record.
    monkeypatch.setattr(store, "add_arrays_artifact", real_add)
    executions.recover(services)
    execution = client.get(f"/sessions/{sid}/executions/{execution_id}").json()
    assert execution["summary"]["n_samples"] > 100
    assert execution["params"]["recovered_from_journal"] is True
    assert not journal.exists()


def test_teachpath_fake_ur_runs_by_hand_and_refuses_what_it_cannot_do():
    import signal
    import subprocess
    import sys

    from tests.service.test_cli import run

    refused = run("fake-ur", "--host", "10.1.2.3")
    assert refused.returncode == 1 and "not a loopback address" in refused.stderr
    host = fake_ur_fixture.free_loopback_host()
    command = [sys.executable, "-m", "service.cli", "fake-ur", "--host", host, "--robot", "ur10e"]
    fake = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert f"fake ur10e controller listening on {host}" in fake.stdout.readline()
        taken = run("fake-ur", "--host", host)
        assert taken.returncode == 2 and f"cannot listen on {host}" in taken.stderr
        fake.send_signal(signal.SIGINT)
        assert fake.wait(timeout=20) == 0
    finally:
        if fake.poll() is None:
            fake.kill()
            fake.wait()


def test_a_controller_that_stops_answering_fails_the_job_and_the_service_stays_responsive(
    arm, fake_ur
):
    client, sid, trajectory_id, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    job = _execute_until(client, sid, trajectory_id, progress=0.3)
    deadline = time.monotonic() + 120
    fake_ur.control("freeze")
    # While the controller is silent, requests are still answered: many of them while the job
    # waits out the silence. A service blocked by the robot link would answer none until the
    # adapter's timeout (seconds, or ur_rtde's 300 s command wait) failed the job. (Counted,
    # not timed: a loaded machine makes each answer slower, not fewer of them possible.)
    answered_while_silent = 0
    while (state := client.get(f"/jobs/{job['id']}").json())["state"] == "running":
        assert client.get("/health").status_code == 200
        answered_while_silent += 1
        assert time.monotonic() < deadline, "the job never noticed the silence"
        time.sleep(0.05)
    assert state["state"] == "failed", state
    assert state["error"]["code"] in ("robot_connection_lost", "robot_timeout"), state
    assert answered_while_silent >= 3, answered_while_silent
    fake_ur.control("unfreeze")


# --- stop means stop; one owner; the exported program --------------------------------------------


def _phase_window(client, sid, trajectory_id, phase: str) -> tuple[float, float]:
    """The fraction of the samples (0..1) a phase spans, from the trajectory's summary."""
    durations = client.get(f"/sessions/{sid}/trajectories/{trajectory_id}").json()["summary"][
        "phase_durations_s"
    ]
    total, start = sum(durations.values()), 0.0
    for name, seconds in durations.items():
        if name == phase:
            return start / total, (start + seconds) / total
        start += seconds
    raise AssertionError(f"no {phase} phase")


def _stop(client, execution_id: str) -> dict:
    response = client.post(f"/executions/{execution_id}/stop")
    assert response.status_code == 200, response.text
    return response.json()


@pytest.mark.parametrize("delay_s", [0.0, 0.005, 0.02])
def test_a_stop_right_after_the_request_moves_nothing(arm, fake_ur, delay_s):
    client, sid, trajectory_id, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    job = _execute(client, sid, trajectory_id)
    time.sleep(delay_s)
    stopped = _stop(client, job["params"]["execution_id"])
    assert stopped["already_ended"] is False
    job = wait(client, job, timeout_s=60)
    assert job["state"] == "cancelled", job
    assert job["result"]["stopped_in"].startswith("before moving")
    # The controller's own record of the arm: it never left the start.
    time.sleep(0.3)
    q_now = np.array(fake_ur.control("status")["q_rad"])
    assert np.abs(q_now - q_start).max() < 1e-3
    execution = client.get(f"/sessions/{sid}/executions/{job['result']['execution_id']}").json()
    assert execution["summary"]["n_samples"] == 0 and not execution["summary"]["completed"]
    # And nothing of it moves later: the job has ended, the arm is free again.
    assert client.get("/robot").json()["owner_execution_id"] is None


def test_a_stop_during_the_approach_ends_it_there_with_no_path_sample(arm, fake_ur):
    client, sid, trajectory_id, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    low, high = _phase_window(client, sid, trajectory_id, "approach")
    job = _execute_until(client, sid, trajectory_id, progress=0.1 + 0.9 * (low + high) / 2)
    _stop(client, job["params"]["execution_id"])
    job = wait(client, job, timeout_s=60)
    assert job["state"] == "cancelled" and job["result"]["stopped_in"] == "approach", job
    summary = client.get(f"/sessions/{sid}/executions/{job['result']['execution_id']}").json()[
        "summary"
    ]
    assert "process" not in summary["executed_phase_durations_s"]
    assert summary["executed_phase_durations_s"]["approach"] > 0
    # At rest where it stopped.
    q_a = np.array(fake_ur.control("status")["q_rad"])
    time.sleep(0.3)
    q_b = np.array(fake_ur.control("status")["q_rad"])
    assert np.abs(q_b - q_a).max() < 1e-4
    # A stop after the end says so.
    assert _stop(client, job["result"]["execution_id"])["already_ended"] is True


def test_one_execution_owns_the_arm(arm, fake_ur):
    client, sid, trajectory_id, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    first = _execute_until(client, sid, trajectory_id, progress=0.15)
    second = client.post(
        f"/sessions/{sid}/executions",
        json={"trajectory_id": trajectory_id, "backend": "ur_rtde", "confirm": True},
    )
    assert second.status_code == 409 and second.json()["code"] == "arm_busy"
    assert first["params"]["execution_id"] in second.json()["message"]
    assert client.get("/robot").json()["owner_execution_id"] == first["params"]["execution_id"]
    # A dry run is not a use of the arm.
    dry = client.post(f"/sessions/{sid}/executions", json={"trajectory_id": trajectory_id})
    assert dry.status_code == 202
    _stop(client, first["params"]["execution_id"])
    assert wait(client, first, timeout_s=60)["state"] == "cancelled"
    wait(client, dry.json())


def test_confirm_takes_only_the_json_true(arm):
    client, sid, trajectory_id, _ = arm
    for value in ("yes", 1, "true"):
        response = client.post(
            f"/sessions/{sid}/executions",
            json={"trajectory_id": trajectory_id, "backend": "ur_rtde", "confirm": value},
        )
        assert response.status_code == 422 and response.json()["code"] == "invalid_request"


def test_the_robot_state_follows_the_controller(arm, fake_ur):
    client, _, _, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    time.sleep(0.5)
    state = client.get("/robot").json()
    assert state["backend"] == "ur_rtde" and state["real_arm"] and state["reachable"]
    assert state["robot_mode"] == "RUNNING" and state["safety_status"] == "NORMAL"
    assert state["remote_control"] is True and state["max_speed_m_s"] == pytest.approx(0.1)
    assert np.abs(np.array(state["q_rad"]) - q_start).max() < 1e-6
    # Where the joints are, for the pendant's live arm: the flange as forward kinematics puts
    # it, and the TCP as the controller reports it.
    from recon import kinematics

    joints = np.array(state["joints_m"])
    assert joints.shape == (8, 3) and np.allclose(joints[0], 0.0)
    flange = kinematics.forward(kinematics.model("ur5e"), np.array(state["q_rad"]))[:3, 3]
    assert np.abs(joints[6] - flange).max() < 2e-5
    assert np.abs(joints[7] - np.array(state["tcp_pose"][:3])).max() < 2e-5
    fake_ur.control("protective_stop")
    deadline = time.monotonic() + 5
    while not client.get("/robot").json()["protective_stop"]:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    stopped = client.get("/robot").json()
    assert stopped["safety_status"] == "PROTECTIVE_STOP" and 0 < stopped["unlock_in_s"] <= 5
    refused = client.post("/robot/unlock")  # within 5 s of the stop: the controller refuses
    assert refused.status_code == 409 and refused.json()["code"] == "protective_stop"
    fake_ur.control("configure", unlock_wait_s=0.0)
    assert client.post("/robot/unlock").json()["protective_stop"] is False
    fake_ur.control("configure", remote_control=False)
    time.sleep(0.5)
    assert client.get("/robot").json()["remote_control"] is False
    fake_ur.control("reset", q_rad=q_start.tolist())


@pytest.mark.parametrize("mode", ["servoj", "movep"])
def test_the_exported_program_runs_on_the_controller_and_ends_where_the_plan_ends(
    arm, fake_ur, mode
):
    client, sid, trajectory_id, q_start = arm
    program = client.get(
        f"/sessions/{sid}/trajectories/{trajectory_id}/urscript", params={"mode": mode}
    )
    assert program.status_code == 200 and "set_tcp(p[" in program.text
    assert trajectory_id in program.text and "checked:" in program.text
    # Away from the start, the program halts at its start check and moves nothing.
    away = q_start + [0.05, 0, 0, 0, 0, 0]
    fake_ur.control("reset", q_rad=away.tolist())
    status = fake_ur.wait_program(fake_ur.send_program(program.text))
    assert status["state"] == "finished"
    assert np.abs(np.array(fake_ur.control("status")["q_rad"]) - away).max() < 1e-9
    assert any("not at the start" in m for m in status["messages"])
    # At the start it runs the whole motion and ends where the plan ends.
    fake_ur.control("reset", q_rad=q_start.tolist())
    status = fake_ur.wait_program(fake_ur.send_program(program.text), timeout_s=120)
    assert status["state"] == "finished", status
    csv = client.get(f"/sessions/{sid}/trajectories/{trajectory_id}/csv").text
    end = csv.strip().splitlines()[-1].split(",")
    q_end, tcp_end = np.array(end[1:7], dtype=float), np.array(end[7:10], dtype=float)
    now = fake_ur.control("status")
    assert np.abs(np.array(now["q_rad"]) - q_end).max() < 2e-3
    assert np.linalg.norm(np.array(now["tcp_pose"][:3]) - tcp_end) < 1e-3
    # Along the whole motion it stays on the plan.
    trace = fake_ur.program_trace(every=5)
    planned = np.array([r.split(",")[7:10] for r in csv.strip().splitlines()[2:]], dtype=float)
    from recon.metrics import distance_to_curve

    off = distance_to_curve(trace["tcp_pose"][:, :3], planned)
    # servoj: the stream itself (measured 0.05 mm); movep: the tolerance, the blends, and the
    # fake's servo lagging the joints where the tool turns at the box's corner (1.2 mm).
    assert off.max() < (1e-3 if mode == "servoj" else 3e-3), off.max()


def test_a_keep_out_box_edited_into_the_path_stops_a_plan_made_before_it(arm, fake_ur):
    """The operator adds a keep-out box around part of the path after planning: the plan is
    outdated (the cell), and picked explicitly it is still refused, because the gate checks the
    samples against the cell in force, not the plan's copy; the arm does not move. While a run
    owns the arm, the cell cannot be edited."""
    client, sid, trajectory_id, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    plan_url = f"/sessions/{sid}/trajectories/{trajectory_id}"
    rows = client.get(f"{plan_url}/csv").text.splitlines()[2:]
    tcp_middle_m = np.array(rows[len(rows) // 2].split(",")[7:10], dtype=float)
    box = [*(tcp_middle_m - 0.01), *(tcp_middle_m + 0.01)]
    revision = client.get("/cell").json()["revision"]
    edit = {"keep_out_boxes_m": [box], "cell_planes": [], "revision": revision}
    assert client.put("/cell", json=edit).status_code == 200
    try:
        (reason,) = client.get(plan_url).json()["outdated"]
        assert reason.startswith("the cell: planned with 0 keep-out boxes"), reason
        run = {"trajectory_id": trajectory_id, "backend": "ur_rtde", "confirm": True}
        refused = client.post(f"/sessions/{sid}/executions", json=run)
        assert refused.status_code == 409 and refused.json()["code"] == "outdated_inputs"
        picked = client.post(f"/sessions/{sid}/executions", json={**run, "accept_outdated": True})
        assert picked.status_code == 409 and picked.json()["code"] == "collides_here", picked.text
        assert "keep-out box 1" in picked.json()["message"]
        assert np.abs(np.array(fake_ur.control("status")["q_rad"]) - q_start).max() < 1e-9
    finally:
        revision = client.get("/cell").json()["revision"]
        assert client.delete("/cell", params={"revision": revision}).status_code == 200
    assert client.get(plan_url).json()["outdated"] == []

    # While the plan runs on the arm, the cell it was checked against cannot change.
    job = _execute_until(client, sid, trajectory_id, progress=0.1)
    revision = client.get("/cell").json()["revision"]
    during = client.put("/cell", json={**edit, "revision": revision})
    assert during.status_code == 409 and during.json()["code"] == "arm_running"
    _stop(client, job["params"]["execution_id"])
    assert wait(client, job, timeout_s=60)["state"] == "cancelled"
    assert client.get("/cell").json()["revision"] == revision


def test_a_cell_edited_while_a_run_is_being_checked_refuses_the_run(arm, fake_ur, monkeypatch):
    """An edit landing between the gate's check of the samples and taking the arm: the run is
    refused (checked against a cell no longer in force) and the arm does not move."""
    from service import executions

    client, sid, trajectory_id, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    services = client.app.state.services
    checked_against = executions._cell_here

    def edited_meanwhile(*args, **kwargs):
        here = checked_against(*args, **kwargs)
        revision = services.store.cell(services.settings.cell_key)
        services.store.set_cell(
            services.settings.cell_key,
            boxes=[],
            planes=[[-1.0, 0.0, 0.0, -1.5]],
            expected_revision=0 if revision is None else revision.revision,
        )
        return here

    monkeypatch.setattr(executions, "_cell_here", edited_meanwhile)
    try:
        run = {"trajectory_id": trajectory_id, "backend": "ur_rtde", "confirm": True}
        refused = client.post(f"/sessions/{sid}/executions", json=run)
        assert refused.status_code == 409 and refused.json()["code"] == "cell_unknown"
        assert "the cell was edited while this run was being checked" in refused.text
        assert np.abs(np.array(fake_ur.control("status")["q_rad"]) - q_start).max() < 1e-9
    finally:
        monkeypatch.undo()
        revision = client.get("/cell").json()["revision"]
        assert client.delete("/cell", params={"revision": revision}).status_code == 200


def test_an_arm_moved_away_goes_back_to_the_plans_start_by_a_move_of_its_own(arm, fake_ur):
    """Jogged away after the plan's dry run: the run is refused (start_moved); a move to the
    start is planned from where the arm is, refused on the arm until it is dry-run here, then
    run; the plan itself then runs as approved, without planning it again."""
    client, sid, trajectory_id, q_start = arm
    jogged = q_start + [0.25, -0.1, 0.05, 0.0, 0.1, 0.3]
    fake_ur.control("reset", q_rad=jogged.tolist())
    time.sleep(0.5)  # the arm's state is read a few times a second
    run = {"trajectory_id": trajectory_id, "backend": "ur_rtde", "confirm": True}
    refused = client.post(f"/sessions/{sid}/executions", json=run)
    assert refused.status_code == 409 and refused.json()["code"] == "start_moved"
    assert "move-to-start" in refused.json()["message"]

    job = client.post(f"/sessions/{sid}/trajectories/{trajectory_id}/move-to-start")
    assert job.status_code == 202, job.text
    job = wait(client, job.json())
    assert job["state"] == "succeeded", job
    move_id = job["result"]["trajectory_id"]
    move = client.get(f"/sessions/{sid}/trajectories/{move_id}").json()
    summary = move["summary"]
    assert summary["move_to_start_of"] == trajectory_id
    assert move["inputs"]["move_to_start_of"] == trajectory_id and move["outdated"] == []
    assert summary["start_from"] == "arm"
    assert list(summary["phase_durations_s"]) == ["transit"]
    assert summary["phase_max_tcp_speed_m_s"]["transit"] <= 0.1 + 1e-9  # the server's cap
    assert any("no collision" in check for check in summary["checks"]), summary["checks"]
    rows = client.get(f"/sessions/{sid}/trajectories/{move_id}/csv").text.splitlines()[2:]
    first, last = (np.array(rows[i].split(",")[1:7], dtype=float) for i in (0, -1))
    np.testing.assert_allclose(first, jogged, atol=1e-4)  # from where the arm stands
    np.testing.assert_allclose(last, q_start, atol=1e-9)  # to exactly where the plan starts

    # Like any plan: not on the arm before its dry run here; then it runs.
    not_yet = client.post(f"/sessions/{sid}/executions", json={**run, "trajectory_id": move_id})
    assert not_yet.status_code == 409 and not_yet.json()["code"] == "dry_run_required"
    dry = client.post(f"/sessions/{sid}/executions", json={"trajectory_id": move_id})
    assert wait(client, dry.json())["result"]["completed"]
    moved = wait(
        client,
        client.post(f"/sessions/{sid}/executions", json={**run, "trajectory_id": move_id}).json(),
    )
    assert moved["state"] == "succeeded", moved
    q_now = np.array(fake_ur.control("status")["q_rad"])
    assert np.abs(q_now - q_start).max() < 1e-3, np.degrees(q_now - q_start)

    # Standing at the start: no move is needed, and the plan runs as it was approved.
    time.sleep(0.5)
    at_start = client.post(f"/sessions/{sid}/trajectories/{trajectory_id}/move-to-start")
    assert at_start.status_code == 409 and at_start.json()["code"] == "at_start"
    again = client.post(f"/sessions/{sid}/trajectories/{move_id}/move-to-start")
    assert again.status_code == 409 and again.json()["code"] == "move_of_a_move"
    ran = wait(client, client.post(f"/sessions/{sid}/executions", json=run).json(), timeout_s=120)
    assert ran["state"] == "succeeded", ran


def test_a_run_stopped_with_the_tool_on_the_workpiece_goes_back_by_a_retract_then_a_move(
    arm, fake_ur
):
    """Stopped in its process, the tool on the workpiece: the move to the start first backs
    the tool straight off it along its axis, and the gate, checking the samples here, allows
    the touch at the move's first pose only. Dry-run, run on the arm, and it ends at the
    plan's start."""
    client, sid, trajectory_id, q_start = arm
    rows = client.get(f"/sessions/{sid}/trajectories/{trajectory_id}/csv").text.splitlines()
    header = rows[1].split(",")
    process = [r.split(",") for r in rows[2:] if r.split(",")[header.index("phase")] == "process"]
    q_stopped = np.array(process[len(process) // 2][1:7], dtype=float)
    fake_ur.control("reset", q_rad=q_stopped.tolist())
    time.sleep(0.5)  # the arm's state is read a few times a second
    try:
        job = wait(
            client,
            client.post(f"/sessions/{sid}/trajectories/{trajectory_id}/move-to-start").json(),
        )
        assert job["state"] == "succeeded", job
        move_id = job["result"]["trajectory_id"]
        summary = client.get(f"/sessions/{sid}/trajectories/{move_id}").json()["summary"]
        assert list(summary["phase_durations_s"]) == ["retract", "transit"]
        assert summary["approach_m"] == 0.05
        assert any("first straight off the workpiece: 50 mm" in line for line in summary["report"])
        run = {"trajectory_id": move_id, "backend": "ur_rtde", "confirm": True}
        dry = client.post(f"/sessions/{sid}/executions", json={"trajectory_id": move_id})
        assert wait(client, dry.json())["result"]["completed"]
        moved = wait(client, client.post(f"/sessions/{sid}/executions", json=run).json())
        assert moved["state"] == "succeeded", moved
        q_now = np.array(fake_ur.control("status")["q_rad"])
        assert np.abs(q_now - q_start).max() < 1e-3, np.degrees(q_now - q_start)
    finally:
        fake_ur.control("reset", q_rad=q_start.tolist())


def test_a_move_to_start_through_a_keep_out_box_is_refused_naming_it(arm, fake_ur):
    client, sid, trajectory_id, q_start = arm
    jogged = q_start + [0.6, 0.0, 0.0, 0.0, 0.0, 0.0]  # the base turned 34 degrees away
    fake_ur.control("reset", q_rad=jogged.tolist())
    time.sleep(0.5)
    # A box around where the flange passes halfway between the two poses.
    arm_model = kinematics.model("ur5e")
    halfway = kinematics.forward(arm_model, ((jogged + q_start) / 2)[None])[0, :3, 3]
    box = [*(halfway - 0.05), *(halfway + 0.05)]
    revision = client.get("/cell").json()["revision"]
    edit = {"keep_out_boxes_m": [box], "cell_planes": [], "revision": revision}
    assert client.put("/cell", json=edit).status_code == 200
    try:
        job = wait(
            client,
            client.post(f"/sessions/{sid}/trajectories/{trajectory_id}/move-to-start").json(),
        )
        assert job["state"] == "failed" and job["error"]["code"] == "collision", job
        assert job["error"]["detail"]["obstacle"] == "keep-out box 1"
    finally:
        revision = client.get("/cell").json()["revision"]
        assert client.delete("/cell", params={"revision": revision}).status_code == 200
        fake_ur.control("reset", q_rad=q_start.tolist())


# -- speed override and pause of a run -------------------------------------------------------------


def _robot_until(client, predicate, what: str, timeout_s: float = 30.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while not predicate(shown := client.get("/robot").json()):
        assert time.monotonic() < deadline, f"{what}: {shown.get('run_speed')}"
        time.sleep(0.05)
    return shown


def _plan_samples(client, sid, trajectory_id) -> np.ndarray:
    csv = client.get(f"/sessions/{sid}/trajectories/{trajectory_id}/csv").text
    return np.array([row.split(",")[1:7] for row in csv.strip().splitlines()[2:]], dtype=float)


def test_a_run_paused_rests_on_its_path_and_goes_on_only_when_approved_again(arm, fake_ur):
    client, sid, trajectory_id, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    low, high = _phase_window(client, sid, trajectory_id, "process")
    job = _execute_until(
        client, sid, trajectory_id, progress=0.1 + 0.9 * (low + 0.3 * (high - low))
    )
    execution_id = job["params"]["execution_id"]
    paused = client.post(f"/executions/{execution_id}/pause")
    assert paused.status_code == 200, paused.text
    assert paused.json()["paused"] is True and paused.json()["overridable"] is True
    shown = _robot_until(
        client, lambda r: r["run_speed"] and r["run_speed"]["speed_now"] == 0.0, "never at rest"
    )
    assert shown["owner_execution_id"] == execution_id and shown["run_speed"]["paused"]
    # At rest, on the planned path (the stream holds a point between two planned samples: the
    # servo settles on it), and still the run's: the job runs on.
    time.sleep(0.4)  # the servo's lookahead settles
    q_a = np.array(fake_ur.control("status")["q_rad"])
    time.sleep(0.5)
    q_b = np.array(fake_ur.control("status")["q_rad"])
    assert np.abs(q_b - q_a).max() < 1e-4
    plan = _plan_samples(client, sid, trajectory_id)
    assert np.abs(plan - q_b).max(axis=1).min() < 2e-3
    assert client.get(f"/jobs/{job['id']}").json()["state"] == "running"
    # Going on needs the approval again: the JSON true, and the running plan's checksum.
    sha = client.get(f"/sessions/{sid}/trajectories/{trajectory_id}").json()["sha256"]
    for body, status, code in [
        ({}, 422, None),
        ({"confirm": True}, 422, None),
        ({"confirm": "true", "approved_sha256": sha}, 422, None),
        ({"confirm": False, "approved_sha256": sha}, 409, "not_confirmed"),
        ({"confirm": True, "approved_sha256": "0" * 64}, 409, "approval_mismatch"),
        ({"confirm": True, "approved_sha256": sha, "speed": 2}, 422, None),
    ]:
        refused = client.post(f"/executions/{execution_id}/resume", json=body)
        assert refused.status_code == status, (body, refused.text)
        assert code is None or refused.json()["code"] == code
    time.sleep(0.2)
    assert np.abs(np.array(fake_ur.control("status")["q_rad"]) - q_b).max() < 1e-4
    resumed = client.post(
        f"/executions/{execution_id}/resume", json={"confirm": True, "approved_sha256": sha}
    )
    assert resumed.status_code == 200 and resumed.json()["paused"] is False
    job = wait(client, job, timeout_s=120)
    assert job["state"] == "succeeded", job
    summary = client.get(f"/sessions/{sid}/executions/{execution_id}").json()["summary"]
    # The fake's arm follows the stream in real time and cuts the box's corner a little, more
    # on a loaded machine (3.2 mm measured with both cores busy in a plain run, 5.2 mm with the
    # suite on two workers): a pause or a resume that left the path would be tens of mm.
    assert summary["completed"] and 0 < summary["max_path_deviation_m"] < 8e-3
    # The record holds the pause (more samples than planned) and ends where the plan ends.
    assert summary["n_samples"] > len(plan) + 100
    assert np.abs(np.array(fake_ur.control("status")["q_rad"]) - plan[-1]).max() < 2e-3
    # It has ended: nothing to change any more.
    late = client.post(f"/executions/{execution_id}/speed", json={"fraction": 0.5})
    assert late.status_code == 409 and late.json()["code"] == "not_running"


def test_the_speed_override_slows_the_run_on_its_path(arm, fake_ur):
    client, sid, trajectory_id, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    job = _execute_until(client, sid, trajectory_id, progress=0.15)
    execution_id = job["params"]["execution_id"]
    slowed = client.post(f"/executions/{execution_id}/speed", json={"fraction": 0.5})
    assert slowed.status_code == 200, slowed.text
    assert slowed.json()["speed_fraction"] == 0.5
    _robot_until(
        client,
        lambda r: r["run_speed"] and r["run_speed"]["speed_now"] == 0.5,
        "never at half speed",
    )
    job = wait(client, job, timeout_s=120)
    assert job["state"] == "succeeded", job
    summary = client.get(f"/sessions/{sid}/executions/{execution_id}").json()["summary"]
    plan = _plan_samples(client, sid, trajectory_id)
    # Most of the run at half speed: well over the planned count of samples, on the same path
    # (the bound as for the paused run above).
    assert summary["n_samples"] > 1.5 * len(plan)
    assert summary["completed"] and 0 < summary["max_path_deviation_m"] < 8e-3


@pytest.mark.parametrize(
    "body",
    [
        {},
        {"fraction": 0},
        {"fraction": 0.04},
        {"fraction": 1.01},
        {"fraction": -1},
        {"fraction": "fast"},
        {"fraction": "NaN"},
        {"fraction": "Infinity"},
        {"fraction": 10**400},
        {"fraction": [0.5]},
        {"fraction": 0.5, "paused": False},
        {"fraction": {"a": {"b": {"c": 0.5}}}},
    ],
)
def test_speeds_no_operator_could_set_are_refused_before_any_run_is_looked_up(arm, body):
    client = arm[0]
    refused = client.post("/executions/exe_unknown/speed", json=body)
    assert refused.status_code == 422, refused.text


def test_the_controls_of_a_run_need_the_token_and_a_run_this_instance_drives(arm):
    client = arm[0]
    for path, body in [
        ("speed", {"fraction": 0.5}),
        ("pause", None),
        ("resume", {"confirm": True, "approved_sha256": "0" * 64}),
    ]:
        anonymous = client.post(
            f"/executions/exe_x/{path}", json=body, headers={"Authorization": ""}
        )
        assert anonymous.status_code == 401, anonymous.text
        unknown = client.post(f"/executions/exe_x/{path}", json=body)
        assert unknown.status_code == 404 and "not running on this instance" in unknown.text
    deep = "[" * 5000 + "]" * 5000
    nested = client.post(
        "/executions/exe_x/speed", content=deep, headers={"Content-Type": "application/json"}
    )
    assert nested.status_code in (400, 413, 422), nested.text


def test_a_movepath_run_is_slowed_and_paused_through_the_arms_speed_slider(arm, fake_ur):
    """On the UR arm a movePath run takes the override and the pause too: the service sets the
    controller's speed slider, the safety bar's state follows the controller's scaling (at rest
    when paused), the resume needs the approval again, and the slider is back at the end."""
    client, sid, trajectory_id, q_start = arm
    fake_ur.control("reset", q_rad=q_start.tolist())
    movepath = {"trajectory_id": trajectory_id, "mode": "movepath"}
    dry = client.post(f"/sessions/{sid}/executions", json=movepath)
    assert wait(client, dry.json())["result"]["completed"]
    started = client.post(
        f"/sessions/{sid}/executions", json={**movepath, "backend": "ur_rtde", "confirm": True}
    )
    assert started.status_code == 202, started.text
    job = started.json()
    execution_id = job["params"]["execution_id"]
    _robot_until(client, lambda r: r["run_speed"] and r["run_speed"]["moving"], "never moving")
    slowed = client.post(f"/executions/{execution_id}/speed", json={"fraction": 0.5})
    assert slowed.status_code == 200, slowed.text
    assert slowed.json()["overridable"] is True and slowed.json()["speed_fraction"] == 0.5
    assert _wait_fake(fake_ur, lambda st: st["speed_slider"] == 0.5), "the slider stayed"
    _robot_until(client, lambda r: r["run_speed"]["speed_now"] == 0.5, "the scaling stayed")
    assert client.post(f"/executions/{execution_id}/pause").status_code == 200
    _robot_until(client, lambda r: r["run_speed"]["speed_now"] == 0.0, "never at rest")
    time.sleep(0.4)
    q_a = np.array(fake_ur.control("status")["q_rad"])
    time.sleep(0.5)
    assert np.abs(np.array(fake_ur.control("status")["q_rad"]) - q_a).max() < 1e-4
    assert client.get(f"/jobs/{job['id']}").json()["state"] == "running"
    sha = client.get(f"/sessions/{sid}/trajectories/{trajectory_id}").json()["sha256"]
    resumed = client.post(
        f"/executions/{execution_id}/resume", json={"confirm": True, "approved_sha256": sha}
    )
    assert resumed.status_code == 200, resumed.text
    job = wait(client, job, timeout_s=120)
    assert job["state"] == "succeeded", job
    assert fake_ur.control("status")["speed_slider"] == 1.0  # as the run found it


def _wait_fake(fake_ur, predicate, timeout_s: float = 15.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate(fake_ur.control("status")):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def test_a_movepath_run_refuses_the_override_where_no_slider_reaches_it(arm, tmp_path):
    """A movePath on a backend without the controller's speed slider (the simulated arm) is
    timed where it runs: there is no stream here to slow or pause, and the refusal says so. On
    the ur_rtde backend the slider takes the override (tests/drivers/test_fake_ur.py)."""
    from drivers.robot.clock import FakeClock
    from drivers.robot.sim import SimBackend, SimConfig
    from drivers.robot.ur_rtde import URRtdeBackend, URRtdeConfig
    from service.arm_runner import ExecutionRunner
    from tests.motion_fixtures import line_process

    client = arm[0]
    services = client.app.state.services
    runner = ExecutionRunner(
        services.store,
        "job_none",
        SimBackend(SimConfig(), clock=FakeClock()),
        line_process("ur5e", 0.1),
        lambda *a: None,
        tool=(np.zeros(6), None, np.zeros(3)),
        journal=str(tmp_path / "j.journal"),
        mode="movepath",
    )  # never started: it counts as running (it may still move the arm)
    services.live.executions["exe_movepath"] = runner
    try:
        for path, body in [("speed", {"fraction": 0.5}), ("pause", None)]:
            refused = client.post(f"/executions/exe_movepath/{path}", json=body)
            assert refused.status_code == 409, refused.text
            assert refused.json()["code"] == "not_streamed"
            assert "teach pendant" in refused.json()["message"]
    finally:
        del services.live.executions["exe_movepath"]
    on_ur = ExecutionRunner(
        services.store,
        "job_none",
        URRtdeBackend(URRtdeConfig(host="127.0.0.1")),  # never connected
        line_process("ur5e", 0.1),
        lambda *a: None,
        tool=(np.zeros(6), None, np.zeros(3)),
        journal=str(tmp_path / "k.journal"),
        mode="movepath",
    )
    assert on_ur.overridable
