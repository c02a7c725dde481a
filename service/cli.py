"""The ``teachpath`` command line.

Every command turns bad input into one line on stderr that says what is wrong and what to do, and
a non-zero exit status; it never leaves a partial output file behind.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from drivers.errors import DriverError, InputFileError
from recon.errors import ReconError

#: Exit status for bad input or impossible work (argparse uses 2 for bad usage).
EXIT_FAILURE = 1


class _OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line, like every other error here."""

    def error(self, message: str) -> None:  # noqa: D401 - argparse's name
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _alpha(value: str) -> float | str:
    if value == "auto":
        return "auto"
    try:
        alpha = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"alpha must be a number in [0, 1] or 'auto', not {value!r}"
        ) from None
    if not (0.0 <= alpha <= 1.0) or math.isnan(alpha):
        raise argparse.ArgumentTypeError(f"alpha must be in [0, 1], got {value}")
    return alpha


def _positive(value: str) -> float:
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, not {value!r}") from None
    if not (number > 0 and math.isfinite(number)):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {value}")
    return number


def _vector3(value: str) -> tuple[float, float, float]:
    try:
        parts = tuple(float(v) for v in value.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z numbers, not {value!r}") from None
    if len(parts) != 3 or not all(math.isfinite(v) for v in parts):
        raise argparse.ArgumentTypeError(f"expected three finite numbers X,Y,Z, not {value!r}")
    return parts  # type: ignore[return-value]


def _trace_options(parser: argparse.ArgumentParser, *, tip: bool = True) -> None:
    parser.add_argument(
        "--path-format",
        choices=("csv", "motive", "c3d"),
        help="format of the trace (default from the suffix; Motive exports are recognised)",
    )
    parser.add_argument("--rigid-body", metavar="NAME", help="Motive: the pen's rigid body")
    parser.add_argument("--marker", metavar="NAME", help="Motive or C3D: a single marker")
    if tip:
        parser.add_argument(
            "--tip-calibration",
            metavar="TIP.json",
            help="pen-tip offset (teachpath calibrate pivot); default: the tracked point itself",
        )
        parser.add_argument(
            "--piece",
            type=int,
            help="when long dropouts split the trace: which piece (0-based; default the longest)",
        )


def _scan_options(parser: argparse.ArgumentParser) -> None:
    from drivers.scanning.base import SCAN_READERS

    parser.add_argument(
        "--scan-format",
        choices=sorted(SCAN_READERS),
        help="format of the scan (default from the suffix; a folder is RGB-D frames)",
    )
    parser.add_argument(
        "--scan-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help='an option of the scan\'s reader, e.g. depth_scale=1000 or fusion="points" '
        "(repeatable; values are JSON, bare words are text)",
    )


def _read_scan_for(args: argparse.Namespace):
    """The scan of a command, with its format, unit and reader options."""
    import json

    from drivers.scanning.base import format_for
    from drivers.scanning.pointcloud import POINT_CLOUD_FORMATS, read_scan

    options = {}
    for item in args.scan_option:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--scan-option takes KEY=VALUE, not {item!r}")
        try:
            options[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            options[key.strip()] = value
    fmt = args.scan_format
    if fmt is None:
        fmt = "rgbd" if Path(args.scan).is_dir() else format_for(args.scan)
    # --units is for files that do not state theirs; E57, RGB-D and bags fix their own.
    units = (args.units or "m") if fmt in POINT_CLOUD_FORMATS.values() else "m"
    return read_scan(args.scan, units=units, fmt=fmt, options=options or None)


def build_parser() -> argparse.ArgumentParser:
    parser = _OneLineParser(
        prog="teachpath",
        description="Reconstruct hand-traced robot paths with a scan of the workpiece.",
    )
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_OneLineParser)

    rec = commands.add_parser(
        "reconstruct",
        help="reconstruct a traced path with a scan of the workpiece",
        description="Reconstruct a traced path, using the scan's structure where there is one. "
        "Writes the path (x,y,z, metres) with per-point diagnostics as CSV.",
    )
    rec.add_argument(
        "path_file",
        metavar="PATH_FILE",
        help="the trace: canonical CSV (x,y,z, optionally t, qx,qy,qz,qw), Motive CSV export "
        "or C3D",
    )
    _trace_options(rec)
    rec.add_argument(
        "--scan",
        metavar="SCAN_FILE",
        help="scan of the workpiece: PLY/PCD/XYZ, E57, RGB-D folder/.zip/.rgbd.json or "
        "RealSense .bag",
    )
    _scan_options(rec)
    rec.add_argument(
        "--units",
        choices=("m", "mm"),
        help="length unit of input files that do not state theirs (default: m)",
    )
    rec.add_argument(
        "--scan-from-tracker",
        metavar="T.json",
        help="stored calibration T_scan_tracker: the initial guess for registration (or the "
        "transform itself with --no-register)",
    )
    rec.add_argument("--radius-m", type=_positive, help="reconstruction radius r (default 0.008)")
    rec.add_argument("--alpha", type=_alpha, help="path weight in [0, 1] or 'auto' (default auto)")
    rec.add_argument("--beta", type=float, help="amount of reconstruction in [0, 1] (default 1)")
    rec.add_argument("--degree", type=int, help="polynomial degree (default 2)")
    rec.add_argument(
        "--method",
        choices=("paper", "anchored"),
        help="paper: Eq. (4) of the paper; anchored: ours (default)",
    )
    rec.add_argument("--spacing-m", type=_positive, help="resampling step (default 0.001)")
    rec.add_argument(
        "--no-register",
        action="store_true",
        help="trust the frames as given: do not register the path to the scan",
    )
    rec.add_argument("--out", required=True, metavar="OUT.csv", help="reconstructed path (CSV)")
    rec.add_argument("--plot", metavar="OUT.png", help="also write a picture")
    rec.set_defaults(handler=_cmd_reconstruct)

    plan = commands.add_parser(
        "plan",
        help="plan a timed UR joint trajectory along a reconstructed path",
        description="Tool poses along a reconstructed path (axis from the scan, the pen or "
        "fixed), inverse kinematics for a UR arm and time-optimal timing within its limits. "
        "Writes t,q0..q5 (s, rad) and the planned TCP x,y,z,rx,ry,rz (base frame) as CSV and "
        "prints the feasibility report.",
    )
    plan.add_argument("recon_file", metavar="RECON.csv", help="output of teachpath reconstruct")
    plan.add_argument(
        "--scan", metavar="SCAN_FILE", help="the scan the path follows (tool axis from its normals)"
    )
    _scan_options(plan)
    plan.add_argument(
        "--units", choices=("m", "mm"), help="unit of the scan file if it does not state one"
    )
    plan.add_argument(
        "--scan-from-tracker",
        metavar="T.json",
        help="T_scan_tracker the scan is used at (the reconstruction's registered transform or "
        "a calibration; default: scan and path in one frame); it is not refined",
    )
    plan.add_argument("--robot", default="ur5e", help="UR model (default ur5e)")
    plan.add_argument("--speed-m-s", type=_positive, required=True, help="TCP speed")
    plan.add_argument(
        "--base-from-tracker",
        metavar="T.json",
        help="calibration T_base_tracker (default: the path is in the base frame)",
    )
    plan.add_argument("--orientation", choices=("auto", "scan", "pen", "fixed"), default="auto")
    plan.add_argument("--lead-deg", type=float, default=0.0)
    plan.add_argument("--tilt-deg", type=float, default=0.0)
    plan.add_argument(
        "--smooth-m",
        type=float,
        default=0.01,
        help="smoothing of the tool axis along the path (default 0.01)",
    )
    plan.add_argument(
        "--tcp-offset-m",
        type=_vector3,
        default=(0.0, 0.0, 0.0),
        metavar="X,Y,Z",
        help="TCP in the flange frame (default 0,0,0)",
    )
    plan.add_argument("--out", required=True, metavar="TRAJ.csv")
    plan.set_defaults(handler=_cmd_plan)

    dry = commands.add_parser(
        "dry-run",
        help="execute a planned trajectory on the simulated arm and report",
        description="Runs TRAJ.csv on a simulated UR arm (faster than real time) and prints "
        "duration, tracking deviation, margins, speed drops and faults.",
    )
    dry.add_argument("traj_file", metavar="TRAJ.csv")
    dry.add_argument("--robot", default="ur5e", help="UR model the trajectory was planned for")
    dry.add_argument(
        "--mode",
        choices=("servoj", "movepath"),
        default="servoj",
        help="stream every sample (default), or coarse blended waypoints run by the controller",
    )
    dry.add_argument(
        "--tolerance-m",
        type=float,
        default=5e-4,
        help="movepath: largest TCP deviation of the waypoints from the plan (default 0.0005)",
    )
    dry.set_defaults(handler=_cmd_dry_run)

    record = commands.add_parser(
        "record",
        help="record the pen from Motive (OptiTrack NatNet) into a trace CSV",
        description="Receives the rigid body from Motive (unicast unless --multicast) until "
        "--duration seconds of stream time, Ctrl-C, or the stream stops, then writes the "
        "tracked frames as a canonical trace CSV (t,x,y,z,qx,qy,qz,qw; metres; seconds from the "
        "first row) and prints frames received, dropped and not tracked. The receiver runs in "
        "a process of its own, so no frame is lost to work elsewhere.",
    )
    record.add_argument("--natnet", required=True, metavar="HOST", help="Motive's address")
    record.add_argument("--rigid-body", required=True, metavar="NAME", help="the pen in Motive")
    record.add_argument("--out", required=True, metavar="FILE.csv")
    record.add_argument(
        "--local", default="127.0.0.1", help="this machine's address on Motive's network"
    )
    record.add_argument("--multicast", action="store_true", help="Motive streams multicast")
    record.add_argument("--command-port", type=int, default=1510)
    record.add_argument("--data-port", type=int, default=1511, help="multicast data port")
    record.add_argument(
        "--duration", type=_positive, metavar="S", help="stream seconds (default: until Ctrl-C)"
    )
    record.add_argument(
        "--timeout", type=_positive, default=5.0, metavar="S", help="bound on each answer"
    )
    record.add_argument("--units", choices=("m", "mm"), default="m", help="unit Motive streams")
    record.set_defaults(handler=_cmd_record)

    calibrate = commands.add_parser(
        "calibrate",
        help="pen-tip (pivot) and tracker-to-robot (point pairs) calibrations",
        description="Compute a calibration, print its residuals and save it as JSON.",
    )
    kinds = calibrate.add_subparsers(dest="kind", required=True, parser_class=_OneLineParser)
    pivot = kinds.add_parser(
        "pivot",
        help="the pen's tip offset from a pivoting recording",
        description="The tip stays on one point while the pen is tilted in every direction; "
        "the least-squares pivot gives the tip in the rigid body's frame. Pass the result to "
        "reconstruct with --tip-calibration.",
    )
    pivot.add_argument("recording", metavar="REC", help="recording with orientations")
    _trace_options(pivot, tip=False)
    pivot.add_argument("--units", choices=("m", "mm"), help="unit if the file states none")
    pivot.add_argument("--out", required=True, metavar="TIP.json")
    pivot.set_defaults(handler=_cmd_calibrate_pivot)
    base = kinds.add_parser(
        "base",
        help="T_base_tracker from point pairs",
        description="PAIRS.csv has a header naming base_x,base_y,base_z,tracker_x,tracker_y,"
        "tracker_z: the same physical points (touched by the robot's TCP and by the tracked "
        "tip) in both frames, at least 3 not on a line. Pairs that disagree with the others "
        "by more than the tolerance are reported and left out.",
    )
    base.add_argument("pairs", metavar="PAIRS.csv")
    base.add_argument("--units", choices=("m", "mm"), default="m", help="unit of the pairs")
    base.add_argument(
        "--tolerance-m", type=_positive, default=1e-3, help="largest acceptable pair error"
    )
    base.add_argument("--out", required=True, metavar="T_base_tracker.json")
    base.set_defaults(handler=_cmd_calibrate_base)

    serve = commands.add_parser(
        "serve",
        help="start the HTTP service (REST API, teach-pendant page)",
        description="Starts the service. Settings also come from TEACHPATH_* environment "
        "variables (TEACHPATH_TOKEN, TEACHPATH_UR_HOST, TEACHPATH_DATABASE_URL, ...).",
    )
    serve.add_argument("--host", help="address to listen on (default 127.0.0.1)")
    serve.add_argument("--port", type=int, help="port (default 8000; 0 picks a free one)")
    serve.add_argument(
        "--data-dir", help="folder for the database and arrays (default ./teachpath_data)"
    )
    serve.add_argument(
        "--demo",
        action="store_true",
        help="create the demo session (a synthetic cylinder trace and scan)",
    )
    serve.set_defaults(handler=_cmd_serve)

    from drivers.robot import fake_ur  # light: imports argparse and logging only

    fake = commands.add_parser(
        "fake-ur",
        help="run a fake UR controller on a loopback address (for the ur_rtde backend)",
        description="Serves RTDE (30004), the dashboard (29999) and the script ports "
        "(30001-30003) of an emulated UR controller that ur_rtde drives, so the service's "
        "real-robot path can be tried without a robot: start the service with "
        "TEACHPATH_UR_HOST set to the same address. Loopback addresses only.",
    )
    fake_ur.add_arguments(fake)
    fake.set_defaults(handler=_cmd_fake_ur)

    demo = commands.add_parser(
        "demo",
        help="run the bundled demo: a synthetic cylinder-edge trace and scan, reconstructed",
        description="Generates the paper's Fig. 4 scene (a noisy trace along the circular edge "
        "of a cylinder and a misplaced, noisy scan of it), writes them as files, reconstructs "
        "them as `teachpath reconstruct` does and prints the accuracy table.",
    )
    demo.add_argument("--out-dir", default="demo_out", help="folder for all outputs")
    demo.add_argument("--seed", type=int, default=0, help="random seed of the scene")
    demo.set_defaults(handler=_cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``teachpath`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except (ReconError, DriverError, ValueError) as exc:
        print(f"teachpath {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except OSError as exc:
        where = f" ({exc.filename})" if exc.filename else ""
        print(f"teachpath {args.command}: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt:
        print(f"teachpath {args.command}: interrupted", file=sys.stderr)
        return 130


def _params_from(args: argparse.Namespace):
    from dataclasses import replace

    from recon.types import ReconParams

    overrides = {
        "radius_m": args.radius_m,
        "alpha": args.alpha,
        "beta": args.beta,
        "degree": args.degree,
        "method": args.method,
        "spacing_m": args.spacing_m,
    }
    params = replace(ReconParams(), **{k: v for k, v in overrides.items() if v is not None})
    if args.no_register:
        params = replace(params, register=False)
    return params


def _check_output(path: str, suffix: str) -> Path:
    out = Path(path)
    if out.suffix.lower() != suffix:
        raise ValueError(f"{path} should end in {suffix}")
    if not out.parent.is_dir() and str(out.parent):
        raise ValueError(f"the folder of {path} does not exist; create it first")
    return out


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    from drivers.calibration import read_calibration
    from drivers.export import write_reconstruction_csv
    from recon.reconstruct import reconstruct

    out = _check_output(args.out, ".csv")
    plot = _check_output(args.plot, ".png") if args.plot else None
    params = _params_from(args)
    T_scan_tracker = None
    if args.scan_from_tracker:
        T_scan_tracker = read_calibration(args.scan_from_tracker, expect="T_scan_tracker").matrix
    recording = _read_trace_for(args)
    scan = None
    if args.scan:
        scan_file = _read_scan_for(args)
        scan = scan_file.scan
        for note in scan_file.notes:
            print(f"note: {note}", file=sys.stderr)
        if scan_file.n_dropped:
            print(
                f"note: {scan_file.n_dropped} scan points without finite coordinates were left out",
                file=sys.stderr,
            )
    recon = reconstruct(recording, scan, params=params, T_scan_tracker_init=T_scan_tracker)
    if plot is not None:
        # Written first: if the plot fails, no CSV claims the run succeeded.
        from recon.transforms import apply_transform, invert_transform
        from service.plots import plot_reconstruction

        scan_tracker = None
        if scan is not None and recon.registration is not None:
            scan_tracker = apply_transform(
                invert_transform(recon.registration.T_scan_tracker), scan.points_m
            )
        elif scan is not None:
            scan_tracker = scan.points_m
        plot_reconstruction(plot, recon, scan_m=scan_tracker, title=Path(args.path_file).name)
    write_reconstruction_csv(out, recon)
    print(summary(recon))
    return 0


def _read_trace_for(args: argparse.Namespace):
    """The trace of a command, with its tip calibration applied and its gaps cleaned; what the
    cleaning did goes to stderr."""
    from drivers.calibration import read_tip_calibration
    from drivers.tracking.readers import read_trace

    tip = None
    if getattr(args, "tip_calibration", None):
        calibration = read_tip_calibration(args.tip_calibration)
        named = calibration.rigid_body
        if named and args.rigid_body and named != args.rigid_body:
            raise InputFileError(
                f"{args.tip_calibration} is the tip of rigid body {named!r}, but the trace is "
                f"of {args.rigid_body!r}; calibrate that pen (teachpath calibrate pivot) or "
                "pick the matching --rigid-body"
            )
        tip = calibration.offset_m
    trace = read_trace(
        args.path_file,
        fmt=args.path_format,
        units=args.units,
        rigid_body=args.rigid_body,
        marker=args.marker,
        tip_offset_m=tip,
        piece=args.piece,
    )
    report = trace.clean.report
    if report.events or len(trace.clean.pieces) > 1:
        for line in report.lines():
            print(f"note: {line}", file=sys.stderr)
        if len(trace.clean.pieces) > 1:
            start, end = report.pieces[trace.piece]
            print(
                f"note: using piece {trace.piece} ({start:.2f}-{end:.2f} s) of "
                f"{len(trace.clean.pieces)}; choose another with --piece",
                file=sys.stderr,
            )
    return trace.recording


def _cmd_record(args: argparse.Namespace) -> int:
    from drivers.tracking.natnet_source import NatNetConfig
    from drivers.tracking.record import record_natnet

    out = _check_output(args.out, ".csv")
    config = NatNetConfig(
        server=args.natnet,
        local=args.local,
        rigid_body=args.rigid_body,
        multicast=args.multicast,
        command_port=args.command_port,
        data_port=args.data_port,
        timeout_s=args.timeout,
        units=args.units,
    )
    print(f"recording {args.rigid_body!r} from {args.natnet}; Ctrl-C to stop", file=sys.stderr)
    result = record_natnet(config, out, duration_s=args.duration)
    print(f"wrote {result.frames_written} frames ({result.duration_s:.2f} s) to {result.path}")
    print(
        f"received {result.frames_received}, dropped {result.frames_dropped}, not tracked "
        f"{result.frames_invalid}; ended by {result.stop_reason}"
    )
    return 0


def _cmd_calibrate_pivot(args: argparse.Namespace) -> int:
    from drivers.calibration import write_tip_calibration
    from drivers.tracking.readers import read_raw_trace, require_orientations
    from recon.calibrate import pivot_calibration

    out = _check_output(args.out, ".json")
    raw = read_raw_trace(
        args.recording,
        fmt=args.path_format,
        units=args.units,
        rigid_body=args.rigid_body,
        marker=args.marker,
    )
    require_orientations(raw, "a pivot calibration")
    batch = raw.batch
    good = (
        np.asarray(batch.valid, dtype=bool)
        & np.isfinite(batch.position_m).all(axis=1)
        & np.isfinite(batch.orientation_xyzw).all(axis=1)
    )
    q = batch.orientation_xyzw[good]
    result = pivot_calibration(batch.position_m[good], q / np.linalg.norm(q, axis=1)[:, None])
    mm = 1e3
    x, y, z = result.tip_offset_m * mm
    print(
        f"tip offset ({x:.2f}, {y:.2f}, {z:.2f}) mm in the rigid body's frame; residual "
        f"{result.residual_rms_m * mm:.3f} mm RMS, {result.residual_max_m * mm:.3f} mm max; pen "
        f"turned {result.rotation_spread_deg:.0f} deg; {result.n_used} samples used, "
        f"{result.n_rejected} rejected, {int(np.count_nonzero(~good))} lost"
    )
    write_tip_calibration(
        out,
        result.tip_offset_m,
        rigid_body=raw.meta.get("rigid_body"),
        residual_rms_m=result.residual_rms_m,
        extra={
            "residual_max_m": result.residual_max_m,
            "pivot_point_m": result.pivot_point_m.tolist(),
            "rotation_spread_deg": result.rotation_spread_deg,
            "n_used": result.n_used,
            "n_rejected": result.n_rejected,
            "source": Path(args.recording).name,
        },
    )
    return 0


def _cmd_calibrate_base(args: argparse.Namespace) -> int:
    from drivers.calibration import write_calibration
    from drivers.tracking.point_pairs import read_point_pairs
    from recon.calibrate import fit_point_pairs

    out = _check_output(args.out, ".json")
    base_m, tracker_m = read_point_pairs(args.pairs, units=args.units)
    fit = fit_point_pairs(base_m, tracker_m, tolerance_m=args.tolerance_m)
    print("\n".join(fit.lines()))
    write_calibration(
        out,
        "T_base_tracker",
        fit.T_a_b,
        residual_rms_m=fit.residual_rms_m,
        extra={
            "residuals_m": fit.residuals_m.tolist(),
            "leave_one_out_m": [None if np.isnan(v) else v for v in fit.leave_one_out_m],
            "used": fit.used.tolist(),
            "tolerance_m": fit.tolerance_m,
            "source": Path(args.pairs).name,
        },
    )
    return 0


def summary(recon) -> str:
    """A few lines on what a reconstruction did."""
    from recon.types import PointMode

    mm = 1e3
    counts = ", ".join(
        f"{recon.count(mode)} {mode.label}" for mode in PointMode if recon.count(mode)
    )
    lines = [
        f"{len(recon)} points ({counts}) in {len(recon.segments)} segment(s); "
        f"moved {np.mean(recon.displacement_m) * mm:.2f} mm on average, "
        f"{np.max(recon.displacement_m) * mm:.2f} mm at most",
    ]
    reg = recon.registration
    if reg is not None:
        lines.append(
            f"registered to the scan's {reg.target}: moved "
            f"{np.linalg.norm(reg.translation_m) * mm:.2f} mm and {reg.rotation_deg:.2f} deg, "
            f"residual {reg.rmse_m * mm:.2f} mm RMS, "
            f"{reg.fitness * 100:.0f} % of the path paired, {reg.constrained_dof}/6 motions fixed"
        )
    lines += [f"note: {note}" for note in recon.notes]
    return "\n".join(lines)


def _cmd_plan(args: argparse.Namespace) -> int:
    from drivers.calibration import read_calibration
    from drivers.export import read_reconstruction_csv, write_trajectory_csv
    from recon.plan import (
        PlanParams,
        approach_in,
        normals_from_scan,
        plan_path,
        scan_model_for_path,
    )

    out = _check_output(args.out, ".csv")
    params = PlanParams(
        robot=args.robot,
        speed_m_s=args.speed_m_s,
        orientation=args.orientation,
        lead_deg=args.lead_deg,
        tilt_deg=args.tilt_deg,
        smooth_m=args.smooth_m,
        tcp_offset_m=args.tcp_offset_m,
    )
    recon = read_reconstruction_csv(args.recon_file)
    T_base_tracker = None
    if args.base_from_tracker:
        T_base_tracker = read_calibration(args.base_from_tracker, expect="T_base_tracker").matrix
    normals = None
    T_scan_tracker = None
    if args.scan_from_tracker:
        T_scan_tracker = read_calibration(args.scan_from_tracker, expect="T_scan_tracker").matrix
    if args.scan and params.orientation in ("auto", "scan"):
        scan = _read_scan_for(args).scan
        # No registration here: the scan is used at the given transform (identity without one).
        T_scan_tracker = np.eye(4) if T_scan_tracker is None else T_scan_tracker
        normals = normals_from_scan(
            recon.points_m,
            recon.mode,
            scan_model_for_path(scan, recon.points_m, T_scan_tracker=T_scan_tracker),
            T_scan_tracker=T_scan_tracker,
            approach_tracker=approach_in(T_base_tracker, params.approach),
        )
    plan = plan_path(
        recon.points_m,
        params=params,
        T_base_tracker=T_base_tracker,
        normals=normals,
        pen_xyzw=recon.orientations_xyzw,
    )
    write_trajectory_csv(out, plan.trajectory)
    print("\n".join(plan.report_lines()))
    return 0


def _cmd_dry_run(args: argparse.Namespace) -> int:
    from drivers.export import read_trajectory_csv
    from drivers.robot.dryrun import dry_run
    from recon.kinematics import model

    model(args.robot)  # an unknown arm is a one-line error before reading anything
    if not args.tolerance_m > 0:
        raise ValueError(f"--tolerance-m must be positive, got {args.tolerance_m}")
    trajectory = read_trajectory_csv(args.traj_file, robot=args.robot.lower())
    report = dry_run(trajectory, mode=args.mode, tolerance_m=args.tolerance_m)
    print("\n".join(report.lines()))
    return 0 if report.completed and not report.faults else EXIT_FAILURE


def _cmd_fake_ur(args: argparse.Namespace) -> int:
    from drivers.robot import fake_ur

    return fake_ur.run_from_args(args)


def _cmd_serve(args: argparse.Namespace) -> int:
    import socket

    import uvicorn

    from service.app import create_app
    from service.settings import Settings

    overrides = {
        k: v
        for k, v in {"host": args.host, "port": args.port, "data_dir": args.data_dir}.items()
        if v is not None
    }
    if args.demo:
        overrides["demo"] = True
    settings = Settings(**overrides)
    token = settings.access_token()
    app = create_app(settings)
    # Bind first, so the printed URL has the real port (also with --port 0).
    sock = socket.socket(socket.AF_INET6 if ":" in settings.host else socket.AF_INET)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    # Accepted connections inherit it: without it, Nagle's algorithm meets the client's delayed
    # ACK and small responses wait 40 ms (measured: p50 50 ms for a 4 ms request).
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.bind((settings.host, settings.port))
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if ":" in host else host
    print(f"teachpath is serving {settings.data_dir}")
    print(f"open http://{shown}:{port}/?token={token}")
    print(f"API: http://{shown}:{port}/docs (send 'Authorization: Bearer {token}')", flush=True)
    config = uvicorn.Config(app, log_level="warning")
    uvicorn.Server(config).run(sockets=[sock])
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from drivers.scanning.pointcloud import write_scan
    from drivers.tracking.canonical_csv import write_trace_csv
    from recon import scenes
    from recon.evaluation import default_variants, evaluate, format_table
    from recon.reconstruct import reconstruct
    from recon.transforms import apply_transform, invert_transform
    from service.plots import plot_reconstruction

    out_dir = Path(args.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scene = scenes.cylinder_edge(args.seed)
    trace_file, scan_file = out_dir / "trace.csv", out_dir / "scan.ply"
    write_trace_csv(trace_file, scene.recording)
    write_scan(scan_file, scene.scan)
    print(f"scene: {scene.description}")
    print(
        f"inputs: {trace_file} ({len(scene.recording)} samples), "
        f"{scan_file} ({len(scene.scan)} points)"
    )
    code = main(
        [
            "reconstruct",
            str(trace_file),
            "--scan",
            str(scan_file),
            "--out",
            str(out_dir / "reconstruction.csv"),
            "--plot",
            str(out_dir / "reconstruction.png"),
        ]
    )
    if code:
        return code
    table = format_table(evaluate(scene, default_variants()), title=scene.description)
    (out_dir / "accuracy.md").write_text(table + "\n")
    # The same reconstruction against the ground truth only the demo knows (the paper's Fig. 5).
    recon = reconstruct(scene.recording, scene.scan)
    plot_reconstruction(
        out_dir / "accuracy.png",
        recon,
        scan_m=apply_transform(invert_transform(scene.T_scan_tracker), scene.scan.points_m),
        truth_m=scene.truth_m,
        title="demo: error against the ground truth (tracker frame)",
    )
    print()
    print(table)
    print(
        f"\nwrote {out_dir / 'reconstruction.csv'}, {out_dir / 'reconstruction.png'}, "
        f"{out_dir / 'accuracy.md'}, {out_dir / 'accuracy.png'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
