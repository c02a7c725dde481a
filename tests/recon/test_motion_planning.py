"""Tool orientation, timing and the planning pipeline, against analytic cases and limits."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon import scenes
from recon.errors import InfeasibleTrajectoryError
from recon.kinematics import HOME_Q_RAD, forward, model
from recon.metrics import distance_to_curve
from recon.orient import smooth_directions, tool_path
from recon.paths import Phase
from recon.plan import PlanParams, approach_in, normals_from_scan, plan_path
from recon.reconstruct import reconstruct
from recon.timing import limits_for
from recon.trajectory import SAMPLE_FIELDS
from tests.motion_fixtures import base_from_tracker, line_plan


def test_fixed_tool_points_down_and_heads_along_the_path():
    s = np.linspace(0, 0.1, 101)
    tool = tool_path(np.column_stack([s, 0 * s, 0 * s]))
    R = Rotation.from_quat(tool.orientations_xyzw).as_matrix()
    np.testing.assert_allclose(R[:, :, 2], np.tile([0, 0, -1.0], (101, 1)), atol=1e-12)
    np.testing.assert_allclose(R[:, :, 0], np.tile([1.0, 0, 0], (101, 1)), atol=1e-12)
    assert tool.source == "fixed"


def test_lead_leans_the_tool_axis_towards_the_direction_of_travel():
    s = np.linspace(0, 0.1, 101)
    tool = tool_path(np.column_stack([s, 0 * s, 0 * s]), lead_deg=10.0)
    axis = Rotation.from_quat(tool.orientations_xyzw).apply([0.0, 0.0, 1.0])
    np.testing.assert_allclose(
        axis[50], [np.sin(np.radians(10)), 0, -np.cos(np.radians(10))], atol=1e-12
    )


def test_tool_axis_is_minus_the_scan_normal():
    s = np.linspace(0, 0.1, 101)
    normal = np.tile([0.0, -np.sin(0.3), np.cos(0.3)], (101, 1))
    tool = tool_path(np.column_stack([s, 0 * s, 0 * s]), normals=normal)
    axis = Rotation.from_quat(tool.orientations_xyzw).apply([0.0, 0.0, 1.0])
    np.testing.assert_allclose(axis, -normal, atol=1e-9)


def test_orientation_smoothing_removes_noise_on_the_sphere():
    rng = np.random.default_rng(0)
    truth = np.tile([0.0, 0.0, 1.0], (500, 1))
    noisy = truth + rng.normal(0, np.radians(0.4), (500, 3))
    noisy /= np.linalg.norm(noisy, axis=1)[:, None]
    smooth = smooth_directions(noisy, sigma_points=10)
    angle = lambda v: np.degrees(np.arccos(np.clip(v @ [0, 0, 1.0], -1, 1)))  # noqa: E731
    assert angle(smooth).max() < 0.25 * angle(noisy).max()
    np.testing.assert_allclose(np.linalg.norm(smooth, axis=1), 1.0)


def test_every_sample_respects_the_limits_and_straight_speed_is_exact():
    plan = line_plan("ur5e", 0.1)
    whole = plan.trajectory
    arm = model("ur5e")
    # Every phase of the whole motion keeps the limits, on the controller's grid.
    assert np.all(np.abs(whole.qd_rad_s) <= arm.qd_max_rad_s * 1.001)
    assert np.all(np.abs(whole.qdd_rad_s2) <= arm.qdd_max_rad_s2 * 1.001)
    assert np.all(np.diff(whole.t_s) == pytest.approx(0.002))
    # The whole motion starts and ends at rest.
    assert np.abs(whole.qd_rad_s[[0, -1]]).max() < 1e-9
    traj = whole.of_phase(Phase.PROCESS)
    # TCP speed from the planned joints (forward kinematics and the TCP, not the planner's own
    # numbers).
    tcp = (forward(arm, traj.q_rad) @ plan.params.T_flange_tcp)[:, :3, 3]
    speed = np.linalg.norm(np.diff(tcp, axis=0), axis=1) / np.diff(traj.t_s)
    cruise = speed[len(speed) // 3 : 2 * len(speed) // 3]
    assert np.abs(cruise / 0.1 - 1).max() < 0.01
    assert speed.max() <= 0.1 * 1.01
    # The process phase ends at rest, on the path.
    assert np.abs(traj.qd_rad_s[-1]).max() < 1e-9
    assert distance_to_curve(tcp, plan.tool.points_m).max() < 1e-4


@pytest.mark.parametrize("robot", ["ur3e", "ur10e", "ur16e", "ur20", "ur30", "ur3", "ur5", "ur10"])
def test_other_arms_plan_at_their_own_rate(robot):
    plan = line_plan(robot, 0.05)
    rate = 125.0 if robot in ("ur3", "ur5", "ur10") else 500.0
    assert plan.trajectory.period_s == pytest.approx(1 / rate)
    assert np.all(np.abs(plan.trajectory.qd_rad_s) <= model(robot).qd_max_rad_s * 1.001)


def test_a_speed_the_joints_cannot_give_is_reported_with_its_cause():
    # Orbit a small circle with the tool heading along it: joint 6 has to turn fast.
    a = np.linspace(0, 2 * np.pi, 400)
    points = np.column_stack([0.45 + 0.03 * np.cos(a), 0.1 + 0.03 * np.sin(a), 0.1 + 0 * a])
    plan = plan_path(points, params=PlanParams(speed_m_s=0.5))
    drops = plan.trajectory.speed_drops
    assert drops, "a 30 mm circle at 0.5 m/s must be slower than requested somewhere"
    assert all(d.min_speed_m_s < 0.5 * 0.95 for d in drops)
    assert all("joint" in d.cause or "singularity" in d.cause for d in drops)


def test_out_of_reach_path_names_the_waypoint():
    s = np.linspace(0, 0.1, 101)
    with pytest.raises(InfeasibleTrajectoryError, match="waypoint 0 .*ur5e"):
        plan_path(np.column_stack([1.2 + s, 0 * s, 0 * s]), params=PlanParams())


def test_bad_plan_parameters():
    with pytest.raises(ValueError, match="speed_m_s"):
        limits_for(model("ur5e"), 5.0)
    with pytest.raises(ValueError):
        PlanParams(robot="abb")
    with pytest.raises(ValueError):
        PlanParams(lead_deg=80)
    with pytest.raises(ValueError, match="orientation 'pen'"):
        plan_path(
            np.column_stack([np.linspace(0.4, 0.5, 50), np.zeros(50), np.full(50, 0.1)]),
            params=PlanParams(orientation="pen"),
        )


def test_the_reconstructed_demo_path_plans_with_scan_normals():
    scene = scenes.cylinder_edge(0)
    recon = reconstruct(scene.recording, scene.scan)
    T = base_from_tracker()
    params = PlanParams(speed_m_s=0.05)
    normals = normals_from_scan(
        recon.points_m,
        recon.mode,
        recon.scan_model,
        T_scan_tracker=recon.T_scan_tracker,
        approach_tracker=approach_in(T, params.approach_direction),
    )
    assert normals.known.all() and recon.registration is not None
    # At the rim the tool axis bisects the top face and the wall: (cos a, sin a, 1)/sqrt 2 out.
    a = np.arctan2(recon.points_m[:, 1], recon.points_m[:, 0])
    expected = np.column_stack([np.cos(a), np.sin(a), np.ones_like(a)]) / np.sqrt(2)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", normals.normals, expected), -1, 1)))
    assert np.median(angle) < 2.0
    plan = plan_path(recon.points_m, params=params, T_base_tracker=T, normals=normals)
    assert plan.tool.source == "scan"
    durations = plan.trajectory.phase_durations_s()
    assert durations["process"] == pytest.approx(0.3 / 0.05, rel=0.1)


def test_the_vectorised_samples_are_toppras_own():
    """``ConstAccelTiming`` evaluates toppra's constant-acceleration parametrisation on whole
    arrays: the same numbers as toppra's ``ParametrizeConstAccel`` at every sample, the end and
    times past the end included."""
    import toppra
    import toppra.algorithm
    import toppra.constraint

    from recon.timing import ConstAccelTiming, _sample

    s = np.linspace(0.0, 0.3, 40)
    q = np.column_stack([np.sin(3 * s + k) for k in range(6)] + [s])
    path = toppra.SplineInterpolator(s, q)
    constraints = [
        toppra.constraint.JointVelocityConstraint(np.tile([-1.0, 1.0], (7, 1))),
        toppra.constraint.JointAccelerationConstraint(np.tile([-2.0, 2.0], (7, 1))),
    ]
    instance = toppra.algorithm.TOPPRA(
        constraints, path, gridpoints=np.linspace(0, 0.3, 301), parametrizer="ParametrizeConstAccel"
    )
    reference = instance.compute_trajectory(0.0, 0.0)
    timing = ConstAccelTiming(instance.problem_data.gridpoints, instance.problem_data.sd_vec)
    assert timing.t_s[-1] == reference.duration
    samples = _sample(path, timing, 500.0)
    at = np.minimum(samples["t"], reference.duration)
    inside = samples["t"] <= reference.duration
    np.testing.assert_array_equal(samples["x"], reference(at))
    np.testing.assert_array_equal(samples["xd"][inside], reference(at, 1)[inside])
    np.testing.assert_array_equal(samples["xdd"][inside], reference(at, 2)[inside])
    assert samples["t"][-1] >= reference.duration > samples["t"][-2]
    np.testing.assert_array_equal(samples["xd"][~inside], 0.0)  # held at rest past the end
    assert len(samples["t"]) > 100


def test_a_summary_lists_the_slowest_speed_drops_and_counts_the_rest():
    from recon.paths import LISTED_SPEED_DROPS, SpeedDrop, speed_drop_lines

    assert speed_drop_lines([]) == []
    few = [SpeedDrop(0.1 * i, 0.1 * i + 0.01, 0.05 + 0.001 * i, "joint speed") for i in range(3)]
    assert len(speed_drop_lines(few)) == 3
    # 40 drops, the slowest (20 mm/s) at 2.0 m: listed first among the few, in path order.
    many = [SpeedDrop(0.1 * i, 0.1 * i + 0.02, 0.09 - 0.001 * (i % 7), "turn") for i in range(40)]
    many[20] = SpeedDrop(2.0, 2.05, 0.02, "a tight curve")
    lines = speed_drop_lines(many)
    assert len(lines) == LISTED_SPEED_DROPS + 1
    assert "from 2000 to 2050 mm of path (down to 20.0 mm/s): a tight curve" in "".join(lines)
    starts = [float(line.split()[4]) for line in lines[:-1]]
    assert starts == sorted(starts)
    assert lines[-1].startswith(f"... and {40 - LISTED_SPEED_DROPS} more stretches")
    assert "40 in all over 830 mm of path" in lines[-1]
    listed = [float(line.split("down to ")[1].split()[0]) for line in lines[:-1]]
    assert f"none below {max(listed):.1f} mm/s" in lines[-1]


@pytest.mark.parametrize("robot", ["ur3e", "ur3"])
@pytest.mark.parametrize("start_deg", [-180, -90, -45, 90])
def test_the_ur3s_endless_wrist_3_plans_a_half_circle_the_ur5e_plans(robot, start_deg):
    """A 180-degree arc of 80 mm radius 0.3 m in front of the base: the UR5e planned it, the
    UR3e refused ("the retract line does not join the path (360.00 deg apart)") on five of
    eight start angles: its endless wrist 3 was never shifted by whole turns towards the joined
    phase. Now it plans, and the retract joins the path exactly."""
    a = np.radians(np.linspace(start_deg, start_deg + 180, 181))
    points = np.column_stack([0.30 + 0.08 * np.cos(a), 0.08 * np.sin(a), np.full_like(a, 0.05)])
    plan = plan_path(points, params=PlanParams(robot=robot, speed_m_s=0.05))
    q, phases = plan.trajectory.q_rad, plan.trajectory.phases
    assert np.abs(np.diff(q, axis=0)).max() < 0.05  # continuous: no turn skipped at a join
    process = np.flatnonzero(phases == int(Phase.PROCESS))
    print(
        f"\n{robot}, arc from {start_deg} deg: wrist 3 over the process "
        f"{np.degrees(q[process, 5].min()):.0f}..{np.degrees(q[process, 5].max()):.0f} deg"
    )


MOUNTS = {
    # up (away from the earth's centre) in the base frame, and a short line on the work there
    "floor": ((0.0, 0.0, 1.0), (0.40, 0.10, 0.05)),
    "ceiling": ((0.0, 0.0, -1.0), (0.40, 0.10, 0.40)),
    "wall": ((1.0, 0.0, 0.0), (-0.45, 0.25, 0.35)),
}


@pytest.mark.parametrize("mount", MOUNTS)
def test_the_tool_comes_at_the_work_from_above_on_every_mount(mount):
    """The approach was fixed to the base's +z: hanging from a ceiling the tool came at the
    part from below, on a wall its axis lay horizontal. The mount's up now drives the approach,
    the retract and the fixed tool axis; the motion is checked against the mounting plane."""
    from recon.collision import Cell

    up, centre = MOUNTS[mount]
    up = np.asarray(up)
    line = np.asarray(centre) + np.outer(np.linspace(-0.05, 0.05, 101), [0.0, 1.0, 0.0])
    params = PlanParams(mount_up=tuple(up), speed_m_s=0.05, orientation="fixed")
    plan = plan_path(line, params=params, cell=Cell())
    trajectory = plan.trajectory
    T = forward(model("ur5e"), trajectory.q_rad) @ params.T_flange_tcp
    process = trajectory.phases == int(Phase.PROCESS)
    # The tool's axis points down, into the work, all along the path.
    np.testing.assert_allclose(T[process][:, :3, 2] @ up, -1.0, atol=1e-6)
    # The approach starts approach_m above the first point and the retract ends above the last.
    approach = T[trajectory.phases == int(Phase.APPROACH)]
    retract = T[trajectory.phases == int(Phase.RETRACT)]
    assert (approach[0, :3, 3] - line[0]) @ up == pytest.approx(params.approach_m, abs=1e-4)
    assert (retract[-1, :3, 3] - line[-1]) @ up == pytest.approx(params.approach_m, abs=1e-4)
    assert plan.collision is not None and plan.collision.clear


def test_a_configuration_that_collides_is_not_the_end_when_another_is_allowed():
    """With elbow "any" the planner took the branch with the best margins, and a collision of
    its motion refused the plan though another configuration was clear. Now the next best
    allowed configuration is tried; one fixed in every word is still refused."""
    from recon.collision import Box, Cell
    from recon.errors import CollisionError
    from recon.kinematics import joint_frames

    line = np.array([0.4, 0.2, 0.3]) + np.outer(np.linspace(-0.05, 0.05, 101), [1.0, 0, 0])
    free = PlanParams(speed_m_s=0.05, orientation="fixed", elbow="any")
    first = plan_path(line, params=free, cell=Cell())
    chosen = first.configuration
    # A fixture where that configuration's elbow passes in the middle of the path.
    process = first.trajectory.phases == int(Phase.PROCESS)
    elbow = joint_frames(model("ur5e"), first.trajectory.q_rad[process])[:, 2, :3, 3]
    centre = elbow[len(elbow) // 2]
    cell = Cell(boxes=(Box(centre - 0.03, centre + 0.03, name="fixture"),))
    fixed = PlanParams(
        speed_m_s=0.05, orientation="fixed",
        shoulder=chosen.shoulder, elbow=chosen.elbow, wrist=chosen.wrist,
    )  # fmt: skip
    with pytest.raises(CollisionError, match="fixture"):
        plan_path(line, params=fixed, cell=cell)
    retried = plan_path(line, params=free, cell=cell)
    assert retried.configuration != chosen and retried.collision.clear
    print(f"\nfirst {chosen.words()}: collides; then {retried.configuration.words()}: clear")


def test_a_motion_that_passes_within_the_joint_margin_of_a_limit_is_refused():
    """A plan 0.4 deg from a wrist's limit was accepted. Every sample keeps joint_margin_deg
    (5 deg by default) from every limit, or the plan is refused naming the joint and where."""
    from recon.errors import InfeasibleTrajectoryError

    line = np.array([0.4, 0.1, 0.1]) + np.outer(np.linspace(-0.05, 0.05, 51), [0, 1.0, 0])
    near = np.array(HOME_Q_RAD) + [0, 0, 0, 0, 0, 2 * np.pi - np.radians(0.4)]
    params = PlanParams(speed_m_s=0.05, orientation="fixed", start_q_rad=tuple(near))
    with pytest.raises(InfeasibleTrajectoryError, match=r"joint 6 comes 0\.4 deg from its limit"):
        plan_path(line, params=params)
    relaxed = PlanParams(
        speed_m_s=0.05, orientation="fixed", start_q_rad=tuple(near), joint_margin_deg=0.0
    )
    assert plan_path(line, params=relaxed).trajectory.duration_s > 0


def test_a_round_tool_free_about_its_axis_keeps_wrist_3_still_on_a_three_turn_circle():
    """With the x axis along the travel, a three-turn circle turns the tool three times about
    its own axis (1074 deg of joint 6 for the tester, refused). Free about the axis (a round
    tool, the default), the heading is carried without twist and wrist 3 stays nearly still."""
    a = np.linspace(0.0, 6 * np.pi, 1801)
    circle = np.column_stack(
        [0.45 + 0.03 * np.cos(a), 0.1 + 0.03 * np.sin(a), np.full_like(a, 0.1)]
    )
    free = plan_path(circle, params=PlanParams(speed_m_s=0.05, orientation="fixed"))
    process = free.trajectory.phases == int(Phase.PROCESS)
    q6 = free.trajectory.q_rad[process, 5]
    turned_deg = np.degrees(q6.max() - q6.min())
    print(f"\nthree turns, heading free: joint 6 turns {turned_deg:.1f} deg")
    assert turned_deg < 30
    along = PlanParams(speed_m_s=0.05, orientation="fixed", heading="travel")
    with pytest.raises(InfeasibleTrajectoryError, match="joint 6"):
        plan_path(circle, params=along)


def test_the_varying_speed_bound_gives_toppra_the_same_limits_as_one_call_per_gridpoint(
    monkeypatch,
):
    """The point-speed bound hands toppra its limits for the whole grid at once; a plan made so
    is the plan made with toppra's own one-call-per-gridpoint constraint, bit for bit."""
    import toppra.constraint

    from recon import timing

    s = np.linspace(0.0, 0.3, 301)
    # A line whose tool turns about its tip: the flange's speed, not the tip's, binds.
    points = np.column_stack([0.4 + 0 * s, -0.15 + s, np.full_like(s, 0.1)])
    params = PlanParams(robot="ur5e", speed_m_s=0.25)
    fast = plan_path(points, params=params).trajectory

    def scalar_bound(bound, s_m):
        """The bound at one position, written out as it was before the table (the lower of
        the two stations around it)."""
        i = int(np.clip(np.searchsorted(bound.stations_m, s_m), 0, len(bound.stations_m) - 1))
        j = i if bound.bound_m_s[i] <= bound.bound_m_s[max(i - 1, 0)] else max(i - 1, 0)
        return float(bound.bound_m_s[j]), int(bound.binding[j])

    def one_call_per_gridpoint(bound, vlim):
        def limits_at(s_m):
            out = np.array(vlim, dtype=np.float64)
            speed = scalar_bound(bound, s_m)[0]
            out[-1] = (-speed, speed)
            return out

        return toppra.constraint.JointVelocityConstraintVarying(limits_at)

    monkeypatch.setattr(timing.PointSpeedBound, "constraint", one_call_per_gridpoint)
    reference = plan_path(points, params=params).trajectory
    assert len(fast) == len(reference)
    for name in SAMPLE_FIELDS:
        assert np.array_equal(getattr(fast, name), getattr(reference, name)), name
    # And the bound's table is the bound, position by position.
    bound = timing.PointSpeedBound(
        np.array([0.0, 0.1, 0.2]), np.array([0.3, 0.1, 0.2]), np.array([0, 2, 1]), 0.3
    )
    grid = np.array([0.0, 0.05, 0.1, 0.15, 0.2, 0.25])
    speeds, points = bound.along_grid(grid)
    assert [scalar_bound(bound, x) for x in grid] == list(zip(speeds, points, strict=True))
    assert bound.at(0.05) == (0.1, 2) and bound.at(0.15) == (0.1, 2) and bound.at(0.0) == (0.3, 0)
