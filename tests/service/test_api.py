"""The REST API route by route, with its bad inputs: each a clear 4xx that changes nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from tests.service.conftest import AUTH, make_settings, wait


def assert_error(response, status: int, code: str):
    assert response.status_code == status, response.text
    body = response.json()
    assert set(body) == {"code", "message", "detail"} and body["code"] == code, body
    assert "Traceback" not in response.text
    return body


# --- health and auth ---------------------------------------------------------------------------


def test_health_needs_no_token(client):
    response = client.get("/health", headers={"Authorization": ""})
    assert response.status_code == 200
    body = response.json()
    assert body["status"] == "ok" and "toppra" in body["versions"]
    assert body["robot_backends"]["sim"] == "available"


@pytest.mark.parametrize(
    "headers",
    [
        {"Authorization": ""},
        {"Authorization": "Bearer wrong"},
        {"Authorization": "Basic dXNlcjpwYXNz"},
    ],
)
def test_every_other_route_needs_the_token(client, headers):
    response = client.get("/sessions", headers=headers)
    assert_error(response, 401, "unauthorized")
    assert response.headers.get("www-authenticate") == "Bearer"


# --- sessions ----------------------------------------------------------------------------------


def test_session_lifecycle(client):
    created = client.post("/sessions", json={"name": "cell 3"})
    assert created.status_code == 201
    sid = created.json()["id"]
    assert client.get(f"/sessions/{sid}").json()["name"] == "cell 3"
    assert sid in [s["id"] for s in client.get("/sessions").json()]
    assert client.delete(f"/sessions/{sid}").status_code == 204
    assert_error(client.get(f"/sessions/{sid}"), 404, "not_found")
    assert sid not in [s["id"] for s in client.get("/sessions").json()]


@pytest.mark.parametrize("body", [{"name": ""}, {"name": "x" * 201}, {"nom": "typo"}, [1, 2]])
def test_bad_session_bodies(client, body):
    assert_error(client.post("/sessions", json=body), 422, "invalid_request")


def test_unknown_ids_are_404(client, session):
    assert_error(client.get("/sessions/ses_nope"), 404, "not_found")
    assert_error(client.get(f"/sessions/{session}/recordings/rec_nope"), 404, "not_found")
    assert_error(client.get(f"/sessions/{session}/reconstructions/rcn_nope"), 404, "not_found")
    assert_error(client.get("/jobs/job_nope"), 404, "not_found")
    assert_error(client.post("/executions/exe_nope/stop"), 404, "not_found")


@pytest.mark.parametrize(
    "matrix", [np.eye(3).tolist(), np.diag([2.0, 1, 1, 1]).tolist(), [[1, 0, 0, float("nan")]] * 4]
)
def test_bad_calibration(client, session, matrix):
    before = client.get(f"/sessions/{session}").json()["T_base_tracker"]
    body = json.dumps({"T_base_tracker": matrix}, allow_nan=True)
    response = client.put(
        f"/sessions/{session}/calibration",
        content=body,
        headers={**AUTH, "Content-Type": "application/json"},
    )
    assert_error(response, 422, "invalid_request")
    assert client.get(f"/sessions/{session}").json()["T_base_tracker"] == before


# --- uploads -----------------------------------------------------------------------------------


def test_uploads_become_the_sessions_inputs(client, session):
    s = client.get(f"/sessions/{session}").json()
    recording = client.get(f"/sessions/{session}/recordings/{s['recording_id']}").json()
    assert recording["summary"]["n_samples"] > 100 and recording["params"]["units"] == "m"
    scan = client.get(f"/sessions/{session}/scans/{s['scan_id']}").json()
    assert scan["summary"]["n_points"] > 1000
    csv_text = client.get(f"/sessions/{session}/recordings/{s['recording_id']}/csv").text
    assert csv_text.splitlines()[0] == "t,x,y,z"
    ply = client.get(f"/sessions/{session}/scans/{s['scan_id']}/ply").content
    assert ply.startswith(b"ply")


BAD_TRACES = [
    ("trace.csv", b"a,b\n1,2\n", "invalid_file"),
    ("trace.csv", b"x,y,z\n0,0,0\nnan,0,0\n0.01,0,0\n", "invalid_file"),
    ("trace.csv", b"x,y,z\n0,0,0\n100,0,0\n", "units_mismatch"),
    ("trace.trc", b"whatever", "unknown_format"),
    ("trace.csv", b"\xff\xfe\x00", "invalid_file"),
    ("trace.c3d", b"whatever", "invalid_file"),
]


@pytest.mark.parametrize(
    "name, content, code",
    BAD_TRACES,
    ids=["no-columns", "nan", "mm-as-m", "unknown-format", "binary", "not-c3d"],
)
def test_bad_recordings_are_refused_and_change_nothing(client, session, name, content, code):
    before = client.get(f"/sessions/{session}").json()
    count = len(client.get(f"/sessions/{session}/recordings").json())
    response = client.put(f"/sessions/{session}/recording", files={"file": (name, content)})
    body = assert_error(response, 422, code)
    assert body["message"]
    assert client.get(f"/sessions/{session}").json() == before
    assert len(client.get(f"/sessions/{session}/recordings").json()) == count


@pytest.mark.parametrize(
    "name, content, code",
    [
        ("scan.ply", b"not a ply", "invalid_file"),
        ("scan.xyz", b"nan nan nan\n", "invalid_file"),
        ("scan.obj", b"v 1 2 3\n", "unknown_format"),
    ],
    ids=["corrupt-ply", "nan", "unknown-format"],
)
def test_bad_scans_are_refused_and_change_nothing(client, session, name, content, code):
    before = client.get(f"/sessions/{session}").json()
    assert_error(
        client.put(f"/sessions/{session}/scan", files={"file": (name, content)}), 422, code
    )
    assert client.get(f"/sessions/{session}").json() == before


def _cylinder_xyz_mm() -> bytes:
    """A 170 mm tall, 60 mm wide cylinder's surface, its numbers in millimetres."""
    angle, height = np.meshgrid(np.linspace(0, 2 * np.pi, 90), np.linspace(0, 170, 60))
    points = np.c_[30 * np.cos(angle).ravel(), 30 * np.sin(angle).ravel(), height.ravel()]
    return "".join(f"{x:.3f} {y:.3f} {z:.3f}\n" for x, y, z in points).encode()


def test_a_scan_in_millimetres_read_as_metres_is_refused_at_upload(client):
    """It was accepted (Inputs done, a 170 m cylinder) and failed only at Reconstruct."""
    session = client.post("/sessions", json={"name": "units"}).json()["id"]  # its own scan
    before = client.get(f"/sessions/{session}").json()
    response = client.put(
        f"/sessions/{session}/scan", files={"file": ("part.xyz", _cylinder_xyz_mm())}
    )
    body = assert_error(response, 422, "units_mismatch")
    assert "look like millimetres" in body["message"] and "units=mm" in body["message"]
    assert client.get(f"/sessions/{session}").json() == before
    response = client.put(
        f"/sessions/{session}/scan",
        files={"file": ("part.xyz", _cylinder_xyz_mm())},
        data={"units": "mm"},
    )
    assert response.status_code in (200, 201), response.text


def test_oversize_upload_is_413_and_changes_nothing(client, session):
    before = client.get(f"/sessions/{session}").json()
    big = b"x,y,z\n" + b"0.1,0.2,0.3\n" * 600_000  # about 7 MB, the limit is 5 MB
    assert_error(
        client.put(f"/sessions/{session}/recording", files={"file": ("big.csv", big)}),
        413,
        "upload_too_large",
    )
    assert client.get(f"/sessions/{session}").json() == before


def test_upload_without_a_file_field(client, session):
    assert_error(
        client.put(f"/sessions/{session}/recording", files={"data": ("t.csv", b"x,y,z\n")}),
        422,
        "invalid_request",
    )


def test_upload_to_an_unknown_session(client, scene_files):
    assert_error(
        client.put(
            "/sessions/ses_nope/recording", files={"file": ("trace.csv", scene_files["trace"])}
        ),
        404,
        "not_found",
    )


# --- the flow: reconstruct, compare, plan, dry run ---------------------------------------------


@pytest.fixture(scope="module")
def reconstruction(client, session):
    job = client.post(f"/sessions/{session}/reconstructions", json={})
    assert job.status_code == 202
    job = wait(client, job.json())
    assert job["state"] == "succeeded", job
    return job["result"]["reconstruction_id"]


def test_reconstruction_keeps_its_inputs_and_parameters(client, session, reconstruction):
    body = client.get(f"/sessions/{session}/reconstructions/{reconstruction}").json()
    s = client.get(f"/sessions/{session}").json()
    assert body["inputs"] == {"recording_id": s["recording_id"], "scan_id": s["scan_id"]}
    assert body["params"]["alpha"] == "auto" and body["params"]["method"] == "anchored"
    assert body["summary"]["modes"]["edge"] > 100
    assert body["summary"]["registration"]["target"] == "edge"
    csv_lines = client.get(f"/sessions/{session}/reconstructions/{reconstruction}/csv").text
    assert csv_lines.startswith("x,y,z,t,")
    png = client.get(f"/sessions/{session}/reconstructions/{reconstruction}/preview.png")
    assert png.headers["content-type"] == "image/png" and png.content[:4] == b"\x89PNG"


def test_several_reconstructions_can_be_compared(client, session, reconstruction):
    job = wait(
        client,
        client.post(
            f"/sessions/{session}/reconstructions", json={"method": "paper", "alpha": 0.5}
        ).json(),
    )
    assert job["state"] == "succeeded"
    listed = client.get(f"/sessions/{session}/reconstructions").json()
    methods = {r["id"]: r["params"]["method"] for r in listed}
    assert methods[reconstruction] == "anchored"
    assert methods[job["result"]["reconstruction_id"]] == "paper"


@pytest.mark.parametrize(
    "body",
    [
        {"alpha": 2},
        {"alpha": "sometimes"},
        {"degree": 0},
        {"radius_m": -1},
        {"method": "magic"},
        {"unknown": 1},
    ],
)
def test_bad_reconstruction_parameters(client, session, body):
    assert_error(
        client.post(f"/sessions/{session}/reconstructions", json=body), 422, "invalid_request"
    )


def test_reconstruction_needs_a_recording(client):
    sid = client.post("/sessions", json={"name": "empty"}).json()["id"]
    assert_error(client.post(f"/sessions/{sid}/reconstructions", json={}), 409, "no_recording")


def test_a_scan_far_from_the_path_fails_the_job_with_a_reason(client, scene_files):
    sid = client.post("/sessions", json={"name": "far"}).json()["id"]
    client.put(f"/sessions/{sid}/recording", files={"file": ("trace.csv", scene_files["trace"])})
    far = "\n".join(f"{x} {y} 5.0" for x, y in np.random.default_rng(0).uniform(0, 1, (500, 2)))
    assert (
        client.put(f"/sessions/{sid}/scan", files={"file": ("far.xyz", far.encode())}).status_code
        == 201
    )
    job = wait(client, client.post(f"/sessions/{sid}/reconstructions", json={}).json())
    assert job["state"] == "failed"
    assert job["error"]["code"] in ("no_overlap", "units_mismatch")
    assert client.get(f"/sessions/{sid}/reconstructions").json() == []


@pytest.fixture(scope="module")
def trajectory(client, session, reconstruction):
    job = client.post(
        f"/sessions/{session}/trajectories",
        json={"reconstruction_id": reconstruction, "robot": "ur5e", "speed_m_s": 0.05},
    )
    assert job.status_code == 202, job.text
    job = wait(client, job.json())
    assert job["state"] == "succeeded", job
    return job["result"]["trajectory_id"]


def test_trajectory_has_its_feasibility_report(client, session, trajectory):
    body = client.get(f"/sessions/{session}/trajectories/{trajectory}").json()
    summary = body["summary"]
    assert summary["robot"] == "ur5e" and summary["rate_hz"] == pytest.approx(500)
    assert summary["tool_axis_from"] == "scan"
    assert summary["min_limit_margin_rad"] > 0 and any(
        "margins" in line for line in summary["report"]
    )
    csv_text = client.get(f"/sessions/{session}/trajectories/{trajectory}/csv").text
    lines = csv_text.splitlines()
    # The file says what it is, then the contracted columns and each sample's phase.
    assert lines[0].startswith("# teachpath: ")
    meta = json.loads(lines[0][len("# teachpath: ") :])
    assert meta["robot"] == "ur5e" and meta["rate_hz"] == pytest.approx(500)
    assert meta["tcp_pose"] == summary["tcp_pose"] and meta["configuration"]
    assert any("collision" in check for check in meta["checks"])
    assert lines[1] == "t,q0,q1,q2,q3,q4,q5,x,y,z,rx,ry,rz,phase"
    phases = [line.rsplit(",", 1)[1] for line in lines[2:]]
    assert phases[0] == "transit" and phases[-1] == "retract"
    assert list(dict.fromkeys(phases)) == ["transit", "approach", "process", "retract"]
    # Summary: the phases' durations, where it starts, what it passed.
    assert set(summary["phase_durations_s"]) == {"transit", "approach", "process", "retract"}
    assert summary["start_from"] == "home" and summary["min_clearance_m"] > 0


@pytest.mark.parametrize(
    "change, status, code",
    [
        ({"robot": "kuka"}, 422, "invalid_value"),
        ({"speed_m_s": 5}, 422, "invalid_request"),
        ({"reconstruction_id": "rcn_nope"}, 404, "not_found"),
        ({"T_base_tracker": [[1, 0, 0, 0]]}, 422, "invalid_request"),
    ],
)
def test_bad_trajectory_requests(client, session, reconstruction, change, status, code):
    body = {"reconstruction_id": reconstruction, "speed_m_s": 0.05, **change}
    assert_error(client.post(f"/sessions/{session}/trajectories", json=body), status, code)


def _plan_at(client, session, reconstruction, T_base_tracker) -> dict:
    return wait(
        client,
        client.post(
            f"/sessions/{session}/trajectories",
            json={
                "reconstruction_id": reconstruction,
                "speed_m_s": 0.05,
                "T_base_tracker": T_base_tracker,
            },
        ).json(),
    )


def test_an_unreachable_placement_fails_the_job_naming_the_waypoint(
    client, session, reconstruction
):
    far = np.eye(4)
    far[0, 3] = 2.0  # two metres in front of a UR5e: out of reach
    job = _plan_at(client, session, reconstruction, far.tolist())
    assert job["state"] == "failed"
    assert job["error"]["code"] == "infeasible_trajectory"
    assert "waypoint" in job["error"]["message"]


def test_a_workpiece_inside_the_arm_fails_the_job_naming_where_it_collides(
    client, session, reconstruction
):
    # The workpiece on the table where the arm's base stands, 5 cm out so that the path itself
    # stays reachable (right over the base's axis it passes the shoulder singularity first).
    at_base = np.eye(4)
    at_base[0, 3] = 0.05
    job = _plan_at(client, session, reconstruction, at_base.tolist())
    assert job["state"] == "failed" and job["error"]["code"] == "collision", job["error"]
    detail = job["error"]["detail"]
    assert detail["link"] == "base" and detail["obstacle"] == "scan"
    assert detail["phase"] == "transit" and detail["clearance_m"] < 0
    assert "base touches the scan" in job["error"]["message"]


@pytest.fixture(scope="module")
def dry_run(client, session, trajectory):
    job = client.post(f"/sessions/{session}/executions", json={"trajectory_id": trajectory})
    assert job.status_code == 202
    job = wait(client, job.json())
    assert job["state"] == "succeeded", job
    return job["result"]["execution_id"]


def test_dry_run_report(client, session, dry_run):
    body = client.get(f"/sessions/{session}/executions/{dry_run}").json()
    assert body["params"] == {
        "backend": "sim",
        "dry_run": True,
        "mode": "servoj",
        "tolerance_m": 5e-4,
    }
    assert body["summary"]["completed"] and not body["summary"]["faults"]
    assert body["summary"]["max_path_deviation_m"] < 1e-3
    csv_text = client.get(f"/sessions/{session}/executions/{dry_run}/csv").text
    assert csv_text.startswith("t,q0_planned")


def test_every_artifact_of_a_session_with_its_typed_summary(client, session, dry_run):
    artifacts = client.get(f"/sessions/{session}/artifacts").json()
    kinds = [a["kind"] for a in artifacts]
    assert {"recording", "scan", "reconstruction", "trajectory", "execution"} <= set(kinds)
    assert [a["created_at"] for a in artifacts] == sorted(a["created_at"] for a in artifacts)
    by_kind = {a["kind"]: a for a in artifacts}
    # Each kind reports its own summary, as the OpenAPI spec says (a union told apart by kind).
    assert by_kind["execution"]["summary"]["backend"] == "sim"
    assert by_kind["trajectory"]["summary"]["rate_hz"] == pytest.approx(500)
    assert by_kind["reconstruction"]["summary"]["modes"]["edge"] > 0
    spec = client.get("/openapi.json").json()
    schema = spec["paths"]["/sessions/{session_id}/artifacts"]["get"]["responses"]["200"]
    items = schema["content"]["application/json"]["schema"]["items"]
    assert items["discriminator"]["propertyName"] == "kind"
    # Every kind this session has, and the touches it has not.
    assert set(items["discriminator"]["mapping"]) == set(by_kind) | {"touches"}


def test_real_arm_execution_is_refused_without_a_configured_arm(client, session, trajectory):
    assert_error(
        client.post(
            f"/sessions/{session}/executions",
            json={"trajectory_id": trajectory, "backend": "ur_rtde", "confirm": True},
        ),
        409,
        "no_robot",
    )


def test_bad_execution_modes(client, session, trajectory):
    for body in (
        {"mode": "teleport"},
        {"mode": "movepath", "tolerance_m": 0},
        {"mode": "movepath", "tolerance_m": 0.5},
    ):
        assert_error(
            client.post(
                f"/sessions/{session}/executions", json={"trajectory_id": trajectory, **body}
            ),
            422,
            "invalid_request",
        )


def test_unknown_backend(client, session, trajectory):
    assert_error(
        client.post(
            f"/sessions/{session}/executions", json={"trajectory_id": trajectory, "backend": "kuka"}
        ),
        422,
        "invalid_request",
    )


# --- jobs --------------------------------------------------------------------------------------


def test_job_events_stream_until_finished(client, session, reconstruction):
    job = client.post(f"/sessions/{session}/reconstructions", json={"radius_m": 0.01}).json()
    with client.stream("GET", f"/jobs/{job['id']}/events") as stream:
        assert stream.headers["content-type"].startswith("text/event-stream")
        states = [
            json.loads(line[6:])["state"]
            for line in stream.iter_lines()
            if line.startswith("data: ")
        ]
    assert states[-1] == "succeeded" and states[0] in ("queued", "running")


def test_finished_jobs_cannot_be_cancelled(client, session, reconstruction):
    job = client.get(f"/sessions/{session}/jobs").json()[0]
    assert job["state"] in ("succeeded", "failed")
    assert_error(client.post(f"/jobs/{job['id']}/cancel"), 409, "job_finished")


# --- captures ----------------------------------------------------------------------------------


def test_replay_capture_becomes_a_recording(client, session):
    s = client.get(f"/sessions/{session}").json()
    source = client.get(f"/sessions/{session}/recordings/{s['recording_id']}").json()
    capture = client.post(
        f"/sessions/{session}/captures",
        json={"source": {"kind": "replay", "recording_id": s["recording_id"], "speed": 20.0}},
    )
    assert capture.status_code == 201
    cid = capture.json()["id"]
    for _ in range(200):
        body = client.get(f"/sessions/{session}/captures/{cid}").json()
        if body["state"] != "running":
            break
        import time

        time.sleep(0.1)
    assert body["state"] == "stopped", body
    recording = client.get(f"/sessions/{session}/recordings/{body['recording_id']}").json()
    assert recording["inputs"] == {"capture_id": cid}
    assert recording["summary"]["n_samples"] == source["summary"]["n_samples"]
    assert client.get(f"/sessions/{session}").json()["recording_id"] == body["recording_id"]


def test_stopping_a_capture_keeps_what_arrived(client, session):
    s = client.get(f"/sessions/{session}").json()
    cid = client.post(
        f"/sessions/{session}/captures",
        json={"source": {"recording_id": s["recording_id"], "speed": 1.0}},
    ).json()["id"]
    import time

    time.sleep(0.6)
    body = client.post(f"/sessions/{session}/captures/{cid}/stop").json()
    assert body["state"] == "stopped" and body["recording_id"]
    recording = client.get(f"/sessions/{session}/recordings/{body['recording_id']}").json()
    assert recording["summary"]["n_samples"] > 10


def test_capture_of_an_unknown_recording(client, session):
    assert_error(
        client.post(f"/sessions/{session}/captures", json={"source": {"recording_id": "rec_nope"}}),
        404,
        "not_found",
    )


# --- persistence -------------------------------------------------------------------------------


def test_a_restart_keeps_everything_and_fails_interrupted_jobs(tmp_path, scene_files):
    settings = make_settings(tmp_path)
    with TestClient(create_app(settings), headers=AUTH) as first:
        sid = first.post("/sessions", json={"name": "kept"}).json()["id"]
        first.put(f"/sessions/{sid}/recording", files={"file": ("trace.csv", scene_files["trace"])})
        ctx = first.app.state.services
        stuck = ctx.store.create_job(sid, "reconstruction", {})
        ctx.store.update_job(stuck.id, state="running")
    with TestClient(create_app(settings), headers=AUTH) as second:
        assert second.get(f"/sessions/{sid}").json()["name"] == "kept"
        assert second.get(f"/sessions/{sid}/recordings").json()[0]["summary"]["n_samples"] > 0
        job = second.get(f"/jobs/{stuck.id}").json()
        assert job["state"] == "failed" and job["error"]["code"] == "interrupted"


def test_the_generated_token_is_private(tmp_path):
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path)
    token = settings.access_token()
    assert len(token) >= 24 and (tmp_path / "token").stat().st_mode & 0o777 == 0o600
    assert settings.access_token() == token


@pytest.mark.parametrize(
    "body, where",
    [
        ({"alpha": -1}, "alpha"),  # a number or "auto": was "body.alpha.constrained-float"
        ({"alpha": "often"}, "alpha"),
        ({"radius_m": "x"}, "radius_m"),
        ({"recording_ids": [1]}, "recording_ids.0"),
    ],
)
def test_validation_errors_name_the_field_as_typed(client, session, body, where):
    response = client.post(f"/sessions/{session}/reconstructions", json=body)
    error = assert_error(response, 422, "invalid_request")
    assert error["message"].startswith(f"{where}: "), error["message"]
    for noise in ("body.", "constrained", "literal[", "function-"):
        assert noise not in error["message"], error["message"]
    assert all(not p["where"].startswith("body") for p in error["detail"])
