"""``teachpath fake-ur``: a fake UR controller on a loopback address, for the ur_rtde backend."""

from __future__ import annotations

import argparse

from service.cli.options import OneLineParser

#: The command's name, and its line in ``teachpath --help``.
NAME = "fake-ur"
HELP = "run a fake UR controller on a loopback address (for the ur_rtde backend)"


def add_parser(commands: argparse._SubParsersAction[OneLineParser]) -> None:
    from drivers.robot import fake_ur  # light: imports argparse and logging only

    fake = commands.add_parser(
        NAME,
        help=HELP,
        description="Serves RTDE (30004), the dashboard (29999) and the script ports "
        "(30001-30003) of an emulated UR controller that ur_rtde drives, so the service's "
        "real-robot path can be tried without a robot: start the service with "
        "TEACHPATH_UR_HOST set to the same address. Loopback addresses only.",
    )
    fake_ur.add_arguments(fake)
    fake.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from drivers.robot import fake_ur

    return fake_ur.run_from_args(args)
