"""Parameters that would explode (a 7 GB worker at speed 1e-5 m/s, OverflowError at 5e-324) are
refused at the request with the bound, from what the arm and the method can use."""

from __future__ import annotations

import numpy as np
import pytest

from recon.plan import MAX_PROCESS_DURATION_S, plan_path
from recon.plan_params import PlanParams


@pytest.mark.parametrize(
    ("body", "name"),
    [
        ({"speed_m_s": 1e-5}, "speed_m_s"),
        ({"speed_m_s": 5e-324}, "speed_m_s"),
        ({"approach_speed_m_s": 1e-300}, "approach_speed_m_s"),
        ({"transit_speed_scale": 5e-324}, "transit_speed_scale"),
        ({"transit_acceleration_scale": 1e-300}, "transit_acceleration_scale"),
        ({"transit_tcp_speed_m_s": 1e-300}, "transit_tcp_speed_m_s"),
        ({"velocity_scale": 1e-300}, "velocity_scale"),
        ({"tool_radius_m": 5e-324}, "tool_radius_m"),
    ],
)
def test_plan_parameters_below_what_the_arm_can_use_are_a_422(client, session, body, name):
    response = client.post(
        f"/sessions/{session}/trajectories", json={"reconstruction_id": "rcn_0", **body}
    )
    assert response.status_code == 422, response.text
    assert name in response.text


@pytest.mark.parametrize(
    ("body", "name"),
    [
        ({"spacing_m": 5e-324}, "spacing_m"),
        ({"radius_m": 1e-300}, "radius_m"),
        ({"icp_max_distance_m": 5e-324}, "icp_max_distance_m"),
        ({"evidence_sigmas": 1e-300}, "evidence_sigmas"),
        ({"voxel_m": 5e-324}, "voxel_m"),
    ],
)
def test_reconstruction_parameters_that_would_explode_are_a_422(client, session, body, name):
    response = client.post(f"/sessions/{session}/reconstructions", json=body)
    assert response.status_code == 422, response.text
    assert name in response.text


def test_a_plan_longer_than_an_hour_at_its_speed_is_refused_before_any_work():
    """5 m at the slowest speed allowed (1 mm/s) is 5,000 s: refused with the speed that fits,
    before inverse kinematics (the line is far out of the arm's reach)."""
    line = np.column_stack([np.linspace(0.0, 5.0, 5001), np.zeros(5001), np.full(5001, 0.2)])
    with pytest.raises(ValueError, match=r"5000 s at speed_m_s 0.001.*at least 0.0014 m/s"):
        plan_path(line, params=PlanParams(speed_m_s=0.001))
    assert MAX_PROCESS_DURATION_S == 3600.0


@pytest.mark.parametrize(
    ("spheres", "message"),
    [
        ([0, 0, 0.1], "four numbers per sphere"),
        ([0, 0, 0.1, -0.01], "radius"),
        ([0, 0, 0.1, 0.01] * 33, "at most 32 spheres"),
        ([0, 0, 5.0, 0.01], "tool_spheres_m"),
        ([0, 0, 0.1, 1e308], "tool_spheres_m"),
        (["a", 0, 0.1, 0.01], "tool_spheres_m"),
        ([[0, 0, 0.1, 0.01]], "tool_spheres_m"),
        ({"x": 0}, "tool_spheres_m"),
    ],
    ids=["three", "negative-radius", "too-many", "far", "huge", "text", "nested", "object"],
)
def test_tool_spheres_that_are_not_a_tool_are_a_422(client, session, spheres, message):
    response = client.post(
        f"/sessions/{session}/trajectories",
        json={"reconstruction_id": "rcn_0", "speed_m_s": 0.05, "tool_spheres_m": spheres},
    )
    assert response.status_code == 422, response.text
    assert message in response.text


def test_tool_spheres_bad_on_the_command_line_are_refused_before_any_work(tmp_path):
    from tests.service.test_cli import run

    for value, message in (
        ("0,0,0.1", "four numbers per sphere"),
        ("0,0,0.1,-0.01", "radius"),
        ("a,b,c,d", "expected numbers"),
        ("0,0,nan,0.01", "finite"),
    ):
        result = run(
            "plan", tmp_path / "missing.csv", "--speed-m-s", "0.05",
            f"--tool-spheres-m={value}", "--out", tmp_path / "o.csv",
        )  # fmt: skip
        assert result.returncode != 0, (value, result.stderr)
        assert message in result.stderr, (value, result.stderr)
