"""Log commands the fake never finishes: ur_rtde waits up to 300 s for a command, so a bug in
the fake would otherwise look like a silent hang of the test."""

from __future__ import annotations

import logging
import threading

from drivers.robot.fake_ur.control_script import REALTIME_COMMANDS
from drivers.robot.fake_ur.controller import FakeController

log = logging.getLogger("fake_ur.watchdog")

#: A command counts as stuck this long after it should have finished (s).
GRACE_S = 5.0
#: A command not answered "done" after this long, with no motion running for it, is stuck
#: too (s): never picked up, or picked up and lost.
PICKUP_S = 1.0


def watch(controller: FakeController, stop: threading.Event, *, period_s: float = 1.0) -> None:
    """Check every ``period_s`` (until ``stop``) and log a warning for each stuck command."""
    pending_since: float | None = None
    warned: set[tuple[str, float]] = set()
    while not stop.wait(period_s):
        with controller.lock:
            busy = controller.busy_command()
            # Only ur_rtde's control script reads the command register (a standalone program
            # leaves whatever a client wrote there last).
            playing = (
                controller.runtime_state == 2
                and controller.script is not None
                and controller.script.is_rtde_control
            )
            offset = controller.script.int_offset if controller.script else 0
            cmd = controller.in_int[offset]
            # Done is the only answer to a command; "executing" is not one -- a command the
            # loop took but neither finished nor started moving for hangs the client too.
            answered = controller.out_int[offset] == 2
            now = controller.t_s
        if busy is not None:
            what, running_s, expected_s = busy
            key = (what, round(now - running_s, 3))
            if running_s > expected_s + GRACE_S and key not in warned:
                warned.add(key)
                log.warning(
                    "stuck command: %s has run %.1f s (expected %.1f s)",
                    what,
                    running_s,
                    expected_s,
                )
        if playing and cmd != 0 and cmd not in REALTIME_COMMANDS and not answered and busy is None:
            pending_since = now if pending_since is None else pending_since
            if now - pending_since > PICKUP_S:
                log.warning(
                    "command %d written by the client was never picked up, or never answered "
                    "and no motion runs for it",
                    cmd,
                )
                pending_since = now
        else:
            pending_since = None
