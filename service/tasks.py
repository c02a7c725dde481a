"""CPU work run in the worker processes: reconstruction, planning, dry runs.

Each task reads its inputs from array files, writes its output with an atomic rename, and
returns a JSON-able summary; it never touches the database (the main process records the
result). Domain errors propagate to the job that ran the task.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np

from drivers.files import atomic_path
from recon.types import PointMode, ReconParams, Recording, Scan


def _save(path: Path, arrays: dict) -> None:
    with atomic_path(path) as tmp, tmp.open("wb") as handle:
        np.savez(handle, **{k: v for k, v in arrays.items() if v is not None})


def _load(path: str) -> dict:
    with np.load(path, allow_pickle=False) as data:
        return {key: data[key] for key in data.files}


def recording_from(arrays: dict) -> Recording:
    return Recording(
        points_m=arrays["points_m"],
        t_s=arrays.get("t_s"),
        orientations_xyzw=arrays.get("orientations_xyzw"),
    )


def scan_from(arrays: dict) -> Scan:
    return Scan(points_m=arrays["points_m"], normals=arrays.get("normals"))


def recording_summary(arrays: dict, fmt: str) -> dict:
    points = arrays["points_m"]
    t = arrays.get("t_s")
    length = float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)))
    return {
        "format": fmt,
        "n_samples": int(len(points)),
        "length_m": length,
        "duration_s": None if t is None else float(t[-1] - t[0]),
        "has_orientations": arrays.get("orientations_xyzw") is not None,
        "bounds_m": [points.min(axis=0).tolist(), points.max(axis=0).tolist()],
    }


def parse_recording_task(
    content: bytes,
    filename: str,
    fmt: str | None,
    units: str | None,
    rigid_body: str | None = None,
    marker: str | None = None,
    tip_offset_m: list | None = None,
    piece: int | None = None,
) -> tuple[dict, dict]:
    """Parse an uploaded trace (in a worker process): read, move to the tip, clean, pick a
    piece. Returns (arrays, summary)."""
    from drivers.tracking.readers import read_trace
    from recon.reconstruct import check_scales

    trace = read_trace(
        content,
        name=filename,
        fmt=fmt,
        units=units,
        rigid_body=rigid_body,
        marker=marker,
        tip_offset_m=None if tip_offset_m is None else np.array(tip_offset_m),
        piece=piece,
        # The session's offset is for rigid-body recordings; a position-only file holds tip
        # positions already (the summary says the offset was not applied).
        tip_needs_orientations=False,
    )
    recording = trace.recording
    check_scales(recording.points_m, None)
    arrays = recording_arrays(recording)
    summary = recording_summary(arrays, trace.format)
    summary.update(trace.summary())
    if tip_offset_m is not None and not trace.tip_offset_applied:
        summary.setdefault("notes", []).append(
            "the session's tip offset was not applied: the file has positions only (taken "
            "as the pen's tip)"
        )
    return arrays, summary


def recording_arrays(recording: Recording) -> dict:
    return {
        "points_m": np.array(recording.points_m),
        "t_s": recording.t_s,
        "orientations_xyzw": recording.orientations_xyzw,
    }


def pivot_task(
    content: bytes,
    filename: str,
    fmt: str | None,
    units: str | None,
    rigid_body: str | None,
    marker: str | None,
) -> dict:
    """A pivot calibration from an uploaded recording (in a worker process)."""
    from drivers.tracking.readers import read_raw_trace, require_orientations
    from recon.calibrate import pivot_calibration

    raw = read_raw_trace(
        content, name=filename, fmt=fmt, units=units, rigid_body=rigid_body, marker=marker
    )
    require_orientations(raw, "a pivot calibration")
    batch = raw.batch
    q = np.asarray(batch.orientation_xyzw, dtype=np.float64)
    good = (
        np.asarray(batch.valid, dtype=bool)
        & np.isfinite(batch.position_m).all(axis=1)
        & np.isfinite(q).all(axis=1)
    )
    q = q[good] / np.linalg.norm(q[good], axis=1)[:, None]
    result = pivot_calibration(np.asarray(batch.position_m)[good], q)
    return {
        "tip_offset_m": result.tip_offset_m.tolist(),
        "pivot_point_m": result.pivot_point_m.tolist(),
        "residual_rms_m": result.residual_rms_m,
        "residual_max_m": result.residual_max_m,
        "rotation_spread_deg": result.rotation_spread_deg,
        "n_used": result.n_used,
        "n_rejected": result.n_rejected,
        "n_lost": int(np.count_nonzero(~good)),
        "rigid_body": raw.meta.get("rigid_body"),
        "format": raw.format,
    }


def parse_scan_task(
    content: bytes,
    filename: str,
    fmt: str | None,
    units: str,
    options: dict | None = None,
    limits: dict | None = None,
) -> tuple[dict, dict]:
    """Parse an uploaded scan (in a worker process). Returns (arrays, summary)."""
    from drivers.scanning.pointcloud import read_scan

    scan_file = read_scan(
        content, name=filename, fmt=fmt, units=units, options=options, limits=limits
    )
    scan = scan_file.scan
    points = np.array(scan.points_m)
    return (
        {"points_m": points, "normals": scan.normals},
        {
            "format": scan_file.format,
            "n_points": int(len(points)),
            "n_dropped": scan_file.n_dropped,
            "has_normals": scan.normals is not None,
            "notes": list(scan_file.notes),
            "bounds_m": [points.min(axis=0).tolist(), points.max(axis=0).tolist()],
        },
    )


def reconstruct_task(
    recording_path: str,
    scan_path: str | None,
    params: dict,
    out_path: str,
    preview_path: str,
    T_scan_tracker_init: list | None = None,
) -> dict:
    """Reconstruct; write the result's arrays and a PNG preview; return a summary."""
    from recon.align import apply_transform, invert_transform
    from recon.reconstruct import reconstruct
    from service.plots import plot_reconstruction

    recording = recording_from(_load(recording_path))
    scan = scan_from(_load(scan_path)) if scan_path else None
    init = None if T_scan_tracker_init is None else np.array(T_scan_tracker_init)
    recon = reconstruct(recording, scan, params=ReconParams(**params), T_scan_tracker_init=init)
    reg = recon.registration
    # The scan's frame as used: registered, else the stored calibration, else the tracker's.
    T_used = reg.T_scan_tracker if reg is not None else init
    _save(
        Path(out_path),
        {
            "points_m": recon.points_m,
            "input_points_m": recon.input_points_m,
            "t_s": recon.t_s,
            "orientations_xyzw": recon.orientations_xyzw,
            "displacement_m": recon.displacement_m,
            "mode": recon.mode,
            "segment": recon.segment,
            "n_path": recon.n_path,
            "n_surface": recon.n_surface,
            "residual_path_m": recon.residual_path_m,
            "residual_surface_m": recon.residual_surface_m,
            "alpha": recon.alpha,
            "T_scan_tracker": T_used,
        },
    )
    scan_tracker = None
    if scan is not None:
        T = np.eye(4) if T_used is None else invert_transform(T_used)
        scan_tracker = apply_transform(T, scan.points_m)
    plot_reconstruction(preview_path, recon, scan_m=scan_tracker, title="reconstruction")
    return {
        "n_points": len(recon),
        "modes": {m.label: recon.count(m) for m in PointMode},
        "mean_displacement_m": float(recon.displacement_m.mean()),
        "max_displacement_m": float(recon.displacement_m.max()),
        "segments": [asdict(s) for s in recon.segments],
        "T_scan_tracker": None if T_used is None else T_used.tolist(),
        "registration": None
        if reg is None
        else {
            "T_scan_tracker": reg.T_scan_tracker.tolist(),
            "rmse_m": reg.rmse_m,
            "fitness": reg.fitness,
            "n_pairs": reg.n_pairs,
            "target": reg.target,
            "constrained_dof": reg.constrained_dof,
        },
        "notes": list(recon.notes),
    }


def plan_task(
    reconstruction_path: str,
    scan_path: str | None,
    params: dict,
    T_base_tracker: list | None,
    T_scan_tracker: list | None,
    out_path: str,
) -> dict:
    """Plan a trajectory along a stored reconstruction; write it; return the report."""
    from recon.plan import PlanParams, approach_in, normals_from_scan, plan_path

    recon = _load(reconstruction_path)
    plan_params = PlanParams(**params)
    T = None if T_base_tracker is None else np.array(T_base_tracker)
    normals = None
    if scan_path and plan_params.orientation in ("auto", "scan"):
        normals, _ = normals_from_scan(
            recon["points_m"],
            recon["mode"],
            scan_from(_load(scan_path)),
            approach_tracker=approach_in(T, plan_params.approach),
            T_scan_tracker_init=None if T_scan_tracker is None else np.array(T_scan_tracker),
        )
    plan = plan_path(
        recon["points_m"],
        params=plan_params,
        T_base_tracker=T,
        normals=normals,
        pen_xyzw=recon.get("orientations_xyzw"),
    )
    traj = plan.trajectory
    _save(
        Path(out_path),
        {
            "t_s": traj.t_s,
            "q_rad": traj.q_rad,
            "qd_rad_s": traj.qd_rad_s,
            "qdd_rad_s2": traj.qdd_rad_s2,
            "tcp_m": traj.tcp_m,
            "tcp_rotvec": traj.tcp_rotvec,
            "arc_length_m": traj.arc_length_m,
        },
    )
    joints = plan.joints
    return {
        "robot": traj.robot,
        "requested_speed_m_s": traj.requested_speed_m_s,
        "duration_s": traj.duration_s,
        "n_samples": len(traj),
        "rate_hz": 1.0 / traj.period_s,
        "path_length_m": float(plan.tool.arc_length_m[-1]),
        "tool_axis_from": plan.tool.source,
        "ik_branch": joints.branch,
        "min_limit_margin_rad": float(joints.limit_margin_rad.min()),
        "min_wrist_singularity": float(joints.wrist_singularity.min()),
        "min_elbow_singularity": float(joints.elbow_singularity.min()),
        "min_shoulder_margin_m": float(joints.shoulder_margin_m.min()),
        "speed_drops": [asdict(d) for d in traj.speed_drops],
        "report": plan.report_lines(),
    }


def load_trajectory(path: str, robot: str, requested_speed_m_s: float):
    from recon.types import JointTrajectory

    data = _load(path)
    return JointTrajectory(robot=robot, requested_speed_m_s=requested_speed_m_s, **data)


def dry_run_task(
    trajectory_path: str,
    robot: str,
    requested_speed_m_s: float,
    speed_drops: list,
    out_path: str,
    mode: str = "servoj",
    tolerance_m: float = 5e-4,
) -> dict:
    """Execute a stored trajectory on the simulated arm; write the record; return the report."""
    from dataclasses import replace

    from drivers.robot.base import create_backend
    from drivers.robot.clock import FakeClock
    from drivers.robot.dryrun import dry_run
    from drivers.robot.sim import SimConfig
    from recon.types import SpeedDrop

    trajectory = load_trajectory(trajectory_path, robot, requested_speed_m_s)
    trajectory = replace(trajectory, speed_drops=tuple(SpeedDrop(**d) for d in speed_drops))
    sim = create_backend(
        SimConfig(robot=robot, q_start_rad=tuple(trajectory.q_rad[0])), clock=FakeClock()
    )
    report = dry_run(trajectory, backend=sim, mode=mode, tolerance_m=tolerance_m)
    record = sim.last_record
    _save(
        Path(out_path),
        {
            "t_s": None if record is None else record.t_s,
            "q_planned_rad": None if record is None else record.q_planned_rad,
            "q_actual_rad": None if record is None else record.q_actual_rad,
        },
    )
    summary = asdict(report)
    summary["report"] = report.lines()
    return summary
