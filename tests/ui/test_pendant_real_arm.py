"""The pendant with a real arm: the server drives the fake UR controller
(``drivers.robot.fake_ur``) on loopback, and the operator runs a plan on it from the browser,
stops it mid-path with the Escape key, watches a second pendant see the arm owned (its Run on
arm disabled, its Stop shown), and clears a protective stop with Unlock.
"""

from __future__ import annotations

import json
import re
import time

import numpy as np
import pytest
from playwright.sync_api import expect

from tests.drivers import fake_ur_fixture
from tests.server_process import Server
from tests.ui.conftest import TOKEN, pendant_for

fake_ur_process = fake_ur_fixture.fake_ur_process

pytestmark = pytest.mark.timeout(600)

#: The server's speed cap for the real arm (m/s): the slider stops there.
CAP_M_S = 0.1


@pytest.fixture(scope="module")
def arm_server(tmp_path_factory, fake_ur_process):
    server = Server(
        tmp_path_factory.mktemp("ui-real-arm"),
        token=TOKEN,
        demo=True,
        timeout_s=30,
        settings={
            "TEACHPATH_UR_HOST": fake_ur_process.host,
            "TEACHPATH_UR_ROBOT": "ur5e",
            "TEACHPATH_MAX_SPEED_M_S": str(CAP_M_S),
            "TEACHPATH_UR_WATCHDOG_HZ": str(fake_ur_fixture.SERVICE_WATCHDOG_HZ),
            "TEACHPATH_UR_STALE_AFTER_S": str(fake_ur_fixture.SERVICE_STALE_AFTER_S),
            # A cabinet beside the arm and the floor under the table: far from the demo's
            # motion, drawn in the 3-D view.
            "TEACHPATH_KEEP_OUT_BOXES": "[[0.0, 0.7, 0.0, 0.2, 0.9, 0.3]]",
            "TEACHPATH_CELL_PLANES": "[[0.0, 0.0, 1.0, -0.5]]",
        },
    )
    yield server
    server.stop()


def client_plan(server: Server) -> dict:
    """The demo session's newest plan, as the server lists it."""
    (demo,) = [s for s in server.client.get("/sessions").json() if s["name"] == "demo"]
    return server.client.get(f"/sessions/{demo['id']}/trajectories").json()[-1]


def _robot_at_rest(client, timeout_s: float = 30.0) -> None:
    """Wait until the owning run stands paused at rest on its path."""
    deadline = time.monotonic() + timeout_s
    while True:
        run = client.get("/robot").json()["run_speed"]
        if run and run["paused"] and run["speed_now"] == 0.0:
            return
        assert time.monotonic() < deadline, f"the run did not come to rest: {run}"
        time.sleep(0.05)


def _joints(fake) -> np.ndarray:
    return np.array(fake.control("status")["q_rad"])


def _progress(page, form: str) -> float:
    return float(page.locator(f"{form} progress").evaluate("bar => bar.value"))


def _job_progress(client, sid: str, execution_id: str) -> float:
    """An execution's progress as the server has it (its job's)."""
    (job,) = [
        j
        for j in client.get(f"/sessions/{sid}/jobs").json()
        if j["kind"] == "execution" and j["params"].get("execution_id") == execution_id
    ]
    return float(job["progress"])


def test_run_on_the_arm_stopped_mid_path_with_escape_and_seen_from_a_second_pendant(
    browser, arm_server, fake_ur_process, screens
):
    fake = fake_ur_process
    fake.control("reset")
    with pendant_for(browser, arm_server, screens, "real-arm") as pendant:
        page = pendant.page
        pendant.open()
        expect(page.locator("#arm-kind")).to_have_text("REAL ARM")
        expect(page.locator("#robot-model")).to_have_text(f"ur5e @ {fake.host}")
        expect(page.locator("#robot-mode")).to_have_text("RUNNING")
        expect(page.locator("#remote-control")).to_have_text("on")
        expect(page.locator("#speed-cap")).to_have_text("100 mm/s")
        page.get_by_role("button", name="demo", exact=True).click()
        # The cell's keep-out box (12 edges) and plane (a grid of 5 + 5 lines) are drawn; the
        # calibration lines name them.
        expect(page.locator("#workspace")).to_have_attribute("data-cell", "22")
        expect(page.locator("#calibration-current tr", has_text="cell")).to_contain_text(
            "1 keep-out box, 1 plane besides the mounting one"
        )
        page.get_by_role("button", name="Reconstruct").click()
        expect(page.locator("#reconstruct-summary")).to_contain_text(
            "max displacement", timeout=90_000
        )
        expect(page.locator("#legend-displacement")).to_be_visible()
        # The plan starts where the arm is (the service reads its joints), at a slow speed so
        # that the run lasts long enough to be stopped in the middle.
        expect(page.locator("#plan-speed")).to_have_attribute("max", str(CAP_M_S))
        page.locator("#plan-speed").fill("0.02")
        page.get_by_role("button", name="Plan", exact=True).click()
        summary = page.locator("#plan-summary")
        expect(summary.locator("tr[data-phase=process]")).to_be_visible(timeout=60_000)
        expect(summary).to_contain_text("the arm's joints")
        expect(summary.locator(".report")).to_contain_text("starts from arm [0.0, -90.0")
        page.get_by_role("button", name="Dry run").click()
        expect(page.locator("#dryrun-summary")).to_contain_text("passed", timeout=120_000)

        # Run on arm: behind a confirmation that names the real arm, the speed and the phases.
        run = page.get_by_role("button", name="Run on arm")
        expect(run).to_be_enabled()
        expect(page.locator("#run-speed")).to_be_hidden()  # no run owns the arm yet
        run.click()
        dialog = page.locator("#confirm-dialog")
        expect(dialog).to_be_visible()
        expect(dialog).to_contain_text(f"REAL ARM ur5e @ {fake.host}")
        expect(dialog).to_contain_text("20 mm/s")
        expect(dialog.locator("th", has_text="approach").first).to_be_visible()
        # What the plan was made from, with checksums: the approval names the file that runs.
        expect(dialog).to_contain_text("plan file")
        for name in ("trace", "scan"):
            row = dialog.locator("tr").filter(has=page.locator("th").get_by_text(name, exact=True))
            expect(row).to_contain_text("sha256")
        # A plan of the current inputs: nothing in the confirmation is styled as a warning.
        expect(dialog.locator("tr.warning")).to_have_count(0)
        # Every phase with its duration and fastest TCP speed, never above the cap; the TCP in
        # mm and degrees and the payload, as a PolyScope operator checks them.
        rows = dict(
            page.locator("#confirm-table tr").evaluate_all(
                "(rows) => rows.map((r) => [r.cells[0].textContent, r.cells[1].textContent])"
            )
        )
        plan = client_plan(arm_server)
        fastest_by_phase = plan["summary"]["phase_max_tcp_speed_m_s"]
        assert {"transit", "approach", "process", "retract"} <= set(fastest_by_phase)
        for phase, fastest in fastest_by_phase.items():
            assert fastest <= CAP_M_S + 1e-9, (phase, fastest)
            shown_mm_s = int(np.floor(fastest * 1000 + 0.5))  # as the page rounds (Math.round)
            assert rows[f"  {phase}"].endswith(f"TCP up to {shown_mm_s} mm/s"), rows
        tcp = plan["summary"]["tcp_pose"]
        assert re.fullmatch(
            rf"x {tcp[0] * 1000:.1f}, y {tcp[1] * 1000:.1f}, z {tcp[2] * 1000:.1f} mm; "
            r"rx [-\d.]+, ry [-\d.]+, rz [-\d.]+ deg",
            rows["TCP"],
        ), rows["TCP"]
        assert tcp[2] > 0.05  # the plan's tool, not a flange at 0, 0, 0
        assert rows["payload"].startswith("not set by the plan: the controller's"), rows
        pendant.shot("confirm")
        q_before = _joints(fake)
        # Cancelling sends nothing; the run is asked for again.
        dialog.get_by_role("button", name="Cancel").click()
        expect(dialog).to_be_hidden()
        expect(page.locator("#arm-owner")).to_have_text("none")
        run.click()
        expect(dialog).to_be_visible()
        page.get_by_role("button", name="Confirm: run on arm").click()
        stop = page.get_by_role("button", name="Stop")
        expect(stop).to_be_visible()
        expect(page.locator("#stop-hint")).to_have_text("Esc = Stop")
        expect(page.locator("#step-run .needs")).to_have_text(
            "The arm is moving: press Stop (or Esc) to stop it at once."
        )
        expect(run).to_be_disabled()
        expect(page.locator("#arm-owner")).to_have_text(re.compile(r"^exe_"))
        owner = page.locator("#arm-owner").inner_text()

        # A second pendant sees the arm owned: in another session it cannot run, and says why;
        # on this session it follows the run too. Both can stop it.
        with pendant_for(browser, arm_server, screens, "real-arm-second") as second:
            other = second.page
            second.open()
            second.create_session("other cell job")
            expect(other.locator("#arm-owner")).to_have_text(owner)
            expect(other.get_by_role("button", name="Stop")).to_be_visible()
            expect(other.get_by_role("button", name="Run on arm")).to_be_disabled()
            expect(other.locator("#step-run .needs")).to_have_text(
                f"The arm is busy: execution {owner} owns it. Wait until it ends, or press Stop."
            )
            second.shot("arm-owned")
            other.get_by_role("button", name="demo", exact=True).click()
            expect(other.locator("#step-run .needs")).to_have_text(
                "The arm is moving: press Stop (or Esc) to stop it at once."
            )
            expect(other.locator("#run-form .job-state")).to_contain_text("running")
            expect(other.get_by_role("button", name="Run on arm")).to_be_disabled()

        # Mid-path, Escape stops the arm: a fifth of the way in, so that a loaded machine (two
        # shared cores, the fake controller in real time beside the browser) still has 16 s of
        # the 20 s run left for the stop to land.
        deadline = time.monotonic() + 120
        while _progress(page, "#run-form") < 0.2:
            assert time.monotonic() < deadline, "the run did not get a fifth of the way"
            time.sleep(0.05)
        assert np.abs(_joints(fake) - q_before).max() > 1e-3  # the arm has moved
        # The 3-D view draws the arm where it is now, following the controller's state.
        drawn = page.locator("#workspace").get_attribute("data-live-arm")
        page.wait_for_function(
            "(before) => document.querySelector('#workspace').dataset.liveArm !== before",
            arg=drawn,
            timeout=10_000,
        )
        tcp_now = np.array(json.loads(page.locator("#workspace").get_attribute("data-live-arm")))
        tcp_server = np.array(arm_server.client.get("/robot").json()["tcp_pose"][:3])
        # Read apart while the transit moves the tool at up to the 100 mm/s cap (54 mm apart
        # once on a loaded machine): within a second's travel.
        assert np.linalg.norm(tcp_now - tcp_server) < CAP_M_S * 1.0
        pendant.shot("running")

        # The bar while a run shows its speed and Stop: one line on a desk's screen; on a
        # cell's touch panel, the arm's state above and the run's controls with Stop below.
        def row_top(selector: str) -> float:
            box = page.locator(selector).bounding_box()
            return box["y"] + box["height"] / 2

        page.set_viewport_size({"width": 1920, "height": 1080})
        expect(page.locator("#run-speed")).to_be_visible()
        centres = [row_top(f) for f in ("#arm-kind", "#speed-cap", "#run-speed", "#stop")]
        assert max(centres) - min(centres) < 12, centres
        page.set_viewport_size({"width": 1280, "height": 800})
        assert abs(row_top("#arm-kind") - row_top("#speed-cap")) < 12
        assert abs(row_top("#run-speed") - row_top("#stop")) < 12
        assert row_top("#stop") > row_top("#speed-cap") + 20
        assert page.locator("#safety-bar").bounding_box()["height"] < 110
        page.set_viewport_size({"width": 1500, "height": 1100})

        # Pause: the arm comes to rest on its path and holds; the bar says so. Resuming is
        # approved again in a dialog that names the plan's file; cancelling it keeps the pause.
        speed_state = page.locator("#run-speed-state")
        expect(speed_state).to_have_text("at 100 %")
        page.get_by_role("button", name="Pause").click()
        expect(speed_state).to_have_text("PAUSED, at rest on the path", timeout=15_000)
        # The servo's lookahead settles (longer on a loaded machine): then the arm holds still.
        deadline = time.monotonic() + 10
        q_paused = _joints(fake)
        while True:
            page.wait_for_timeout(300)
            q_previous, q_paused = q_paused, _joints(fake)
            if np.abs(q_paused - q_previous).max() < 1e-5:
                break
            assert time.monotonic() < deadline, "the arm did not come to rest when paused"
        page.wait_for_timeout(600)
        assert np.abs(_joints(fake) - q_paused).max() < 1e-4
        progress_paused = _progress(page, "#run-form")
        expect(page.locator("#step-run .needs")).to_contain_text("The run is paused")
        pendant.shot("paused")
        resume = page.get_by_role("button", name="Resume…")
        resume.click()
        expect(dialog).to_be_visible()
        expect(page.locator("#confirm-title")).to_have_text("Resume the run on the arm?")
        sha = arm_server.client.get("/robot").json()["run_speed"]["approved_sha256"]
        expect(dialog.locator("tr", has_text="plan file")).to_contain_text(f"sha256 {sha[:12]}")
        expect(dialog.locator("tr", has_text="speed")).to_contain_text("100 % of the plan's speed")
        pendant.shot("confirm-resume")
        dialog.get_by_role("button", name="Cancel").click()
        page.wait_for_timeout(300)
        assert np.abs(_joints(fake) - q_paused).max() < 1e-4
        expect(speed_state).to_have_text("PAUSED, at rest on the path")
        # The speed is set while paused (typed, with a comma), and the run goes on at it.
        speed_field = page.locator("#run-speed-value")
        speed_field.fill("2")
        speed_field.press("Enter")
        expect(page.locator("#banner")).to_contain_text("type 5 to 100")
        assert arm_server.client.get("/robot").json()["run_speed"]["speed_fraction"] == 1.0
        speed_field.fill("50,0")
        speed_field.press("Enter")
        expect(page.locator("#run-speed-slider")).to_have_value("50")
        expect(page.locator("#banner")).to_be_hidden()
        resume.click()
        expect(dialog.locator("tr", has_text="speed")).to_contain_text("50 % of the plan's speed")
        page.get_by_role("button", name="Confirm: resume").click()
        expect(speed_state).to_have_text("at 50 %", timeout=15_000)
        expect(page.get_by_role("button", name="Pause")).to_be_visible()
        expect(page.locator("#step-run .needs")).to_have_text(
            "The arm is moving: press Stop (or Esc) to stop it at once."
        )
        # It goes on: the page's progress and the arm itself (a slow stretch of the path turns
        # the joints by less than a milliradian per 1 % of the run: each is waited for).
        deadline = time.monotonic() + 30
        while (
            _progress(page, "#run-form") <= progress_paused + 0.01
            or np.abs(_joints(fake) - q_paused).max() <= 1e-3
        ):
            assert time.monotonic() < deadline, "the run did not go on after the resume"
            time.sleep(0.05)
        pendant.shot("half-speed")
        # Where the process (the tool on the workpiece) runs, as the run's progress bar shows
        # it (a tenth for the start, then the plan's samples sent): the stop below lands there.
        sid = page.evaluate("sessionStorage.getItem('teachpath.session')")
        client = arm_server.client
        plan_id = client.get(f"/sessions/{sid}/trajectories").json()[-1]["id"]
        rows = client.get(f"/sessions/{sid}/trajectories/{plan_id}/csv").text.splitlines()
        column = rows[1].split(",").index("phase")
        phases = [row.split(",")[column] for row in rows[2:]]
        in_process = [i for i, phase in enumerate(phases) if phase == "process"]
        process_from, process_to = (
            0.1 + 0.9 * in_process[0] / (len(phases) - 1),
            0.1 + 0.9 * in_process[-1] / (len(phases) - 1),
        )
        # The least speed from here on, before the process, so that the stop below lands at the
        # same point of it however long a loaded machine takes over the presses (run at half
        # speed, a busy machine saw the process end before the stop; stopped later in it, the
        # straight retract passes inside the scan's margin and the move back is refused).
        # Where the run is, from the server (the page's bar follows it a moment later: on a
        # loaded machine that moment let the run pass the process before the stop below).
        deadline = time.monotonic() + 120
        while _job_progress(client, sid, owner) < process_from - 0.03:  # the approach's start
            assert time.monotonic() < deadline, "the run did not reach its approach"
            time.sleep(0.05)
        client.post(f"/executions/{owner}/speed", json={"fraction": 0.05}).raise_for_status()
        expect(page.locator("#run-speed-state")).to_have_text("at 5 %", timeout=15_000)

        # A screen that is not signed in (a tablet by the cell, no token) shows the arm owned
        # and a Stop that works: its Escape is the stop that lands. The operator's page presses
        # Escape too. From each press until the server confirms, each page says "Stopping…"
        # (the stops' requests are held a moment, as on a slow network).
        with pendant_for(browser, arm_server, screens, "real-arm-signed-out") as bystander:
            near = bystander.page
            bystander.guard.allow(401, "/")
            near.goto(arm_server.url + "/")
            near.wait_for_selector("body[data-ready=true]")
            expect(near.locator("#sign-in")).to_be_visible()
            expect(near.locator("#arm-kind")).to_have_text("REAL ARM")
            expect(near.locator("#arm-owner")).to_have_text(owner)
            near_stop = near.get_by_role("button", name="Stop")
            expect(near_stop).to_be_visible()
            # It shows the run's speed; changing it or pausing takes the token (Stop does not).
            expect(near.locator("#run-speed-state")).to_have_text("at 5 %")
            expect(near.get_by_role("button", name="Pause")).to_be_hidden()
            expect(near.locator("#run-speed-slider")).to_be_hidden()
            expect(near.locator("#run-speed-unit")).to_be_hidden()  # no stray "%" either
            # Nothing reconstructed is shown here: no colour scale for it.
            expect(near.locator("#legend-displacement")).to_be_hidden()
            bystander.shot("arm-owned")
            # Into the process, with the tool on the workpiece: stopped there, the arm goes back
            # by a retract off the workpiece and a joint move (below).
            deadline = time.monotonic() + 120
            while _job_progress(client, sid, owner) < process_from + 0.02:
                assert time.monotonic() < deadline, "the run did not reach its process"
                time.sleep(0.05)
            # Held there (paused at rest on the path) for the stops below: where they land then
            # does not depend on how long a loaded machine takes over the presses (twice in
            # this session's runs the process went by before the stop landed, once into the
            # retract).
            paused = client.post(f"/executions/{owner}/pause")
            assert paused.status_code == 200, paused.text
            _robot_at_rest(client)
            assert _job_progress(client, sid, owner) < process_to, (
                "the process ended before the stop"
            )
            held, near_held = [], []
            page.route("**/executions/*/stop", lambda route: held.append(route))
            near.route("**/executions/*/stop", lambda route: near_held.append(route))
            near.keyboard.press("Escape")
            expect(near_stop).to_have_text("Stopping…")
            page.keyboard.press("Escape")
            expect(stop).to_have_text("Stopping…")
            expect(page.locator("#step-run .needs")).to_contain_text("Stopping: the stop was sent")
            expect(stop).to_be_enabled()  # pressing again sends it again
            deadline = time.monotonic() + 10
            while not (held and near_held):
                assert time.monotonic() < deadline, "a stop was not sent"
                page.wait_for_timeout(20)
            near_held[0].continue_()  # the signed-out screen's stop, without a token
            expect(near_stop).to_be_hidden(timeout=30_000)
            expect(near.locator("#arm-owner")).to_have_text("none")
            held[0].continue_()
            page.unroute("**/executions/*/stop")
        result = page.locator("#run-summary")
        expect(result).to_contain_text("stopped in", timeout=30_000)
        expect(result).to_contain_text("not completed")
        expect(page.locator("#run-form .message")).to_contain_text("cancelled")
        expect(page.locator("#run-form .message")).to_contain_text(
            "Stopped at your request: the arm stands where it stopped"
        )
        expect(page.locator("#run-form .message")).to_contain_text("the arm stopped in ")
        expect(stop).to_be_hidden()
        expect(page.locator("#arm-owner")).to_have_text("none")
        # The run's speed goes with it: nothing stale is left beside the bar's state.
        expect(page.locator("#run-speed")).to_be_hidden()
        # The arm stands where it stopped: no motion after the stop.
        q_stopped = _joints(fake)
        time.sleep(0.5)
        assert np.abs(_joints(fake) - q_stopped).max() < 1e-6
        assert fake.control("program_status")["state"] != "running"
        # The dry run still holds, but the arm stands mid-path, not where the plan starts: Run
        # is not offered (the server would refuse it: start_moved); a move to the start is.
        expect(run).to_be_disabled()
        expect(page.locator("#step-run .needs")).to_contain_text(
            "The arm is not where the plan starts (joint "
        )
        pendant.shot("stopped")
        expect(result).to_contain_text("stopped in process")
        # The run's record keeps the approval: the checksum of the file the operator confirmed.
        record = client.get(f"/sessions/{sid}/executions").json()[-1]
        assert record["inputs"]["trajectory_id"] == plan_id
        plan = client.get(f"/sessions/{sid}/trajectories/{plan_id}").json()
        assert record["params"]["approved_sha256"] == plan["sha256"]

        # Back to the start by a move of its own: planned from where the arm stopped, drawn in
        # the 3-D view, dry-run, then approved and run; the plan can then run again.
        panel = page.locator("#move-to-start")
        expect(panel).to_be_visible()
        expect(page.locator("#move-status")).to_contain_text("from where the plan starts")
        move_on_arm = page.get_by_role("button", name="Move to start on the arm")
        expect(move_on_arm).to_be_disabled()
        page.get_by_role("button", name="Plan the move to the start").click()
        move_summary = page.locator("#move-summary")
        expect(move_summary).to_contain_text("fastest TCP", timeout=60_000)
        expect(move_summary.locator(".report")).to_contain_text("a move of")
        # The tool stands on the workpiece: the move backs it off along its axis first.
        expect(move_summary.locator("tr", has_text="motion")).to_have_text(
            re.compile(
                "straight off the workpiece, 50 mm back along the tool's axis, then a joint move"
            )
        )
        expect(move_summary.locator("tr", has_text="fastest TCP")).to_contain_text("(retract)")
        move_id = move_summary.locator("td").first.inner_text()
        assert move_id.startswith("trj_"), move_id
        expect(page.locator("#workspace")).to_have_attribute("data-move", move_id)
        expect(page.locator("#plan-summary td").first).to_have_text(plan_id)  # still the plan
        expect(move_on_arm).to_be_disabled()  # not before its dry run
        page.get_by_role("button", name="Dry run the move").click()
        expect(move_summary.locator("tr", has_text="dry run")).to_contain_text(
            "passed", timeout=60_000
        )
        expect(move_on_arm).to_be_enabled()
        pendant.shot("move-planned")
        move_on_arm.click()
        expect(dialog).to_be_visible()
        expect(page.locator("#confirm-title")).to_have_text("Move the arm to the plan's start?")
        expect(dialog.locator("tr", has_text="motion")).to_contain_text(
            "straight off the workpiece, 50 mm back along the tool's axis, then a joint move to "
            f"the start of plan {plan_id}"
        )
        expect(dialog.locator("tr", has_text="move file")).to_contain_text(move_id)
        pendant.shot("move-confirm")
        page.get_by_role("button", name="Confirm: move to start").click()
        expect(panel).to_be_hidden(timeout=60_000)
        q_start = np.array(plan["summary"]["start_q_rad"])
        assert np.abs(_joints(fake) - q_start).max() < 0.01
        move_run = client.get(f"/sessions/{sid}/executions").json()[-1]
        assert move_run["inputs"]["trajectory_id"] == move_id
        assert not move_run["params"]["dry_run"] and move_run["summary"]["completed"]
        expect(run).to_be_enabled()
        expect(page.locator("#step-run .needs")).to_have_text(
            "Ready: press “Run on arm” and confirm."
        )
        pendant.shot("at-start")


def test_a_protective_stop_is_shown_and_unlocked_when_the_controller_allows(
    browser, arm_server, fake_ur_process, screens
):
    fake = fake_ur_process
    fake.control("reset")
    with pendant_for(browser, arm_server, screens, "protective-stop") as pendant:
        page = pendant.page
        pendant.open()
        expect(page.locator("#protective-stop")).to_have_text("no")
        # Shown only while there is one (the safety status says NORMAL otherwise).
        expect(page.locator("#protective-stop-field")).to_be_hidden()
        unlock = page.get_by_role("button", name="Unlock")
        expect(unlock).to_be_hidden()
        fake.control("protective_stop")
        expect(page.locator("#protective-stop-field")).to_be_visible()
        expect(page.locator("#protective-stop")).to_have_text(
            re.compile(r"^YES \(unlock in \d s\)")
        )
        expect(page.locator("#safety-status")).to_have_text("PROTECTIVE_STOP")
        expect(page.locator("#safety-bar")).to_have_class(re.compile("alarm"))
        expect(unlock).to_be_visible()
        expect(unlock).to_be_disabled()  # the controller refuses within 5 s of the stop
        pendant.shot("protective-stop")
        expect(unlock).to_be_enabled(timeout=10_000)
        unlock.click()
        expect(page.locator("#protective-stop")).to_have_text("no")
        expect(page.locator("#protective-stop-field")).to_be_hidden()
        expect(page.locator("#safety-status")).to_have_text("NORMAL")
        expect(page.locator("#safety-bar")).not_to_have_class(re.compile("alarm"))
        expect(unlock).to_be_hidden()
        pendant.shot("unlocked")


def test_an_imported_plan_must_be_dry_run_here_and_the_pendant_says_so(
    browser, arm_server, fake_ur_process, screens, tmp_path
):
    """A session planned and dry-run at another site arrives as a bundle: its dry run does not
    count on this server (the gate checks the samples here and wants a dry run made here), and
    the operator is told so, with Run on arm disabled until the plan is dry-run here."""
    from fastapi.testclient import TestClient

    from drivers.scanning.pointcloud import write_scan
    from drivers.tracking.canonical_csv import write_trace_csv
    from recon import scenes
    from recon.kinematics import HOME_Q_RAD
    from service.app import create_app
    from tests.service.conftest import AUTH, make_settings, planned_session, wait

    fake_ur_process.control("reset")
    scene = scenes.box_corner(0)
    write_trace_csv(tmp_path / "trace.csv", scene.recording)
    write_scan(tmp_path / "scan.ply", scene.scan)
    files = {
        k: (tmp_path / f).read_bytes() for k, f in (("trace", "trace.csv"), ("scan", "scan.ply"))
    }
    # Planned elsewhere for this cell (its box and floor): not outdated here, only not dry-run.
    site_a_settings = make_settings(
        tmp_path / "site_a",
        keep_out_boxes=[(0.0, 0.7, 0.0, 0.2, 0.9, 0.3)],
        cell_planes=[(0.0, 0.0, 1.0, -0.5)],
    )
    with TestClient(create_app(site_a_settings), headers=AUTH) as site_a:
        sid, trajectories = planned_session(
            site_a, files, [0.05], name="from site A", start_q_rad=HOME_Q_RAD
        )
        dry = site_a.post(f"/sessions/{sid}/executions", json={"trajectory_id": trajectories[0.05]})
        assert wait(site_a, dry.json())["result"]["completed"]
        bundle = site_a.get(f"/sessions/{sid}/bundle").content
    imported = arm_server.client.post(
        "/sessions/import", files={"file": ("site-a.zip", bundle, "application/zip")}
    )
    assert imported.status_code == 201, imported.text
    with pendant_for(browser, arm_server, screens, "imported-plan") as pendant:
        page = pendant.page
        pendant.open()
        page.get_by_role("button", name="from site A", exact=True).click()
        expect(page.locator("#step-dryrun .needs")).to_contain_text(
            "imported with the session and does not count here"
        )
        expect(page.locator("#step-run .needs")).to_contain_text("does not count here")
        expect(page.get_by_role("button", name="Run on arm")).to_be_disabled()
        pendant.shot("imported")
        page.get_by_role("button", name="Dry run").click()
        expect(page.locator("#step-dryrun .needs")).to_have_text("", timeout=60_000)
        expect(page.locator("#step-run .needs")).to_contain_text("Run on arm")
        pendant.shot("dry-run-here")


def test_an_outdated_plan_runs_only_when_taken_on_purpose_with_its_inputs_in_view(
    browser, arm_server, fake_ur_process, screens, tmp_path
):
    """A new trace outdates the session's plans: none is offered for the arm. The operator
    selects the older of two plans, reads what it was made from and what changed since, takes
    it through a confirmation that names them (a Cancel changes nothing), dry-runs it and runs
    it; the run's confirmation says first that the plan is outdated, the request says it was
    accepted, and the run's record keeps what had changed. A reload forgets the choice."""
    from drivers.scanning.pointcloud import write_scan
    from drivers.tracking.canonical_csv import write_trace_csv
    from recon import scenes
    from recon.kinematics import HOME_Q_RAD
    from tests.service.conftest import T_BASE_TRACKER, planned_session

    fake_ur_process.control("reset")
    client = arm_server.client
    scene = scenes.box_corner(0)
    write_trace_csv(tmp_path / "first-trace.csv", scene.recording)
    write_trace_csv(tmp_path / "second-trace.csv", scenes.box_corner(1).recording)
    write_scan(tmp_path / "scan.ply", scene.scan)
    files = {
        "trace": (tmp_path / "first-trace.csv").read_bytes(),
        "scan": (tmp_path / "scan.ply").read_bytes(),
    }
    sid, plans = planned_session(
        client, files, [0.03, 0.05], name="older plan", start_q_rad=HOME_Q_RAD
    )
    first_trace = client.get(f"/sessions/{sid}").json()["recording_id"]
    # A second trace arrives (uploaded, captured or replayed): both plans are of the first.
    second = client.put(
        f"/sessions/{sid}/recording",
        files={"file": ("second-trace.csv", (tmp_path / "second-trace.csv").read_bytes())},
    )
    assert second.status_code == 201, second.text
    older, newest = plans[0.03], plans[0.05]
    with pendant_for(browser, arm_server, screens, "older-plan") as pendant:
        page = pendant.page
        pendant.open()
        page.get_by_role("button", name="older plan", exact=True).click()
        expect(page.locator("#plan-summary .outdated")).to_contain_text("the trace")
        run = page.get_by_role("button", name="Run on arm")
        expect(run).to_be_disabled()
        expect(page.locator("#step-run .needs")).to_contain_text("The plan is outdated")
        # Both plans are listed, newest first and in use, each marked outdated.
        choice = page.locator("#plan-choice")
        expect(choice).to_be_visible()
        options = page.locator("#plan-pick option")
        expect(options).to_have_count(2)
        expect(options.nth(0)).to_contain_text(f"{newest}, ")
        expect(options.nth(0)).to_contain_text("newest · OUTDATED · in use")
        expect(options.nth(1)).to_contain_text(f"{older}, ")
        expect(options.nth(1)).to_contain_text("30 mm/s")
        expect(options.nth(1)).to_contain_text("OUTDATED")
        # Selecting the older plan shows what it was made from and what changed since.
        page.locator("#plan-pick").select_option(older)
        inputs = page.locator("#plan-pick-inputs")
        expect(inputs.locator("tr", has_text="changed since it was made")).to_contain_text(
            f"the trace: made from {first_trace}"
        )
        row = lambda box, name: box.locator("tr").filter(  # noqa: E731
            has=page.locator("th").get_by_text(name, exact=True)
        )
        expect(row(inputs, "trace")).to_contain_text(f"t.csv ({first_trace}, sha256 ")
        expect(inputs.locator("tr", has_text="speed")).to_contain_text("30 mm/s")
        expect(inputs.locator("tr", has_text="plan file")).to_contain_text(older)
        expect(row(inputs, "tracker → base")).to_contain_text(
            "translation (350.0, -50.0, 100.0) mm, turned 0.0°, the session's (set directly"
        )
        expect(row(inputs, "tracker → scan")).to_contain_text("registered by rcn_")
        expect(row(inputs, "arm kinematics")).to_contain_text("ur5e")
        choice.scroll_into_view_if_needed()
        pendant.shot("older-plan-selected")
        # Taken only through a confirmation that names them; Cancel changes nothing.
        use = page.get_by_role("button", name="Use this plan…")
        use.click()
        dialog = page.locator("#confirm-dialog")
        expect(dialog).to_be_visible()
        expect(page.locator("#confirm-title")).to_have_text("Use this outdated plan?")
        expect(page.locator("#confirm-warning")).to_have_text(re.compile("^Nothing moves now"))
        table = page.locator("#confirm-table")
        expect(table.locator("tr", has_text="changed since it was made")).to_contain_text(
            "the trace"
        )
        expect(row(table, "trace")).to_contain_text(first_trace)
        expect(table.locator("tr", has_text="plan file")).to_contain_text(older)
        pendant.shot("older-plan-confirm")
        page.get_by_role("button", name="Cancel").click()
        expect(dialog).to_be_hidden()
        expect(options.nth(0)).to_contain_text("in use")
        expect(run).to_be_disabled()
        use.click()
        page.get_by_role("button", name="Confirm: use this plan").click()
        expect(dialog).to_be_hidden()
        expect(options.nth(1)).to_contain_text("OUTDATED · in use")
        expect(page.locator("#plan-summary tr", has_text="trajectory")).to_contain_text(older)
        expect(page.locator("#plan-summary .outdated")).to_contain_text("Taken on purpose")
        expect(page.locator("#steps li[data-step=plan]")).to_have_class(re.compile("done"))
        expect(use).to_be_disabled()  # it is the plan in use
        # The 3-D view and the timeline show the plan taken.
        expect(page.locator("#workspace")).to_have_attribute(
            "data-shown", re.compile(f"/{older}/"), timeout=30_000
        )
        pendant.shot("older-plan-taken")
        page.get_by_role("button", name="Dry run").click()
        expect(page.locator("#dryrun-summary")).to_contain_text("passed", timeout=120_000)
        dry = client.get(f"/sessions/{sid}/executions").json()[-1]
        assert dry["inputs"]["trajectory_id"] == older and dry["params"]["dry_run"]
        expect(run).to_be_enabled()
        run.click()
        expect(page.locator("#confirm-title")).to_have_text("Run on the arm?")
        first_row = page.locator("#confirm-table tr").first
        expect(first_row).to_contain_text("OUTDATED, taken on purpose")
        expect(first_row).to_contain_text("the trace")
        # Styled as the warning it is, and the only row so styled.
        expect(first_row).to_have_class(re.compile(r"\bwarning\b"))
        expect(page.locator("#confirm-table tr.warning")).to_have_count(1)
        expect(page.locator("#confirm-table tr", has_text="plan file")).to_contain_text(older)
        pendant.shot("older-plan-run-confirm")
        page.get_by_role("button", name="Confirm: run on arm").click()
        expect(page.locator("#run-summary")).to_contain_text("passed", timeout=180_000)
        record = client.get(f"/sessions/{sid}/executions").json()[-1]
        assert record["inputs"]["trajectory_id"] == older and not record["params"]["dry_run"]
        assert record["summary"]["completed"]
        (accepted,) = record["params"]["accepted_outdated"]
        assert accepted.startswith(f"the trace: made from {first_trace}")
        # A reload forgets the choice: the newest plan again, outdated, not offered.
        page.reload()
        expect(page.locator("#session-title")).to_have_text("Session older plan")
        expect(options.nth(0)).to_contain_text("newest · OUTDATED · in use")
        expect(run).to_be_disabled()
        expect(page.locator("#step-run .needs")).to_contain_text("The plan is outdated")
        # Recalibrated since: the plan can be taken to dry-run it, but the arm is not offered
        # (the service would refuse it: its scan would be checked in the wrong place).
        shifted = np.array(T_BASE_TRACKER)
        shifted[0, 3] += 0.005
        recalibrated = client.put(
            f"/sessions/{sid}/calibration", json={"T_base_tracker": shifted.tolist()}
        )
        assert recalibrated.status_code == 200, recalibrated.text
        page.reload()
        expect(page.locator("#session-title")).to_have_text("Session older plan")
        page.locator("#plan-pick").select_option(older)
        expect(
            page.locator("#plan-pick-inputs tr", has_text="changed since it was made")
        ).to_contain_text("5.0 mm")
        use.click()
        expect(page.locator("#confirm-table tr", has_text="then")).to_contain_text(
            "It can be dry-run, not run."
        )
        page.get_by_role("button", name="Confirm: use this plan").click()
        expect(options.nth(1)).to_contain_text("in use")
        expect(page.locator("#step-run .needs")).to_contain_text(
            "made with another tracker-to-base calibration than the session's (5.0 mm"
        )
        expect(row(page.locator("#plan-pick-inputs"), "tracker → base")).to_contain_text(
            "NOT the session's calibration now"
        )
        expect(run).to_be_disabled()
        pendant.shot("older-plan-recalibrated")


def test_the_run_step_says_why_the_arm_cannot_run_through_its_stops_and_offers_it_after(
    browser, arm_server, fake_ur_process, screens, tmp_path
):
    """A dry-run plan ready to run: a protective stop, an emergency stop, the arm powered off
    after its release, and local control each disable Run on arm with the reason and what to
    do (as the server's gate would refuse); once each is cleared the run is offered again."""
    from drivers.scanning.pointcloud import write_scan
    from drivers.tracking.canonical_csv import write_trace_csv
    from recon import scenes
    from recon.kinematics import HOME_Q_RAD
    from tests.service.conftest import planned_session, wait

    fake = fake_ur_process
    fake.control("reset")
    fake.control("configure", unlock_wait_s=0.0)  # UR's 5 s wait is tested above
    client = arm_server.client
    scene = scenes.box_corner(0)
    write_trace_csv(tmp_path / "trace.csv", scene.recording)
    write_scan(tmp_path / "scan.ply", scene.scan)
    files = {
        "trace": (tmp_path / "trace.csv").read_bytes(),
        "scan": (tmp_path / "scan.ply").read_bytes(),
    }
    sid, plans = planned_session(client, files, [0.05], name="stops", start_q_rad=HOME_Q_RAD)
    dry = client.post(f"/sessions/{sid}/executions", json={"trajectory_id": plans[0.05]})
    assert wait(client, dry.json())["result"]["completed"]
    with pendant_for(browser, arm_server, screens, "run-step-stops") as pendant:
        page = pendant.page
        pendant.open()
        page.get_by_role("button", name="stops", exact=True).click()
        needs = page.locator("#step-run .needs")
        run = page.get_by_role("button", name="Run on arm")
        ready = "Ready: press “Run on arm” and confirm."

        def offered() -> None:
            expect(needs).to_have_text(ready)
            expect(run).to_be_enabled()

        def refused(command: str, why: str) -> None:
            """The fake arm in a state (a control command): Run on arm disabled, saying why."""
            fake.control(command)
            expect(needs).to_have_text(why)
            expect(run).to_be_disabled()

        offered()
        refused(
            "protective_stop",
            "The arm is in a protective stop: clear its cause, then press Unlock in the safety "
            "bar.",
        )
        pendant.shot("protective-stop")
        page.get_by_role("button", name="Unlock").click()
        offered()
        refused(
            "emergency_stop",
            "The arm is in an emergency stop: release it on the teach pendant, then power it on.",
        )
        expect(page.locator("#safety-status")).to_have_text("EMERGENCY STOP")
        pendant.shot("emergency-stop")
        # Released, the arm is still powered off: nothing can move it yet.
        refused(
            "release_emergency_stop",
            "The arm is not running (mode POWER_OFF): power it on and release its brakes on the "
            "UR teach pendant.",
        )
        expect(page.locator("#safety-bar")).to_have_class(re.compile("alarm"))
        # The server refuses it too, naming the same reason.
        answer = client.post(
            f"/sessions/{sid}/executions",
            json={"trajectory_id": plans[0.05], "backend": "ur_rtde", "confirm": True},
        )
        assert answer.status_code == 409, answer.text
        assert answer.json()["code"] == "arm_not_running", answer.text
        fake.control("reset")  # powered on and brakes released, at the plan's start
        offered()

        fake.control("configure", remote_control=False)
        expect(needs).to_have_text(
            "The arm is in local control: switch the UR teach pendant to Remote Control."
        )
        expect(run).to_be_disabled()
        expect(page.locator("#remote-control")).to_have_text("OFF (local)")
        fake.control("configure", remote_control=True)
        offered()
