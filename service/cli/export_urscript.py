"""``teachpath export-urscript``: a planned trajectory as a program for UR's teach pendant."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.options import OneLineParser, check_output, positive

#: The command's name, and its line in ``teachpath --help``.
NAME = "export-urscript"
HELP = "write a planned trajectory as a standalone URScript program"


def add_parser(commands: argparse._SubParsersAction[OneLineParser]) -> None:
    export = commands.add_parser(
        NAME,
        help=HELP,
        description="Writes TRAJ.csv (from teachpath plan) as a URScript program for the teach "
        "pendant: the TCP and payload set, movej to the approach pose, movel down, the path "
        "as servoj at the controller rate (or movep blends within --tolerance-m), movel up. "
        "The program halts at once if the arm does not stand at the plan's start.",
    )
    export.add_argument("traj_file", metavar="TRAJ.csv")
    export.add_argument("--out", required=True, metavar="PROGRAM.script")
    export.add_argument("--robot", help="the UR model (default: the one the file names)")
    export.add_argument("--mode", choices=("servoj", "movep"), default="servoj")
    export.add_argument(
        "--tolerance-m",
        type=positive,
        default=5e-4,
        help="movep: largest TCP deviation of the blended path from the plan (default 0.0005)",
    )
    export.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from drivers.export import read_trajectory_csv
    from drivers.files import atomic_path
    from drivers.robot.urscript import program_header, urscript_program

    out = check_output(args.out, ".script")
    read = read_trajectory_csv(args.traj_file, robot=args.robot)
    meta = read.meta
    program = urscript_program(
        read.trajectory,
        tcp_pose=meta.get("tcp_pose") or (0.0,) * 6,
        payload_kg=meta.get("payload_kg"),
        payload_cog_m=meta.get("payload_cog_m") or (0.0, 0.0, 0.0),
        mode=args.mode,
        tolerance_m=args.tolerance_m,
        header=program_header(meta, Path(args.traj_file).name),
    )
    with atomic_path(out) as tmp:
        tmp.write_text(program)
    payload = meta.get("payload_kg")
    print(
        f"wrote {out} ({program.count(chr(10))} lines, {args.mode}); payload: "
        + (
            "not set, the installation's is kept (plan with --payload-kg to set it)"
            if payload is None
            else f"{payload:g} kg set"
        )
    )
    return 0
