"""``teachpath record``: the pen recorded from Motive's NatNet stream into a trace CSV."""

from __future__ import annotations

import argparse
import sys

from service.cli.options import OneLineParser, check_output, positive

#: The command's name, and its line in ``teachpath --help``.
NAME = "record"
HELP = "record the pen from Motive (OptiTrack NatNet) into a trace CSV"


def add_parser(commands: argparse._SubParsersAction[OneLineParser]) -> None:
    record = commands.add_parser(
        NAME,
        help=HELP,
        description="Receives the rigid body from Motive (unicast unless --multicast) until "
        "--duration seconds of stream time, Ctrl-C, or the stream stops, then writes the "
        "tracked frames as a canonical trace CSV (t,x,y,z,qx,qy,qz,qw; metres; seconds from the "
        "first row) and prints frames received, dropped and not tracked. The receiver runs in "
        "a process of its own, so no frame is lost to work elsewhere.",
    )
    record.add_argument("--natnet", required=True, metavar="HOST", help="Motive's address")
    record.add_argument("--rigid-body", required=True, metavar="NAME", help="the pen in Motive")
    record.add_argument("--out", required=True, metavar="FILE.csv")
    record.add_argument(
        "--local", default="127.0.0.1", help="this machine's address on Motive's network"
    )
    record.add_argument("--multicast", action="store_true", help="Motive streams multicast")
    record.add_argument("--command-port", type=int, default=1510)
    record.add_argument("--data-port", type=int, default=1511, help="multicast data port")
    record.add_argument(
        "--duration", type=positive, metavar="S", help="stream seconds (default: until Ctrl-C)"
    )
    record.add_argument(
        "--timeout", type=positive, default=5.0, metavar="S", help="bound on each answer"
    )
    record.add_argument("--units", choices=("m", "mm"), default="m", help="unit Motive streams")
    record.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from drivers.tracking.natnet_source import NatNetConfig
    from drivers.tracking.record import record_natnet

    out = check_output(args.out, ".csv")
    config = NatNetConfig(
        server=args.natnet,
        local=args.local,
        rigid_body=args.rigid_body,
        multicast=args.multicast,
        command_port=args.command_port,
        data_port=args.data_port,
        timeout_s=args.timeout,
        units=args.units,
    )
    print(f"recording {args.rigid_body!r} from {args.natnet}; Ctrl-C to stop", file=sys.stderr)
    result = record_natnet(config, out, duration_s=args.duration)
    print(f"wrote {result.frames_written} frames ({result.duration_s:.2f} s) to {result.path}")
    print(
        f"received {result.frames_received}, dropped {result.frames_dropped}, not tracked "
        f"{result.frames_invalid}; ended by {result.stop_reason}"
    )
    return 0
