"""``teachpath plan``: a timed UR joint trajectory along a reconstructed path."""

from __future__ import annotations

import argparse

from service.cli.options import (
    add_param_options,
    add_scan_options,
    add_units_option,
    check_output,
    params_from_args,
    read_matrix,
    read_scan_for,
)


def add_parser(commands) -> None:
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
        "--scan",
        metavar="SCAN_FILE",
        help="the scan the path follows (tool axis from its normals)",
    )
    add_scan_options(plan)
    add_units_option(plan, "unit of the scan file if it does not state one")
    plan.add_argument(
        "--scan-from-tracker",
        metavar="T.json",
        help="T_scan_tracker the reconstruction used (teachpath reconstruct --registration-out): "
        "the scan is placed with it, nothing is registered again; without it the path is "
        "registered to the scan here",
    )
    from recon.types import PlanParams
    from service.schemas import TRAJECTORY_PARAMS

    add_param_options(plan, PlanParams, TRAJECTORY_PARAMS, required=("speed_m_s",))
    plan.add_argument(
        "--base-from-tracker",
        metavar="T.json",
        help="calibration T_base_tracker (default: the path is in the base frame)",
    )
    plan.add_argument("--out", required=True, metavar="TRAJ.csv")
    plan.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from drivers.export import read_reconstruction_csv, write_trajectory_csv
    from recon.types import PlanParams
    from service import pipelines
    from service.cli.options import note
    from service.schemas import TRAJECTORY_PARAMS

    out = check_output(args.out, ".csv")
    params = params_from_args(PlanParams, args, TRAJECTORY_PARAMS)
    path = read_reconstruction_csv(args.recon_file)
    T_base_tracker = read_matrix(args.base_from_tracker, "T_base_tracker")
    path = replace(path, T_scan_tracker=read_matrix(args.scan_from_tracker, "T_scan_tracker"))
    scan_model = None
    if args.scan and params.orientation in ("auto", "scan"):
        placed = pipelines.place_scan(read_scan_for(args), path)
        if placed.registration is not None:
            note(
                "registered the path to the scan to find its normals; pass the reconstruction's "
                "own transform with --scan-from-tracker (reconstruct --registration-out)"
            )
        path, scan_model = replace(path, T_scan_tracker=placed.T_scan_tracker), placed.model
    outcome = pipelines.plan(
        path, params=params, T_base_tracker=T_base_tracker, scan_model=scan_model
    )
    write_trajectory_csv(out, outcome.trajectory)
    print("\n".join(outcome.lines()))
    return 0
