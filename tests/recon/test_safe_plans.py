"""Plans that keep the arm out of the table and the workpiece, on the scenes the integrator
found them wrong on (issue: the elbow under the table, unplanned moves to the start)."""

import numpy as np
import pytest

from drivers.robot.dryrun import dry_run
from recon import scenes
from recon.collision import Cell
from recon.errors import CollisionError
from recon.kinematics import joint_frames, model
from recon.plan import PlanParams, approach_in, normals_from_scan, plan_path
from recon.reconstruct import reconstruct
from recon.transforms import apply_transform, invert_transform

#: Where the demo places the cylinder in front of the arm (service.demo).
DEMO_T_BASE_TRACKER = np.array(
    [[1.0, 0, 0, 0.45], [0, 1.0, 0, 0.1], [0, 0, 1.0, 0.05], [0, 0, 0, 1.0]]
)


@pytest.fixture(scope="module")
def cylinder():
    scene = scenes.cylinder_edge(0)
    recon = reconstruct(scene.recording, scene.scan)
    return scene, recon


def _plan(cylinder, *, with_scan: bool = True, **changes):
    scene, recon = cylinder
    params = PlanParams(**{"speed_m_s": 0.05, **changes})
    T = DEMO_T_BASE_TRACKER
    normals = normals_from_scan(
        recon.points_m,
        recon.mode,
        recon.scan_model,
        T_scan_tracker=recon.T_scan_tracker,
        approach_tracker=approach_in(T, params.approach_direction),
    )
    scan_base = apply_transform(T @ invert_transform(recon.T_scan_tracker), scene.scan.points_m)
    return plan_path(
        recon.points_m,
        params=params,
        T_base_tracker=T,
        normals=normals,
        cell=Cell(scan_points_m=scan_base if with_scan else None),
    )


def test_the_default_plan_keeps_every_joint_above_the_table(cylinder):
    plan = _plan(cylinder)
    assert plan.configuration.elbow == "up"
    frames = joint_frames(model("ur5e"), plan.trajectory.q_rad)
    # Every joint from the shoulder on, at every sample of every phase, above the mounting
    # plane (the base's z = 0), and the whole motion cleared against the cell.
    lowest_m = frames[:, 2:, 2, 3].min()
    print(f"lowest joint {lowest_m * 1e3:.0f} mm above the table")
    assert lowest_m > 0.05
    assert plan.collision is not None and plan.collision.clear


@pytest.mark.slow
def test_elbow_down_over_the_demo_cylinder_is_refused_naming_why(cylinder):
    # Against the table alone: the elbow goes under it.
    with pytest.raises(CollisionError) as refused:
        _plan(cylinder, with_scan=False, elbow="down")
    detail = refused.value.detail
    assert detail["obstacle"] == "mounting plane", detail
    assert detail["link"] in ("upper arm", "elbow", "forearm"), detail
    assert "mounting plane" in str(refused.value)
    # With the workpiece too: refused at the first thing the arm meets, named.
    with pytest.raises(CollisionError) as refused:
        _plan(cylinder, elbow="down")
    assert refused.value.detail["link"] != "tool"
    assert refused.value.detail["obstacle"] in ("mounting plane", "scan")


@pytest.mark.slow
def test_a_tool_tilted_into_the_workpiece_is_refused_with_its_link_and_place():
    """A flat plate: the tool tilted 60 deg sideways, 30 mm thick, lies on the plate."""
    scene = scenes.flat_liftoff(0)
    recon = reconstruct(scene.recording, scene.scan)
    params = PlanParams(speed_m_s=0.05, tilt_deg=60.0, tool_radius_m=0.03)
    T = DEMO_T_BASE_TRACKER
    normals = normals_from_scan(
        recon.points_m,
        recon.mode,
        recon.scan_model,
        T_scan_tracker=recon.T_scan_tracker,
        approach_tracker=approach_in(T, params.approach_direction),
    )
    scan_base = apply_transform(T @ invert_transform(recon.T_scan_tracker), scene.scan.points_m)
    with pytest.raises(CollisionError) as refused:
        plan_path(
            recon.points_m,
            params=params,
            T_base_tracker=T,
            normals=normals,
            cell=Cell(scan_points_m=scan_base),
        )
    detail = refused.value.detail
    assert detail["link"] == "tool" and detail["obstacle"] == "scan", detail
    # The place is on the plate (its top is z = 0 of the tracker, 50 mm up in the base frame).
    point = np.array(detail["point_m"])
    assert abs(point[2] - 0.05) < 0.005 and detail["clearance_m"] < detail["margin_m"]
    assert "tool" in str(refused.value) and "scan" in str(refused.value)


@pytest.mark.slow
def test_a_far_start_is_planned_shown_and_dry_run_with_its_duration(cylinder):
    near = _plan(cylinder)
    runs = near.trajectory.runs()
    approach_q = near.trajectory.q_rad[runs[1][1].start]
    far_start = approach_q + [1.5, 0.0, 0.0, 0.0, 0.0, 0.0]  # the base turned away
    far = _plan(cylinder, start_q_rad=tuple(far_start))
    traj = far.trajectory
    np.testing.assert_allclose(traj.q_rad[0], far_start)
    planned = traj.phase_durations_s()
    # The base's 1.5 rad take at least 1.5 rad / its top speed at the transit's scale.
    arm = model("ur5e")
    fastest_s = 1.5 / (arm.qd_max_rad_s[0] * far.params.transit_speed_scale)
    assert planned["transit"] >= fastest_s
    assert any(f"transit {planned['transit']:.2f} s" in line for line in far.report_lines())
    report = dry_run(traj)
    assert report.completed
    # A completed run got through every phase as planned (servoJ's lookahead, the arm waiting
    # at the start, is not counted into the transit any more: 0.1 s more than planned was).
    assert report.executed_phase_durations_s["transit"] == pytest.approx(
        planned["transit"], abs=0.02
    )
    # The speed reported is the path's, however long the transit took.
    path_speed = far.tool.arc_length_m[-1] / planned["process"]
    assert report.mean_speed_m_s == pytest.approx(path_speed, rel=0.01)
    assert report.min_elbow_singularity == pytest.approx(
        far.joints.elbow_singularity.min(), abs=0.05
    )
    # The simulated arm follows the planned transit: nothing outside the plan.
    assert report.max_deviation_by_phase_m["transit"] < 2e-3


def test_no_point_of_the_arm_passes_the_speed_cap_in_any_phase(cylinder):
    """At 0.25 m/s on the demo cylinder the wrists reached 620 mm/s in the process (the tool
    turns about its tip) and 265 mm/s in the transit, over a 250 mm/s cap that a real arm's
    safety limits (the elbow's, the tool's) hold for every point. Now every speed point of the
    arm keeps under the fastest TCP speed any phase asks for, and the real-arm gate's sample
    check, which judges every point, passes the plan."""
    from recon.kinematics import SPEED_POINT_NAMES, speed_points_m
    from recon.paths import Phase
    from recon.sample_check import sample_problems

    plan = _plan(cylinder, speed_m_s=0.25, transit_tcp_speed_m_s=0.25)
    trajectory, arm = plan.trajectory, model("ur5e")
    T_ft = PlanParams().T_flange_tcp
    points = speed_points_m(arm, trajectory.q_rad, T_ft)
    speed = np.linalg.norm(np.diff(points, axis=0), axis=-1) / trajectory.period_s
    for phase in Phase:
        rows = trajectory.phases[1:] == int(phase)
        if rows.any():
            fastest_mm_s = np.round(speed[rows].max(axis=0) * 1e3).tolist()
            fastest = dict(zip(SPEED_POINT_NAMES, fastest_mm_s, strict=True))
            print(f"{phase.label}: {fastest} mm/s")
    assert speed.max() <= 0.25 * 1.001
    problems = sample_problems(
        arm, trajectory.t_s, trajectory.q_rad, tcp_speed_max_m_s=0.25, T_flange_tcp=T_ft
    )
    assert problems == []
    # The same samples judged against a lower cap: the first point over it is named.
    (slow,) = [
        p
        for p in sample_problems(
            arm, trajectory.t_s, trajectory.q_rad, tcp_speed_max_m_s=0.1, T_flange_tcp=T_ft
        )
        if p.check == "link_speed"
    ]
    assert (
        any(name in slow.message for name in SPEED_POINT_NAMES[:-1]) and "100 mm/s" in slow.message
    )
