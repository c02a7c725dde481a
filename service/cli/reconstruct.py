"""``teachpath reconstruct``: a traced path reconstructed with a scan of the workpiece."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.options import (
    OneLineParser,
    add_param_options,
    add_scan_options,
    add_trace_options,
    add_units_option,
    check_output,
    params_from_args,
    read_matrix,
    read_scan_for,
    read_trace_for,
)

#: The command's name, and its line in ``teachpath --help``.
NAME = "reconstruct"
HELP = "reconstruct a traced path with a scan of the workpiece"


def add_parser(commands: argparse._SubParsersAction[OneLineParser]) -> None:
    rec = commands.add_parser(
        NAME,
        help=HELP,
        description="Reconstruct a traced path, using the scan's structure where there is one. "
        "Writes the path (x,y,z, metres) with per-point diagnostics as CSV, and beside it "
        "OUT.npz: the same with the scan's transform and model, which `teachpath plan` reuses.",
    )
    rec.add_argument(
        "path_files",
        nargs="+",
        metavar="PATH_FILE",
        help="the trace: canonical CSV (x,y,z, optionally t, qx,qy,qz,qw), Motive CSV export "
        "or C3D. Several files are demonstrations of one path (either direction): they are "
        "fused, an outlier is left out and named, and the fused trace is reconstructed",
    )
    add_trace_options(rec)
    rec.add_argument(
        "--scan",
        metavar="SCAN_FILE",
        help="scan of the workpiece: PLY/PCD/XYZ, E57, RGB-D folder/.zip/.rgbd.json or "
        "RealSense .bag",
    )
    add_scan_options(rec)
    add_units_option(rec, "length unit of input files that do not state theirs (default: m)")
    rec.add_argument(
        "--scan-from-tracker",
        metavar="T.json",
        help="stored calibration T_scan_tracker: the initial guess for registration (or the "
        "transform itself with --no-register)",
    )
    from recon.recon_params import ReconParams
    from service.schemas import RECONSTRUCTION_PARAMS

    add_param_options(rec, ReconParams, RECONSTRUCTION_PARAMS)
    rec.add_argument(
        "--touches",
        metavar="TOUCHES_FILE",
        help="a recording (any trace format, with times) in which the pen's tip rests 0.3 s or "
        "more on each of 3 or more points of the workpiece: the scanner is registered by them "
        "(see `teachpath calibrate scan`) rather than by the trace, and refused if they leave "
        "free a motion the traced features need",
    )
    rec.add_argument(
        "--no-register",
        action="store_true",
        help="trust the frames as given: do not register the path to the scan",
    )
    rec.add_argument("--out", required=True, metavar="OUT.csv", help="reconstructed path (CSV)")
    rec.add_argument("--plot", metavar="OUT.png", help="also write a picture")

    rec.set_defaults(handler=run)


def sidecar_of(csv_path: str | Path) -> Path:
    """Where ``teachpath reconstruct --out OUT.csv`` writes its arrays: ``OUT.npz``."""
    return Path(csv_path).with_suffix(".npz")


def run(args: argparse.Namespace) -> int:
    from drivers.export import write_reconstruction_csv
    from recon.recon_params import ReconParams
    from service import pipelines
    from service.artifacts import ReconstructionCodec
    from service.parsing import save_arrays
    from service.schemas import RECONSTRUCTION_PARAMS

    out = check_output(args.out, ".csv")
    plot = check_output(args.plot, ".png") if args.plot else None
    fixed = {"register": False} if args.no_register else {}
    params = params_from_args(ReconParams, args, RECONSTRUCTION_PARAMS, **fixed)
    T_init = read_matrix(args.scan_from_tracker, "T_scan_tracker")
    resolved = [Path(path).resolve() for path in args.path_files]
    if len(set(resolved)) < len(resolved):
        raise ValueError(
            "the same trace file is given twice: fusing it with itself would count its errors "
            "as if two hands had drawn them; give each demonstration once"
        )
    recordings = [read_trace_for(args, path) for path in args.path_files]
    if args.touches and not args.scan:
        raise ValueError("--touches register the scanner: give the scan too (--scan SCAN_FILE)")
    touches = read_trace_for(args, args.touches, piece="all") if args.touches else None
    scan = read_scan_for(args) if args.scan else None
    outcome = pipelines.reconstruct(
        recordings if len(recordings) > 1 else recordings[0],
        scan,
        params=params,
        T_scan_tracker_init=T_init,
        touches=touches,
    )
    if plot is not None:
        # Written first: if the plot fails, no CSV claims the run succeeded.
        outcome.write_preview(plot, title=Path(args.path_files[0]).name)
    # Beside the CSV, for `teachpath plan`: the arrays the service stores (with the transform
    # and the scan model the reconstruction used, so planning registers nothing again).
    save_arrays(sidecar_of(out), ReconstructionCodec.encode(outcome.reconstruction))
    write_reconstruction_csv(out, outcome.reconstruction)
    print("\n".join(outcome.lines()))
    return 0
