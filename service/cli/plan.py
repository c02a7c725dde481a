"""``teachpath plan``: a timed UR joint trajectory along a reconstructed path."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from service.cli.options import (
    OneLineParser,
    add_param_options,
    add_scan_options,
    add_units_option,
    box6,
    cell_plane,
    check_output,
    note,
    params_from_args,
    read_matrix,
    read_scan_for,
)

if TYPE_CHECKING:
    from recon.kinematics import DHCalibration
    from recon.paths import ReconstructedPath
    from recon.recon_params import ReconParams
    from recon.scan_model import ScanModel


#: The command's name, and its line in ``teachpath --help``.
NAME = "plan"
HELP = "plan a timed UR joint trajectory along a reconstructed path"


def add_parser(commands: argparse._SubParsersAction[OneLineParser]) -> None:
    plan = commands.add_parser(
        NAME,
        help=HELP,
        description="Tool poses along a reconstructed path (axis from the scan, the pen or "
        "fixed), inverse kinematics for a UR arm and time-optimal timing within its limits. "
        "Writes t,q0..q5 (s, rad) and the planned TCP x,y,z,rx,ry,rz (base frame) as CSV and "
        "prints the feasibility report.",
    )
    plan.add_argument("recon_file", metavar="RECON.csv", help="output of teachpath reconstruct")
    plan.add_argument(
        "--scan",
        metavar="SCAN_FILE",
        help="the scan the path follows (tool axis from its normals): with the RECON.npz "
        "`teachpath reconstruct` wrote beside RECON.csv, its stored model and transform are "
        "used",
    )
    add_scan_options(plan)
    add_units_option(plan, "unit of the scan file if it does not state one")
    plan.add_argument(
        "--scan-from-tracker",
        metavar="T.json",
        help="place the scan with this T_scan_tracker instead (nothing is registered); without "
        "it and without RECON.npz the path is registered to the scan here",
    )
    from recon.plan_params import PlanParams
    from service.schemas import TRAJECTORY_PARAMS

    add_param_options(
        plan,
        PlanParams,
        TRAJECTORY_PARAMS,
        required=("speed_m_s",),
        aliases={"start_q_rad": ("--start-q",)},
    )
    plan.add_argument(
        "--ur-calibration",
        metavar="calibration.conf",
        help="the arm's own kinematics calibration (its controller's "
        "/root/.urcontrol/calibration.conf): the joints are solved for it, and the file "
        "records it (default: UR's nominal model, millimetres off on a real arm)",
    )
    plan.add_argument(
        "--base-from-tracker",
        metavar="T.json",
        help="calibration T_base_tracker (default: the path is in the base frame)",
    )
    plan.add_argument(
        "--keep-out-box",
        action="append",
        default=[],
        type=box6,
        metavar="X0,Y0,Z0,X1,Y1,Z1",
        help="a box the arm and tool must keep out of, base frame, metres (repeatable; "
        "write --keep-out-box=-1,... when the first number is negative)",
    )
    plan.add_argument(
        "--cell-plane",
        action="append",
        default=[],
        type=cell_plane,
        metavar="NX,NY,NZ,D",
        help="a surface of the cell besides the one the base stands on (a wall, the floor "
        "below a wall-mounted arm), base frame: the arm keeps to n . p >= D (repeatable; "
        "write --cell-plane=-1,... when the first number is negative)",
    )
    plan.add_argument("--out", required=True, metavar="TRAJ.csv")
    plan.add_argument(
        "--plot",
        metavar="OUT.png",
        help="also write a picture: TCP speed against the requested one with the causes of "
        "slow-downs, joints against their limits, joint speeds against theirs",
    )
    plan.set_defaults(handler=run)


def _reconstruction(
    recon_file: str,
) -> tuple[ReconstructedPath, ScanModel | None, ReconParams | None]:
    """The reconstruction to plan along: its CSV, and the arrays ``teachpath reconstruct`` wrote
    beside it (``RECON.npz``: the transform, parameters and scan model it used) when they are
    there and belong to it. Returns (path, scan model or None, parameters or None)."""
    from drivers.export import read_reconstruction_csv
    from service.artifacts import ReconstructionCodec
    from service.cli.reconstruct import sidecar_of
    from service.parsing import load_arrays

    path = read_reconstruction_csv(recon_file)
    sidecar = sidecar_of(recon_file)
    if not sidecar.is_file():
        return path, None, None
    arrays = load_arrays(sidecar)
    stored = ReconstructionCodec.decode(arrays)
    # The CSV holds 9 significant digits; anything more is an edited CSV or another sidecar.
    if stored.points_m.shape != path.points_m.shape or not np.allclose(
        stored.points_m, path.points_m, rtol=0, atol=1e-7
    ):
        note(f"{sidecar.name} does not belong to {recon_file} (other points): not used")
        return path, None, None
    return stored, ReconstructionCodec.scan_model(arrays), ReconstructionCodec.recon_params(arrays)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from drivers.export import write_trajectory_csv
    from recon.plan_params import PlanParams
    from recon.toppra_import import import_toppra
    from service import pipelines
    from service.artifacts import TrajectorySummary
    from service.schemas import TRAJECTORY_PARAMS

    # toppra now, while this is the process's only thread: then without matplotlib (0.3 s;
    # recon.toppra_import). Later, the scan model's threads would rule that out.
    import_toppra()
    out = check_output(args.out, ".csv")
    plot = check_output(args.plot, ".png") if args.plot else None  # refused before any work
    params = params_from_args(PlanParams, args, TRAJECTORY_PARAMS)
    calibration = _calibration(args.ur_calibration, params.robot)
    path, scan_model, recon_params = _reconstruction(args.recon_file)
    T_base_tracker = read_matrix(args.base_from_tracker, "T_base_tracker")
    given = read_matrix(args.scan_from_tracker, "T_scan_tracker")
    wants_scan = args.scan and params.orientation in ("auto", "scan")
    scan = read_scan_for(args) if args.scan else None  # the tool axis, and the collision check
    # A scan given is always checked against: its place is the transform given, the one the
    # reconstruction recorded, or found here by registering the path to it (never dropped).
    if not wants_scan:
        scan_model = None  # the tool axis does not come from the scan
    if scan is not None and given is not None and not wants_scan:
        path = replace(path, T_scan_tracker=given)
    elif scan is not None and (
        given is not None or path.T_scan_tracker is None or (scan_model is None and wants_scan)
    ):
        # A transform given by hand, or none stored, or no stored model: build one here.
        known = given if given is not None else path.T_scan_tracker
        placed = pipelines.place_scan(
            scan, replace(path, T_scan_tracker=known), recon_params=recon_params
        )
        if placed.registration is not None:
            note(
                f"registered the path to the scan to place it ({args.recon_file} came without "
                "the arrays `teachpath reconstruct` writes beside it); pass "
                "--scan-from-tracker to use a known transform"
            )
        path = replace(path, T_scan_tracker=placed.T_scan_tracker)
        scan_model = placed.model if wants_scan else None
    outcome = pipelines.plan(
        path,
        params=params,
        T_base_tracker=T_base_tracker,
        scan_model=scan_model,
        recon_params=recon_params,
        scan=scan,
        keep_out_boxes=args.keep_out_box,
        cell_planes=args.cell_plane,
        start_from="given" if args.start_q_rad is not None else "home",
        calibration=calibration,
    )
    meta = TrajectorySummary.model_validate(outcome.summary()).file_meta()
    write_trajectory_csv(
        out, outcome.trajectory, meta={**meta, "source": Path(args.recon_file).name}
    )
    if plot is not None:
        from service.plots import plot_plan

        plot_plan(plot, outcome.trajectory, title=Path(out).name)
    print("\n".join(outcome.lines()))
    return 0


def _calibration(path: str | None, robot: str) -> DHCalibration | None:
    """The arm's calibration from ``--ur-calibration``, checked against the robot model before
    any work (None without the option).

    Raises
    ------
    InputFileError
        The file is not a calibration.
    ValueError
        It is another arm type's.
    """
    if path is None:
        return None
    from drivers.robot.ur_calibration import read_ur_calibration
    from recon import kinematics

    calibration = read_ur_calibration(path)
    kinematics.with_calibration(kinematics.model(robot), calibration)
    return calibration
