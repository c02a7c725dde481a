"""``teachpath calibrate pivot|base|scan``: the pen's tip offset, the tracker-to-robot transform
and the tracker-to-scanner transform from touches of the workpiece."""

from __future__ import annotations

import argparse
from pathlib import Path

from recon.params import PIVOT_TOLERANCE_M
from service.cli.options import (
    OneLineParser,
    add_scan_options,
    add_trace_options,
    check_output,
    positive,
    read_matrix,
    read_scan_for,
    read_trace_for,
)

#: The command's name, and its line in ``teachpath --help``.
NAME = "calibrate"
HELP = (
    "pen-tip (pivot), tracker-to-robot (point pairs) and tracker-to-scanner (touches) calibrations"
)


def add_parser(commands: argparse._SubParsersAction[OneLineParser]) -> None:
    calibrate = commands.add_parser(
        NAME,
        help=HELP,
        description="Compute a calibration, print its residuals and save it as JSON.",
    )
    kinds = calibrate.add_subparsers(dest="kind", required=True, parser_class=OneLineParser)
    pivot = kinds.add_parser(
        "pivot",
        help="the pen's tip offset from a pivoting recording",
        description="The tip stays on one point while the pen is tilted in every direction; "
        "the least-squares pivot gives the tip in the rigid body's frame. Pass the result to "
        "reconstruct with --tip-calibration.",
    )
    pivot.add_argument("recording", metavar="REC", help="recording with orientations")
    add_trace_options(pivot, tip=False)
    pivot.add_argument("--units", choices=("m", "mm"), help="unit if the file states none")
    pivot.add_argument(
        "--tolerance-m",
        type=positive,
        default=PIVOT_TOLERANCE_M,
        help="largest acceptable RMS of the tip about its point (default %(default)s)",
    )
    _accept_poor_fit(pivot)
    pivot.add_argument("--out", required=True, metavar="TIP.json")
    pivot.set_defaults(handler=run_pivot)
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
        "--tolerance-m", type=positive, default=1e-3, help="largest acceptable pair error"
    )
    _accept_poor_fit(base)
    base.add_argument("--out", required=True, metavar="T_base_tracker.json")
    base.set_defaults(handler=run_base)
    scan = kinds.add_parser(
        "scan",
        help="T_scan_tracker from touches of the workpiece",
        description="TOUCHES_FILE is a recording (any trace format, with times) in which the "
        "pen's tip rests 0.3 s or more on each of 3 or more points of the workpiece, on two or "
        "three faces, and moves between them. The rests are found and averaged, and registered "
        "point to plane to the scan's surface; the result names the residual of every touch "
        "and the motions the touches fix (those they leave free keep the initial guess); it is "
        "refused where the placement they leave is uncertain by more than 0.5 mm (1 sigma). "
        "Pass the file to reconstruct or plan with --scan-from-tracker (and --no-register).",
    )
    scan.add_argument("touches", metavar="TOUCHES_FILE")
    add_trace_options(scan)
    scan.add_argument("--scan", required=True, metavar="SCAN_FILE", help="the workpiece's scan")
    add_scan_options(scan)
    scan.add_argument("--units", choices=("m", "mm"), help="unit if a file states none")
    scan.add_argument(
        "--scan-from-tracker",
        metavar="T0.json",
        help="initial guess (a stored T_scan_tracker); default: from --trace registered to the "
        "scan, else the frames as given",
    )
    scan.add_argument(
        "--trace",
        metavar="PATH_FILE",
        help="the path the calibration is for: the initial guess comes from registering it, "
        "and the touches are judged by the millimetres of placement they leave at it, across "
        "its features (else near the touches)",
    )
    scan.add_argument("--out", required=True, metavar="T_scan_tracker.json")
    scan.set_defaults(handler=run_scan)


def _accept_poor_fit(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--accept-poor-fit",
        action="store_true",
        help="write the calibration even when it is worse than the tolerance (default: "
        "refused, exit 1)",
    )


def run_pivot(args: argparse.Namespace) -> int:
    from drivers.calibration import write_tip_calibration
    from drivers.tracking.readers import read_raw_trace
    from service import pipelines

    out = check_output(args.out, ".json")
    raw = read_raw_trace(
        args.recording,
        fmt=args.path_format,
        units=args.units,
        rigid_body=args.rigid_body,
        marker=args.marker,
    )
    outcome = pipelines.pivot(
        raw, tolerance_m=args.tolerance_m, accept_poor_fit=args.accept_poor_fit
    )
    print(outcome.line())
    result = outcome.as_json()
    write_tip_calibration(
        out,
        outcome.calibration.tip_offset_m,
        rigid_body=result["rigid_body"],
        residual_rms_m=result["residual_rms_m"],
        extra={
            key: result[key]
            for key in (
                "residual_max_m",
                "pivot_point_m",
                "rotation_spread_deg",
                "n_used",
                "n_rejected",
            )
        }
        | {"source": Path(args.recording).name},
    )
    return 0


def run_base(args: argparse.Namespace) -> int:
    from drivers.calibration import write_calibration
    from drivers.tracking.point_pairs import read_point_pairs
    from service import pipelines

    out = check_output(args.out, ".json")
    base_m, tracker_m = read_point_pairs(args.pairs, units=args.units)
    outcome = pipelines.point_pairs(
        base_m, tracker_m, tolerance_m=args.tolerance_m, accept_poor_fit=args.accept_poor_fit
    )
    print("\n".join(outcome.lines()))
    result = outcome.as_json()
    write_calibration(
        out,
        "T_base_tracker",
        outcome.fit.T_a_b,
        residual_rms_m=result["residual_rms_m"],
        extra={
            key: result[key] for key in ("residuals_m", "leave_one_out_m", "used", "tolerance_m")
        }
        | {"source": Path(args.pairs).name},
    )
    return 0


def run_scan(args: argparse.Namespace) -> int:
    from drivers.calibration import write_calibration
    from service import pipelines

    out = check_output(args.out, ".json")
    touches = read_trace_for(args, args.touches, piece="all")
    trace = read_trace_for(args, args.trace) if args.trace else None
    scan = read_scan_for(args)
    outcome = pipelines.touch_calibration(
        touches,
        scan,
        trace=trace,
        T_scan_tracker_init=read_matrix(args.scan_from_tracker, "T_scan_tracker"),
    )
    print("\n".join(outcome.lines()))
    write_calibration(
        out,
        "T_scan_tracker",
        outcome.registration.T_scan_tracker,
        residual_rms_m=outcome.residual_rms_m,
        extra=outcome.as_json() | {"source": Path(args.touches).name},
    )
    return 0
