"""A move of its own from where the arm is to a plan's start (recon.plan.plan_move): exact ends,
at rest, within the limits, the trapezoid's duration, the cell."""

from __future__ import annotations

import numpy as np
import pytest

from recon import kinematics
from recon.collision import Box, Cell
from recon.errors import CollisionError
from recon.plan import plan_move
from recon.types import Phase, PlanParams

HOME = np.array(kinematics.HOME_Q_RAD)


def test_the_move_starts_and_ends_exactly_at_rest_within_the_limits():
    params = PlanParams(robot="ur5e")
    goal = HOME + [0.4, -0.3, 0.2, 0.5, -0.2, 1.0]
    move = plan_move(HOME, goal, params=params)
    traj = move.trajectory
    np.testing.assert_array_equal(traj.q_rad[0], HOME)
    np.testing.assert_array_equal(traj.q_rad[-1], goal)
    assert np.abs(traj.qd_rad_s[[0, -1]]).max() == 0.0
    assert set(traj.phases.tolist()) == {int(Phase.TRANSIT)}
    arm = kinematics.model("ur5e")
    speed_limit = arm.qd_max_rad_s * params.transit_speed_scale
    assert np.all(np.abs(traj.qd_rad_s) <= speed_limit * (1 + 1e-9))
    measured = np.abs(np.diff(traj.q_rad, axis=0)) * arm.control_rate_hz
    assert np.all(measured <= speed_limit * 1.01)
    assert traj.phase_max_tcp_speed_m_s()["transit"] <= params.transit_tcp_speed_m_s * 1.001
    assert not move.base_first and move.collision is None
    margins = move.margins()
    assert margins["min_limit_margin_rad"] > 0 and 0 < margins["min_wrist_singularity"] <= 1


def test_a_one_joint_move_takes_the_trapezoids_time():
    """Joint 6 alone, far enough to cruise: T = d / v + v / a (an independent formula), with
    the TCP cap out of the way (the TCP sits on joint 6's axis)."""
    params = PlanParams(robot="ur5e", transit_speed_scale=0.5, transit_acceleration_scale=0.5)
    arm = kinematics.model("ur5e")
    distance = 2.0
    move = plan_move(HOME, HOME + [0, 0, 0, 0, 0, distance], params=params)
    v = arm.qd_max_rad_s[5] * 0.5
    a = arm.qdd_max_rad_s2[5] * 0.5
    assert distance > v * v / a  # it cruises
    expected_s = distance / v + v / a
    assert move.trajectory.duration_s == pytest.approx(expected_s, abs=2.0 / arm.control_rate_hz)


def test_a_direct_move_through_a_box_turns_the_base_first_and_one_that_cannot_is_refused():
    params = PlanParams(robot="ur5e")
    arm = kinematics.model("ur5e")
    start = HOME + [-1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    goal = HOME + [1.0, -0.5, 0.6, 0.0, 0.0, 0.0]
    direct = plan_move(start, goal, params=params).trajectory
    # A box where the direct move's flange passes at its middle, but not where the base turns
    # the folded arm first.
    middle = kinematics.forward(arm, direct.q_rad[len(direct) // 2][None])[0, :3, 3]
    box = Box(min_m=middle - 0.03, max_m=middle + 0.03, name="keep-out box 1")
    turned = HOME.copy()
    turned[0] = goal[0]
    via = np.array([start, turned])
    assert np.all(np.abs(kinematics.forward(arm, via)[:, :3, 3] - middle).max(axis=1) > 0.1), (
        "the box must be off the base-first way"
    )
    move = plan_move(start, goal, params=params, cell=Cell(boxes=(box,)))
    assert move.base_first
    assert move.collision.first_collision is None
    assert "the base turns alone first" in move.report_lines()[0]
    np.testing.assert_array_equal(move.trajectory.q_rad[-1], goal)

    # A box around the goal's flange: no way reaches it.
    at_goal = kinematics.forward(arm, goal[None])[0, :3, 3]
    blocked = Cell(boxes=(Box(min_m=at_goal - 0.05, max_m=at_goal + 0.05, name="keep-out box 1"),))
    with pytest.raises(CollisionError, match="keep-out box 1"):
        plan_move(start, goal, params=params, cell=blocked)


@pytest.mark.parametrize(
    "q_from, words",
    [
        ([0.0] * 5, "six finite joint angles"),
        ([0.0, 0.0, np.nan, 0.0, 0.0, 0.0], "six finite joint angles"),
        ([0.0, 0.0, 4.0, 0.0, 0.0, 0.0], "outside the ur5e's joint limits"),
    ],
    ids=["five", "nan", "elbow-past-its-limit"],
)
def test_joints_that_are_not_an_arms_are_refused(q_from, words):
    with pytest.raises(ValueError, match=words):
        plan_move(q_from, HOME, params=PlanParams(robot="ur5e"))
