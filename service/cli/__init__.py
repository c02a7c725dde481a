"""The ``teachpath`` command line: one module per command, shared option groups in
:mod:`service.cli.options` (the way python-can lays out its scripts).

Every command turns bad input into one line on stderr that says what is wrong and what to do, and
a non-zero exit status; it never leaves a partial output file behind. Each command module imports
its heavy dependencies inside its handler, and only the command named is built in full
(:func:`build_parser`), so each command imports what it needs.
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


def build_parser(argv: Sequence[str] | None = None) -> OneLineParser:
    """The command line's parser; with ``argv``, only the command it names is built in full.

    A command's options are built from the parameter specifications (pydantic, the arm models:
    most of a second of imports), which the other commands do not need: they are listed by name
    and help line only, so ``teachpath --help`` and each command start with what they use.
    Without ``argv`` every command is built.
    """
    parser = OneLineParser(
        prog="teachpath",
        description="Reconstruct hand-traced robot paths with a scan of the workpiece.",
    )
    commands = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    names = {command.NAME for command in COMMANDS}
    words = [word for word in (argv or ()) if not word.startswith("-")]
    chosen = words[0] if words and words[0] in names else None
    for command in COMMANDS:
        if argv is None or chosen == command.NAME:
            command.add_parser(commands)
        else:
            commands.add_parser(command.NAME, help=command.HELP)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``teachpath`` console script."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv if argv else None)
    args = parser.parse_args(argv)
    if not hasattr(args, "handler"):  # a command listed by name only: never built, never run
        parser.error(f"could not tell the command from {' '.join(argv)!r}")
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
