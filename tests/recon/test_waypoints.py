"""Coarse waypoints for movePath: the TCP stays within the tolerance, checked independently."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from recon import kinematics
from recon.plan import PlanParams, plan_path
from recon.waypoints import MAX_SPAN_SAMPLES, coarse_waypoints
from tests.motion_fixtures import line_plan


@pytest.fixture(scope="module")
def arc_trajectory():
    """A quarter circle (R 80 mm) on a table, with a tool 120 mm long: the TCP offset matters."""
    angle = np.linspace(0.0, np.pi / 2, 126)
    points = np.column_stack(
        [0.35 + 0.08 * np.cos(angle), 0.08 * np.sin(angle), np.full_like(angle, 0.1)]
    )
    params = PlanParams(robot="ur5e", speed_m_s=0.1, tcp_offset_m=(0.0, 0.0, 0.12))
    return plan_path(points, params=params).trajectory


def _dense_deviation(arm, trajectory, path) -> float:
    """Distance of each planned TCP sample from the densely sampled joint lines (FK)."""
    T_flange_tcp = np.linalg.inv(kinematics.forward(arm, trajectory.q_rad[0]))
    T_flange_tcp = T_flange_tcp @ _pose(trajectory.tcp_m[0], trajectory.tcp_rotvec[0])
    # Dense enough for every joint line, a long transit included: 0.02 mrad per step.
    steps = int(np.abs(np.diff(path.q_rad, axis=0)).max() / 2e-5) + 400
    u = np.linspace(0.0, 1.0, steps)[:, None, None]
    q0, q1 = path.q_rad[:-1][None], path.q_rad[1:][None]
    lines = (q0 + u * (q1 - q0)).reshape(-1, 6)
    tcp = (kinematics.forward(arm, lines) @ T_flange_tcp)[:, :3, 3]
    distance, _ = cKDTree(tcp).query(trajectory.tcp_m)
    return float(distance.max())


def _pose(p, rotvec):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.array(rotvec)).as_matrix()
    T[:3, 3] = p
    return T


@pytest.mark.slow
@pytest.mark.parametrize("tolerance_m", [1e-4, 5e-4, 2e-3])
def test_every_planned_sample_is_within_the_tolerance(arc_trajectory, tolerance_m):
    arm = kinematics.model("ur5e")
    path = coarse_waypoints(arm, arc_trajectory, tolerance_m=tolerance_m)
    assert path.sample_index[0] == 0 and path.sample_index[-1] == len(arc_trajectory) - 1
    assert np.all(np.diff(path.sample_index) > 0)
    assert path.deviation_max_m <= tolerance_m
    # Independent check (dense FK along each joint line, nearest point) agrees within the
    # sampling of the check itself.
    assert _dense_deviation(arm, arc_trajectory, path) <= tolerance_m * 1.01
    # Coarse means coarse: a small fraction of the controller-rate samples.
    assert len(path) < len(arc_trajectory) / 10


def test_looser_tolerance_needs_fewer_waypoints(arc_trajectory):
    arm = kinematics.model("ur5e")
    counts = [len(coarse_waypoints(arm, arc_trajectory, tolerance_m=t)) for t in (1e-4, 1e-3, 1e-2)]
    assert counts[0] > counts[1] >= counts[2] >= 2


def test_a_straight_line_in_joint_space_is_two_waypoints():
    arm = kinematics.model("ur5e")
    trajectory = line_plan("ur5e", 0.1).trajectory
    # Replace the joints by an exact joint-space line (with the TCP it really gives).
    u = np.linspace(0, 1, len(trajectory))[:, None]
    q = trajectory.q_rad[0] + u * (trajectory.q_rad[-1] - trajectory.q_rad[0])
    T = kinematics.forward(arm, q)
    straight = dataclasses.replace(trajectory, q_rad=q, tcp_m=T[:, :3, 3], tcp_rotvec=_rotvec(T))
    path = coarse_waypoints(arm, straight, tolerance_m=1e-5)
    # Two waypoints, but for the bound on the stretch one check considers (MAX_SPAN_SAMPLES):
    # the transit, held to the TCP speed cap, makes this motion longer than one span.
    n = len(trajectory)
    assert list(path.sample_index) == [*range(0, n - 1, MAX_SPAN_SAMPLES), n - 1]


def _rotvec(T):
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(T[:, :3, :3]).as_rotvec()


def test_speeds_take_as_long_as_the_plan_and_blends_fit(arc_trajectory):
    arm = kinematics.model("ur5e")
    path = coarse_waypoints(arm, arc_trajectory, blend_m=0.005)
    lead = np.abs(np.diff(path.q_rad, axis=0)).max(axis=1)
    planned_s = np.diff(arc_trajectory.t_s[path.sample_index])
    np.testing.assert_allclose(lead / path.speed_rad_s[1:], planned_s, rtol=1e-9)
    assert path.blend_m[0] == 0 and path.blend_m[-1] == 0
    stretch = np.linalg.norm(np.diff(arc_trajectory.tcp_m[path.sample_index], axis=0), axis=1)
    assert np.all(path.blend_m[1:-1] <= 0.4 * np.minimum(stretch[:-1], stretch[1:]) + 1e-15)
    assert 0 < path.acceleration_rad_s2 <= arm.qdd_max_rad_s2.min()


def test_bad_arguments():
    arm = kinematics.model("ur5e")
    trajectory = line_plan("ur5e", 0.1).trajectory
    with pytest.raises(ValueError, match="tolerance_m"):
        coarse_waypoints(arm, trajectory, tolerance_m=0)
    with pytest.raises(ValueError, match="blend_m"):
        coarse_waypoints(arm, trajectory, blend_m=-1)
    with pytest.raises(ValueError, match="ur10e"):
        coarse_waypoints(kinematics.model("ur10e"), trajectory)
