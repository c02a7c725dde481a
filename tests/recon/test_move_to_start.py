"""A move of its own from where the arm is to a plan's start (recon.plan.plan_move): exact ends,
at rest, within the limits, the trapezoid's duration, the cell."""

from __future__ import annotations

import numpy as np
import pytest

from recon import kinematics
from recon.collision import Box, Cell
from recon.errors import CollisionError
from recon.paths import Phase
from recon.plan import plan_move
from recon.plan_params import PlanParams

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


# -- a move from where a stopped run left the tool on the workpiece ----------------------------


@pytest.fixture(scope="module")
def on_the_cylinder():
    """The demo plan over the cylinder's edge with its cell (the scan in the base frame), as
    the service plans it, and a process sample halfway along: where a run stopped in its
    process leaves the arm, the tool on the workpiece."""
    from recon import scenes
    from recon.plan import approach_in, normals_from_scan, plan_path
    from recon.reconstruct import reconstruct
    from recon.transforms import apply_transform, invert_transform

    scene = scenes.cylinder_edge(0)
    recon = reconstruct(scene.recording, scene.scan)
    T_base_tracker = np.eye(4)
    T_base_tracker[:3, 3] = [0.45, 0.1, 0.05]
    params = PlanParams(robot="ur5e", speed_m_s=0.05)
    normals = normals_from_scan(
        recon.points_m,
        recon.mode,
        recon.scan_model,
        T_scan_tracker=recon.T_scan_tracker,
        approach_tracker=approach_in(T_base_tracker, params.approach_direction),
    )
    scan_base = apply_transform(
        T_base_tracker @ invert_transform(recon.T_scan_tracker), scene.scan.points_m
    )
    cell = Cell(scan_points_m=scan_base)
    plan = plan_path(
        recon.points_m, params=params, T_base_tracker=T_base_tracker, normals=normals, cell=cell
    )
    process = np.flatnonzero(plan.trajectory.phases == int(Phase.PROCESS))
    q_stopped = plan.trajectory.q_rad[process[len(process) // 2]]
    return plan, cell, q_stopped


def test_a_move_from_the_tool_on_the_workpiece_first_retracts_straight_along_its_axis(
    on_the_cylinder,
):
    from recon import motion
    from recon.collision import ObstacleKind
    from recon.plan import check_cell

    plan, cell, q_stopped = on_the_cylinder
    params, arm = plan.params, kinematics.model("ur5e")
    goal = plan.trajectory.q_rad[0]
    # The joint move alone (either way) drags the tool through the workpiece from its first
    # sample: what the planner refused before this move existed.
    direct = motion.assemble(
        arm,
        [
            motion.joint_move(
                arm,
                q_stopped,
                goal,
                speed_scale=params.transit_speed_scale,
                acceleration_scale=params.transit_acceleration_scale,
                T_flange_tcp=params.T_flange_tcp,
            )
        ],
        T_flange_tcp=params.T_flange_tcp,
        requested_speed_m_s=params.transit_tcp_speed_m_s,
    )
    first = check_cell(arm, direct, cell, params).first_collision
    assert (first.sample, first.link, first.kind) == (0, "tool", ObstacleKind.SCAN)

    move = plan_move(q_stopped, goal, params=params, cell=cell)
    traj = move.trajectory
    assert move.retract_m == params.approach_m == 0.05
    assert move.collision.first_collision is None
    np.testing.assert_array_equal(traj.q_rad[0], q_stopped)
    np.testing.assert_array_equal(traj.q_rad[-1], goal)
    assert np.abs(traj.qd_rad_s[[0, -1]]).max() == 0.0
    retract = traj.phases == int(Phase.RETRACT)
    assert retract[0] and set(traj.phases[~retract].tolist()) == {int(Phase.TRANSIT)}
    assert np.all(np.diff(retract.astype(int)) <= 0)  # one retract, at the start
    # The retract: straight back along the tool's axis at the stop, the orientation held, by
    # the plan's approach distance, no faster than its approach speed.
    tcp = kinematics.forward(arm, traj.q_rad[retract]) @ params.T_flange_tcp
    axis = tcp[0, :3, 2]  # the tool's z points into the work
    travel = tcp[:, :3, 3] - tcp[0, :3, 3]
    along = travel @ -axis
    sideways = np.linalg.norm(travel + along[:, None] * axis, axis=1)
    assert sideways.max() < 1e-5
    assert np.all(np.diff(along) >= -1e-9)
    assert along[-1] == pytest.approx(0.05, abs=1e-4)
    np.testing.assert_allclose(
        tcp[:, :3, :3], np.broadcast_to(tcp[0, :3, :3], (len(tcp), 3, 3)), atol=1e-6
    )
    assert traj.phase_max_tcp_speed_m_s()["retract"] <= params.approach_speed_m_s * 1.001
    assert "first straight off the workpiece: 50 mm back along the tool's axis" in (
        " ".join(move.report_lines())
    )


def test_the_touch_at_a_moves_start_is_allowed_there_only(on_the_cylinder):
    """The contact a move off the workpiece may make is at its first pose, along the first
    millimetres of a retract: a "retract" that slides along the workpiece instead is refused
    (the gate checks stored samples this way, whatever their phases say)."""
    from recon import motion
    from recon.collision import ObstacleKind
    from recon.plan import check_cell

    plan, cell, q_stopped = on_the_cylinder
    params, arm = plan.params, kinematics.model("ur5e")
    T_tcp = kinematics.forward(arm, q_stopped[None])[0] @ params.T_flange_tcp
    aside = T_tcp.copy()
    aside[:3, 3] += 0.03 * T_tcp[:3, 0]  # 30 mm across the tool's axis, on the surface
    slide = motion.line_move(
        arm,
        motion.tool_line(T_tcp, aside),
        branch=plan.joints.branch,
        q_end_rad=None,
        q_start_rad=q_stopped,
        T_flange_tcp=params.T_flange_tcp,
        speed_m_s=params.approach_speed_m_s,
        velocity_scale=params.velocity_scale,
        acceleration_scale=params.acceleration_scale,
        phase=Phase.RETRACT,
    )
    dragged = motion.assemble(
        arm, [slide], T_flange_tcp=params.T_flange_tcp, requested_speed_m_s=0.05
    )
    first = check_cell(arm, dragged, cell, params).first_collision
    assert first is not None and (first.link, first.kind) == ("tool", ObstacleKind.SCAN)
    assert first.sample > 0  # allowed at the start, not along the slide


def test_a_retract_blocked_above_the_tool_is_refused_naming_what_blocks_it(on_the_cylinder):
    plan, cell, q_stopped = on_the_cylinder
    params, arm = plan.params, kinematics.model("ur5e")
    T_tcp = kinematics.forward(arm, q_stopped[None])[0] @ params.T_flange_tcp
    # A box the tool's tip would pass through 40 mm up its axis, beside the flange's way.
    above = T_tcp[:3, 3] - 0.04 * T_tcp[:3, 2]
    box = Box(min_m=above - 0.012, max_m=above + 0.012, name="clamp")
    blocked = Cell(scan_points_m=cell.scan_m, boxes=(box,), voxel_m=0.0)
    with pytest.raises(CollisionError, match="clamp"):
        plan_move(q_stopped, plan.trajectory.q_rad[0], params=params, cell=blocked)


# -- the ways back from a run stopped on its path -------------------------------------------


def _stops_along(plan, every: int) -> np.ndarray:
    """Samples of the plan's approach, process and retract: where a stopped run leaves the arm."""
    phases = plan.trajectory.phases
    moving = (Phase.APPROACH, Phase.PROCESS, Phase.RETRACT)
    return np.flatnonzero(np.isin(phases, [int(p) for p in moving]))[::every]


@pytest.mark.slow
def test_from_stops_along_the_path_the_way_back_is_found_or_its_retract_named(on_the_cylinder):
    """From stops all along the cylinder demo's path: a direct joint move back swings the wrist
    past the arm's own links from a third of them; by the ways back (the approach start, the
    path lifted off the workpiece) most of those get a checked move; the rest (mostly where
    the straight retract itself passes the workpiece) are refused naming where and what."""
    from recon.plan import ways_back

    plan, cell, _ = on_the_cylinder
    traj, params = plan.trajectory, plan.params
    goal = traj.q_rad[0]
    direct_refused, by_a_way, refused = 0, 0, []
    for i in _stops_along(plan, 80):
        q_stop = traj.q_rad[i]
        try:
            plan_move(q_stop, goal, params=params, cell=cell)
        except CollisionError:
            direct_refused += 1
        try:
            move = plan_move(
                q_stop, goal, params=params, cell=cell, ways=ways_back(traj, q_stop, params)
            )
        except CollisionError as error:
            refused.append(str(error))
            continue
        assert move.collision.first_collision is None
        np.testing.assert_array_equal(move.trajectory.q_rad[0], q_stop)
        np.testing.assert_array_equal(move.trajectory.q_rad[-1], goal)
        if move.via_q_rad is not None:
            by_a_way += 1
            # At rest at each stop of the way, exactly there.
            for via in move.via_q_rad:
                at = np.flatnonzero(np.all(move.trajectory.q_rad == via, axis=1))
                assert len(at) and np.abs(move.trajectory.qd_rad_s[at]).max() == 0.0
            assert "stop(s) at rest" in " ".join(move.report_lines())
    assert direct_refused >= 10, "the scene no longer shows the problem the ways solve"
    assert by_a_way >= direct_refused - len(refused) > 0
    assert len(refused) < direct_refused / 2
    assert all(message.startswith("the motion collides: ") for message in refused), refused


def test_a_way_back_runs_along_the_path_lifted_off_it(on_the_cylinder):
    """The second way from a stop on the path: the path's own poses back to its start, each
    lifted by the approach distance along the tool's axis, in the arm's branch; then the
    approach start. An arm jogged off the plan's way gets no way back."""
    from recon.plan import WAY_BACK_TURN_RAD, ways_back

    plan, _, q_stopped = on_the_cylinder
    traj, params, arm = plan.trajectory, plan.params, kinematics.model("ur5e")
    approach_start = traj.q_rad[np.flatnonzero(traj.phases == int(Phase.APPROACH))[0]]
    ways = ways_back(traj, q_stopped, params)
    assert len(ways) == 2
    np.testing.assert_array_equal(ways[0], approach_start[None])
    back = ways[1]
    # Its last stop: the approach start, or the path's start lifted (the same pose, solved apart).
    np.testing.assert_allclose(back[-1], approach_start, atol=1e-6)
    # Each stop lies above the path by the approach distance, against the tool's axis.
    process = traj.q_rad[traj.phases == int(Phase.PROCESS)]
    path_tcp = kinematics.forward(arm, process) @ params.T_flange_tcp
    lifted_tcp = kinematics.forward(arm, back) @ params.T_flange_tcp
    for T in lifted_tcp:
        below = T[:3, 3] + params.approach_m * T[:3, 2]
        assert np.linalg.norm(path_tcp[:, :3, 3] - below, axis=1).min() < 1e-6
    # Neighbouring stops are close in every joint (a joint move between them stays near the
    # lifted path), and the way goes back towards the path's start.
    assert np.abs(np.diff(back, axis=0)).max() <= 2 * WAY_BACK_TURN_RAD
    assert np.linalg.norm(lifted_tcp[-1, :3, 3] - path_tcp[0, :3, 3]) == pytest.approx(
        params.approach_m, abs=1e-6
    )
    # From anywhere off the plan's way (a jog), no way back: the direct moves' verdict stands.
    assert ways_back(traj, HOME + [0.3, 0, 0, 0, 0, 0], params) == []


@pytest.mark.parametrize(
    "way, words",
    [
        (np.zeros((2, 5)), "shape \\(V, 6\\)"),
        ([[0.0, 0.0, np.nan, 0.0, 0.0, 0.0]], "way 1's stop 1 must be six finite"),
        ([HOME, [0.0, 0.0, 4.0, 0.0, 0.0, 0.0]], "way 1's stop 2 .* outside the ur5e's"),
    ],
    ids=["five-joints", "nan", "past-a-limit"],
)
def test_ways_that_are_not_an_arms_are_refused(way, words):
    with pytest.raises(ValueError, match=words):
        plan_move(HOME, HOME + 0.1, params=PlanParams(robot="ur5e"), ways=[way])
