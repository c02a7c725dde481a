"""Motion benchmarks: planning time, achieved TCP speed, dry-run tracking (``make bench``)."""

from __future__ import annotations

import statistics
import time

import numpy as np
import pytest

from drivers.robot.dryrun import dry_run
from recon import scenes
from recon.kinematics import follow_path, model
from recon.plan import PlanParams, approach_in, normals_from_scan, plan_path
from recon.reconstruct import reconstruct
from recon.timing import limits_for, time_parameterize
from recon.waypoints import coarse_waypoints
from tests.motion_fixtures import base_from_tracker

pytestmark = pytest.mark.bench


def _median(fn, repeats=5):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def test_planning_time():
    print("\n## Planning time (median of 5, seconds)\n")
    print("| waypoints | IK along the path | toppra timing | IK + timing |")
    print("|---:|---:|---:|---:|")
    arm = model("ur5e")
    for n in (100, 1_000, 10_000):
        # The same S-curve on the table (about 0.5 m long) sampled with n waypoints.
        u = np.linspace(0.0, 1.0, n)
        points = np.column_stack(
            [0.35 + 0.1 * np.sin(2 * np.pi * u), -0.2 + 0.4 * u, np.full(n, 0.1)]
        )
        from recon.orient import tool_path

        tool = tool_path(points)
        flange = tool.poses()
        limits = limits_for(arm, 0.05)
        ik = _median(lambda: follow_path(arm, flange))  # noqa: B023
        joints = follow_path(arm, flange)
        timing = _median(lambda: time_parameterize(arm, joints, tool, limits))  # noqa: B023
        print(f"| {n:,} | {ik:.3f} | {timing:.3f} | {ik + timing:.3f} |")
    print("\nTarget: 1k waypoints planned (IK + timing) in under 0.2 s.")


def test_whole_plan_time():
    """The whole plan as the service makes it: tool path, IK in the configuration, toppra
    timing, transit / approach / retract, and the collision check against the mounting plane
    and a scanned plate under the path (about 400k points)."""
    from recon.collision import Cell

    print("\n## Whole plan (median of 3, seconds): IK, timing, phases, collision check\n")
    print("| waypoints | samples | plan without cell | plan with the check | check share |")
    print("|---:|---:|---:|---:|---:|")
    x, y = np.meshgrid(np.arange(0.2, 0.55, 0.0007), np.arange(-0.3, 0.3, 0.0007))
    plate = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 0.05)])
    cell = Cell(scan_points_m=plate)
    for n in (1_000, 10_000):
        u = np.linspace(0.0, 1.0, n)
        points = np.column_stack(
            [0.35 + 0.1 * np.sin(2 * np.pi * u), -0.2 + 0.4 * u, np.full(n, 0.05)]
        )
        params = PlanParams(speed_m_s=0.05)
        bare = _median(lambda: plan_path(points, params=params), repeats=3)  # noqa: B023
        checked = _median(
            lambda: plan_path(points, params=params, cell=cell),  # noqa: B023
            repeats=3,
        )
        samples = len(plan_path(points, params=params).trajectory)
        print(
            f"| {n:,} | {samples:,} | {bare:.2f} | {checked:.2f} | "
            f"{(checked - bare) / checked * 100:.0f} % |"
        )
    print(f"\nScan: {len(plate):,} points. Target: the whole plan within about a second.")


def test_achieved_speed_with_and_without_orientation_smoothing():
    print("\n## Achieved mean TCP speed on the demo paths (tool axis from the scan)\n")
    print("| scene | requested mm/s | smoothing 10 mm | no smoothing |")
    print("|---|---:|---:|---:|")
    T = base_from_tracker()
    for name in ("cylinder_edge", "box_corner", "flat_liftoff"):
        scene = scenes.SCENES[name](0)
        recon = reconstruct(scene.recording, scene.scan)
        normals = normals_from_scan(
            recon.points_m,
            recon.mode,
            recon.scan_model,
            T_scan_tracker=recon.T_scan_tracker,
            approach_tracker=approach_in(T, (0, 0, 1)),
        )
        for speed in (0.05, 0.2):
            cells = []
            for smooth in (0.01, 0.0):
                try:
                    plan = plan_path(
                        recon.points_m,
                        T_base_tracker=T,
                        normals=normals,
                        params=PlanParams(speed_m_s=speed, smooth_m=smooth),
                    )
                    length = plan.tool.arc_length_m[-1]
                    process_s = plan.trajectory.phase_durations_s()["process"]
                    cells.append(f"{length / process_s * 1e3:.1f}")
                except Exception as exc:  # report, do not hide: the table says what failed
                    cells.append(f"failed: {type(exc).__name__}")
            print(f"| {name} | {speed * 1e3:.0f} | {cells[0]} | {cells[1]} |")


def test_dry_run_tracking():
    print(
        "\n## Dry-run tracking on the simulated UR5e (servoJ lookahead 0.1 s, gain 300; "
        "movePath: blended moveJ waypoints)\n"
    )
    print(
        "| scene | speed mm/s | mode | waypoints | off the path, max mm | behind, max mm "
        "| duration s (planned) |"
    )
    print("|---|---:|---|---:|---:|---:|---:|")
    T = base_from_tracker()
    for name in ("cylinder_edge", "box_corner"):
        scene = scenes.SCENES[name](0)
        recon = reconstruct(scene.recording, scene.scan)
        normals = normals_from_scan(
            recon.points_m,
            recon.mode,
            recon.scan_model,
            T_scan_tracker=recon.T_scan_tracker,
            approach_tracker=approach_in(T, (0, 0, 1)),
        )
        for speed in (0.05, 0.1):
            plan = plan_path(
                recon.points_m,
                T_base_tracker=T,
                normals=normals,
                params=PlanParams(speed_m_s=speed),
            )
            arm = model(plan.trajectory.robot)
            for mode, tolerance_m in (("servoj", None), ("movepath", 5e-4), ("movepath", 2e-3)):
                if mode == "servoj":
                    report, label, count = dry_run(plan.trajectory), "servoJ", len(plan.trajectory)
                else:
                    report = dry_run(plan.trajectory, mode=mode, tolerance_m=tolerance_m)
                    label = f"movePath, tolerance {tolerance_m * 1e3:.1f} mm"
                    count = len(coarse_waypoints(arm, plan.trajectory, tolerance_m=tolerance_m))
                print(
                    f"| {name} | {speed * 1e3:.0f} | {label} | {count} | "
                    f"{report.max_path_deviation_m * 1e3:.3f} | {report.max_lag_m * 1e3:.1f} | "
                    f"{report.duration_s:.2f} ({report.planned_duration_s:.2f}) |"
                )
