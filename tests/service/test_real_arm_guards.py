"""Executions on a real arm are refused unless confirmed, dry-run first, and within the cap."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from recon.kinematics import HOME_Q_RAD
from service.app import create_app
from tests.service.conftest import AUTH, make_settings, planned_session, wait


@pytest.fixture(scope="module")
def arm_client(tmp_path_factory, scene_files):
    # 127.0.0.9: nothing listens there, so an attempt to move fails fast and harmlessly.
    settings = make_settings(
        tmp_path_factory.mktemp("arm"), ur_host="127.0.0.9", ur_robot="ur5e", max_speed_m_s=0.06
    )
    with TestClient(create_app(settings), headers=AUTH) as client:
        # Nothing answers at 127.0.0.9: the plans start from the arm's home, given.
        sid, trajectories = planned_session(
            client, scene_files, (0.05, 0.1), start_q_rad=HOME_Q_RAD
        )
        yield client, sid, trajectories


def post(client, sid, **body):
    return client.post(f"/sessions/{sid}/executions", json=body)


def test_confirmation_is_required(arm_client):
    client, sid, trajectories = arm_client
    response = post(client, sid, trajectory_id=trajectories[0.05], backend="ur_rtde")
    assert response.status_code == 409 and response.json()["code"] == "confirmation_required"


def test_a_dry_run_must_pass_first(arm_client):
    client, sid, trajectories = arm_client
    response = post(client, sid, trajectory_id=trajectories[0.05], backend="ur_rtde", confirm=True)
    assert response.status_code == 409 and response.json()["code"] == "dry_run_required"


def test_the_server_caps_the_speed(arm_client):
    client, sid, trajectories = arm_client
    response = post(client, sid, trajectory_id=trajectories[0.1], backend="ur_rtde", confirm=True)
    assert response.status_code == 409 and response.json()["code"] == "speed_cap"


def test_after_a_dry_run_an_unreachable_arm_is_refused_naming_it(arm_client):
    client, sid, trajectories = arm_client
    dry = wait(client, post(client, sid, trajectory_id=trajectories[0.05]).json())
    assert dry["state"] == "succeeded" and dry["result"]["completed"]
    response = post(client, sid, trajectory_id=trajectories[0.05], backend="ur_rtde", confirm=True)
    # The arm's state cannot be read: nothing is started on a state that is not known.
    assert response.status_code == 409 and response.json()["code"] == "robot_unavailable"
    assert "127.0.0.9" in response.json()["message"]
    jobs = client.get(f"/sessions/{sid}/jobs").json()
    assert all(j["params"].get("backend") != "ur_rtde" for j in jobs)  # nothing was started


def test_a_dry_run_counts_only_for_the_mode_and_tolerance_it_ran_in(arm_client):
    client, sid, trajectories = arm_client
    trajectory_id = trajectories[0.05]
    dry = wait(client, post(client, sid, trajectory_id=trajectory_id, mode="movepath").json())
    assert dry["state"] == "succeeded" and dry["result"]["completed"]
    execution = client.get(f"/sessions/{sid}/executions/{dry['result']['execution_id']}").json()
    assert execution["params"]["mode"] == "movepath"
    assert "movepath" in execution["summary"]["report"][0]
    for body, code in (
        ({"mode": "movepath", "tolerance_m": 0.002}, "dry_run_required"),
        ({"mode": "movepath"}, None),
    ):
        response = post(
            client, sid, trajectory_id=trajectory_id, backend="ur_rtde", confirm=True, **body
        )
        if code is None:  # past the dry-run check: refused for the unreachable arm only
            assert response.status_code == 409
            assert response.json()["code"] == "robot_unavailable"
        else:
            assert response.status_code == 409 and response.json()["code"] == code
            assert "tolerance_m" in response.json()["message"]
