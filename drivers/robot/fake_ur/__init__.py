"""A fake Universal Robots controller that the pinned ur_rtde client talks to on loopback.

It speaks RTDE (30004), the dashboard server (29999) and the script ports (30001-30003), runs
ur_rtde's uploaded control script by emulating its register protocol, moves an arm integrated by
the ``sim`` backend's model, and takes faults on demand through a JSON line control channel
(port 30100). It runs as its own process: ur_rtde's constructors hold the GIL while they block,
so a fake in the client's process would deadlock. See :mod:`.server` for ports and commands.

``teachpath fake-ur --host 127.0.0.2 [--robot ur5e]`` (:func:`main`) runs one by hand. This
module imports nothing heavy, so a CLI can build its parser with :func:`add_arguments`.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys

__all__ = ["add_arguments", "main", "run_fake_ur", "run_from_args"]


def run_fake_ur(host: str, robot: str = "ur5e", *, powered: bool = True) -> None:
    """Serve a fake controller on ``host`` until SIGINT/SIGTERM or a ``shutdown`` request.

    Raises
    ------
    ValueError
        ``host`` is not a loopback address: the fake never listens beyond this machine.
    OSError
        A port on ``host`` is taken (another fake or a real controller): pick another loopback
        address (127.0.0.2, 127.0.0.3, ...).
    """
    import ipaddress

    from drivers.robot.fake_ur.server import FakeUR

    try:
        loopback = ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        raise ValueError(
            f"--host {host!r} is not a loopback address; the fake controller listens on "
            "127.0.0.x only (use 127.0.0.2, 127.0.0.3, ... to run several)"
        )

    fake = FakeUR(host, robot, powered=powered)
    fake.start()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: fake.shutdown())
    print(f"fake {robot} controller listening on {host} (ctrl-C to stop)", flush=True)
    fake.wait()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``fake-ur`` options, for a CLI's sub-command parser."""
    parser.add_argument("--host", default="127.0.0.2", help="loopback address to listen on")
    parser.add_argument("--robot", default="ur5e", help="UR model (ur5e, ur10e, ur5, ...)")
    parser.add_argument(
        "--powered-off", action="store_true", help="start powered off (brakes engaged)"
    )
    parser.add_argument("--log-level", default="INFO", help="logging level (DEBUG, INFO, ...)")


def run_from_args(args: argparse.Namespace) -> int:
    """Run with parsed :func:`add_arguments` options; the process exit status."""
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s"
    )
    try:
        run_fake_ur(args.host, args.robot, powered=not args.powered_off)
    except OSError as exc:
        print(f"cannot listen on {args.host}: {exc}", file=sys.stderr)
        return 2
    return 0


def main(argv: list[str] | None = None) -> int:
    """``teachpath fake-ur``: run a fake UR controller for the ``ur_rtde`` backend."""
    parser = argparse.ArgumentParser(
        prog="teachpath fake-ur",
        description="A fake UR controller on a loopback address; point the ur_rtde backend's "
        "host at it.",
    )
    add_arguments(parser)
    try:
        return run_from_args(parser.parse_args(argv))
    except ValueError as exc:
        print(f"teachpath fake-ur: error: {exc}", file=sys.stderr)
        return 1
