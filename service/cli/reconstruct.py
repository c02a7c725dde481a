"""``teachpath reconstruct``: a traced path reconstructed with a scan of the workpiece."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.options import (
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


def add_parser(commands) -> None:
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
    from recon.types import ReconParams
    from service.schemas import RECONSTRUCTION_PARAMS

    add_param_options(rec, ReconParams, RECONSTRUCTION_PARAMS)
    rec.add_argument(
        "--no-register",
        action="store_true",
        help="trust the frames as given: do not register the path to the scan",
    )
    rec.add_argument("--out", required=True, metavar="OUT.csv", help="reconstructed path (CSV)")
    rec.add_argument("--plot", metavar="OUT.png", help="also write a picture")
    rec.add_argument(
        "--registration-out",
        metavar="T.json",
        help="also write the T_scan_tracker the reconstruction used (registered, or the one "
        "given), for `teachpath plan --scan-from-tracker`",
    )
    rec.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from drivers.calibration import write_calibration
    from drivers.export import write_reconstruction_csv
    from service import pipelines

    out = check_output(args.out, ".csv")
    plot = check_output(args.plot, ".png") if args.plot else None
    registration_out = (
        check_output(args.registration_out, ".json") if args.registration_out else None
    )
    if registration_out is not None and not args.scan:
        raise ValueError("--registration-out needs --scan: without a scan nothing is registered")
    from recon.types import ReconParams
    from service.schemas import RECONSTRUCTION_PARAMS

    params = params_from_args(
        ReconParams,
        args,
        RECONSTRUCTION_PARAMS,
        **({"register": False} if args.no_register else {}),
    )
    T_init = read_matrix(args.scan_from_tracker, "T_scan_tracker")
    recording = read_trace_for(args)
    scan = read_scan_for(args) if args.scan else None
    outcome = pipelines.reconstruct(recording, scan, params=params, T_scan_tracker_init=T_init)
    if plot is not None:
        # Written first: if the plot fails, no CSV claims the run succeeded.
        outcome.write_preview(plot, title=Path(args.path_file).name)
    recon = outcome.reconstruction
    if registration_out is not None:
        if recon.T_scan_tracker is None:
            raise ValueError("--registration-out needs a scan: no transform was used")
        write_calibration(
            registration_out,
            "T_scan_tracker",
            recon.T_scan_tracker,
            residual_rms_m=None if recon.registration is None else recon.registration.rmse_m,
            extra={
                "source": Path(args.path_file).name,
                "registered": recon.registration is not None,
            },
        )
    write_reconstruction_csv(out, recon)
    print("\n".join(outcome.lines()))
    return 0
