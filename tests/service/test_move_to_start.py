"""POST .../trajectories/{id}/move-to-start on the simulated arm (which stands at its home): the
move's record, and each refusal with what to do. The real arm's flow is in test_fake_arm.py."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from recon.kinematics import HOME_Q_RAD
from service.app import create_app
from tests.service.conftest import AUTH, make_settings, planned_session, wait

AWAY = (np.array(HOME_Q_RAD) + [0.3, -0.1, 0.1, 0.0, 0.2, 0.4]).tolist()


@pytest.fixture(scope="module")
def planned(tmp_path_factory, scene_files):
    """A plan that starts away from the simulated arm's home, and one that starts at it."""
    settings = make_settings(tmp_path_factory.mktemp("move_to_start"))
    with TestClient(create_app(settings), headers=AUTH) as client:
        sid, away = planned_session(client, scene_files, [0.05], start_q_rad=AWAY)
        _, home = planned_session(client, scene_files, [0.05], name="at home")
        yield client, sid, away[0.05], home[0.05]


def test_the_move_goes_from_the_arm_to_the_plans_first_joints(planned):
    client, sid, plan_id, _ = planned
    job = wait(client, client.post(f"/sessions/{sid}/trajectories/{plan_id}/move-to-start").json())
    assert job["state"] == "succeeded", job
    assert job["result"]["move_to_start_of"] == plan_id
    move = client.get(f"/sessions/{sid}/trajectories/{job['result']['trajectory_id']}").json()
    summary = move["summary"]
    assert summary["start_from"] == "home"
    np.testing.assert_allclose(summary["start_q_rad"], HOME_Q_RAD)
    np.testing.assert_allclose(summary["goal_q_rad"], AWAY, atol=1e-12)
    assert summary["path_length_m"] == 0.0 and summary["n_pieces"] == 0
    assert summary["tool_axis_from"] == "none: a joint move"
    assert list(summary["phase_durations_s"]) == ["transit"]
    assert summary["report"][0].startswith("ur5e: a joint move of ")
    # The move is checked against what the plan is: the mounting plane and the scan.
    (checked,) = [line for line in summary["checks"] if line.startswith("no collision")]
    assert "mounting plane" in checked and "scan" in checked
    assert move["params"]["T_base_tracker"] is not None and move["outdated"] == []


def test_each_refusal_says_what_to_do(planned):
    client, sid, plan_id, at_home_id = planned
    # A plan that starts where the arm stands needs no move.
    sessions = {s["name"]: s["id"] for s in client.get("/sessions").json()}
    home_sid = sessions["at home"]
    at_start = client.post(f"/sessions/{home_sid}/trajectories/{at_home_id}/move-to-start")
    assert at_start.status_code == 409 and at_start.json()["code"] == "at_start"
    # An unknown plan, or one of another session.
    for url in (
        f"/sessions/{sid}/trajectories/trj_000000000000/move-to-start",
        f"/sessions/{sid}/trajectories/{at_home_id}/move-to-start",
    ):
        assert client.post(url).status_code == 404, url
    # Not a move of a move.
    job = wait(client, client.post(f"/sessions/{sid}/trajectories/{plan_id}/move-to-start").json())
    move_id = job["result"]["trajectory_id"]
    again = client.post(f"/sessions/{sid}/trajectories/{move_id}/move-to-start")
    assert again.status_code == 409 and again.json()["code"] == "move_of_a_move"
    assert plan_id in again.json()["message"]

    # Not while a run owns the arm: the arm's pose is not a place to start from.
    class Running:  # what the gate registers while the arm moves: only `running` is read
        running = True

    live = client.app.state.services.live
    with live.lock:
        live.executions["exe_running"] = Running()
    try:
        busy = client.post(f"/sessions/{sid}/trajectories/{plan_id}/move-to-start")
        assert busy.status_code == 409 and busy.json()["code"] == "arm_busy"
        assert "exe_running" in busy.json()["message"]
    finally:
        with live.lock:
            del live.executions["exe_running"]
