"""The ``teachpath`` command line: one module per command, shared option groups in
:mod:`service.cli.options` (the way python-can lays out its scripts).

Every command turns bad input into one line on stderr that says what is wrong and what to do, and
a non-zero exit status; it never leaves a partial output file behind. Each command module imports
its heavy dependencies inside its handler, so ``teachpath --help`` stays fast.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from drivers.errors import DriverError
from recon.errors import ReconError
from service.cli import (
    bundle,
    calibrate,
    demo,
    dry_run,
    export_urscript,
    fake_ur,
    plan,
    reconstruct,
    record,
    replay,
    serve,
)
from service.cli.options import EXIT_FAILURE, OneLineParser

#: The commands in the order ``--help`` lists them.
COMMANDS = (
    reconstruct,
    plan,
    dry_run,
    export_urscript,
    record,
    calibrate,
    serve,
    bundle,
    replay,
    fake_ur,
    demo,
)


def build_parser() -> OneLineParser:
    parser = OneLineParser(
        prog="teachpath",
        description="Reconstruct hand-traced robot paths with a scan of the workpiece.",
    )
    commands = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    for command in COMMANDS:
        command.add_parser(commands)
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
