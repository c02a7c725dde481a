"""``teachpath dry-run``: a planned trajectory executed on the simulated arm."""

from __future__ import annotations

import argparse

from service.cli.options import EXIT_FAILURE, OneLineParser

#: The command's name, and its line in ``teachpath --help``.
NAME = "dry-run"
HELP = "execute a planned trajectory on the simulated arm and report"


def add_parser(commands: argparse._SubParsersAction[OneLineParser]) -> None:
    dry = commands.add_parser(
        NAME,
        help=HELP,
        description="Runs TRAJ.csv on a simulated UR arm (faster than real time) and prints "
        "duration, tracking deviation, margins, speed drops and faults.",
    )
    dry.add_argument("traj_file", metavar="TRAJ.csv")
    dry.add_argument(
        "--robot",
        help="the UR model to run it on (default: the one the file was planned for; a file "
        "planned for another is refused)",
    )
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
    dry.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from drivers.export import read_trajectory_csv
    from recon.kinematics import model
    from service import pipelines

    if args.robot is not None:
        model(args.robot)  # an unknown arm is a one-line error before reading anything
    if not args.tolerance_m > 0:
        raise ValueError(f"--tolerance-m must be positive, got {args.tolerance_m}")
    trajectory = read_trajectory_csv(args.traj_file, robot=args.robot).trajectory
    outcome = pipelines.dry_run(trajectory, mode=args.mode, tolerance_m=args.tolerance_m)
    print("\n".join(outcome.lines()))
    return 0 if outcome.passed else EXIT_FAILURE
