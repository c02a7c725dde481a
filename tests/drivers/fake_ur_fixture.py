"""Run the fake UR controller (``drivers.robot.fake_ur``) in its own process for a test.

ur_rtde's constructors hold the GIL while they block, so the fake must not live in the test
process's threads. The ports are fixed (as on a real controller), so each fake gets its own
loopback address: :func:`free_loopback_host` picks one whose ports are free.

Use the ``fake_ur`` fixture (one fake per module, reset before each test) or
:class:`FakeURProcess` directly. Faults are injected through the fake's JSON line control
channel: ``fake_ur.control("protective_stop")``.
"""

from __future__ import annotations

import json
import os
import random
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.robot.fake_ur.server import CONTROL_PORT, DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORTS

REPO = Path(__file__).resolve().parents[2]
#: Loopback addresses the fixtures may use (127.0.0.9 and .11 belong to other tests).
CANDIDATE_HOSTS = [f"127.0.0.{i}" for i in range(20, 250)]
#: Bound on the fake's start-up (an interpreter importing numpy and scipy on a busy machine).
START_TIMEOUT_S = 30.0
#: The RTDE watchdog of a service that drives the fake (Hz, its slowest). Here the controller
#: shares two cores with the service, its workers, a browser and the tests: its 2 Hz default
#: (a real controller on its own box) tripped at a run's start once in about 1,600 tests, the
#: client silent 0.5 s on a loaded machine. The watchdog's own tests keep 2 Hz
#: (tests/drivers/test_fake_ur.py).
SERVICE_WATCHDOG_HZ = 0.5
#: How long the fake's state may stand still before such a service's run fails as a lost link
#: (s; 0.5 on a real controller): a run on a loaded test machine once failed "no new data from
#: the controller for 0.5 s" (the server's log, in the failed browser test's report).
SERVICE_STALE_AFTER_S = 2.0


def _ports_free(host: str) -> bool:
    for port in (DASHBOARD_PORT, RTDE_PORT, CONTROL_PORT, *SCRIPT_PORTS):
        try:
            with socket.create_server((host, port)):
                pass
        except OSError:
            return False
    return True


def free_loopback_host() -> str:
    """A 127.0.0.x address whose controller ports are all free now."""
    for host in random.sample(CANDIDATE_HOSTS, len(CANDIDATE_HOSTS)):
        if _ports_free(host):
            return host
    raise RuntimeError("no loopback address with free UR ports (127.0.0.20-249)")


class FakeURProcess:
    """A fake controller process on a free loopback address.

    Parameters
    ----------
    robot : str
    log_path : Path
        Where the fake's log goes (shown when a test fails).
    """

    def __init__(self, log_path: Path, robot: str = "ur5e", *, extra_args=()) -> None:
        self.robot = robot
        self.log_path = log_path
        self.extra_args = tuple(extra_args)
        self.host = ""
        self.process: subprocess.Popen | None = None
        self._channel: socket.socket | None = None
        self._reader = None

    def start(self) -> FakeURProcess:
        """Start the fake and wait until it answers on its control channel."""
        for _attempt in range(5):  # another test run may take the address between check and bind
            self.host = free_loopback_host()
            log = open(self.log_path, "ab")  # noqa: SIM115 - handed to the child process
            self.process = subprocess.Popen(
                [sys.executable, "-m", "drivers.robot.fake_ur", "--host", self.host]
                + ["--robot", self.robot, *self.extra_args],
                cwd=REPO,
                stdout=log,
                stderr=subprocess.STDOUT,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
            log.close()
            deadline = time.monotonic() + START_TIMEOUT_S
            while time.monotonic() < deadline and self.process.poll() is None:
                try:
                    self._channel = socket.create_connection((self.host, CONTROL_PORT), 1.0)
                    self._channel.settimeout(10.0)
                    self._reader = self._channel.makefile("rb")
                    self.control("status")
                    return self
                except OSError:
                    time.sleep(0.05)
            self.stop()
        raise RuntimeError(f"the fake UR controller did not start; log:\n{self.log_text()}")

    def control(self, cmd: str, **arguments) -> dict:
        """Send one control channel request; the fake's reply (raises if it failed)."""
        assert self._channel is not None and self._reader is not None
        self._channel.sendall((json.dumps({"cmd": cmd, **arguments}) + "\n").encode())
        reply = json.loads(self._reader.readline())
        if not reply.pop("ok"):
            raise RuntimeError(f"fake controller refused {cmd}: {reply['error']}")
        return reply

    def send_program(self, text: str, port: int = SCRIPT_PORTS[1]) -> int:
        """Send a URScript program to a script port and close the connection (which completes
        it). The number of the controller's last program before it, for :meth:`wait_program`."""
        before = self.control("program_status")["number"]
        with socket.create_connection((self.host, port), timeout=5.0) as sock:
            sock.sendall(text.encode())
        return before

    def wait_program(self, after: int, timeout_s: float = 30.0, *, running=False) -> dict:
        """The ``program_status`` of the first program after the controller's program number
        ``after`` once it has ended (or, ``running``, once it runs: for programs that run a
        while -- one that ends between two polls is never seen running). Numbers, not start
        times: a refused program and the next one can start in the same control period."""
        deadline = time.monotonic() + timeout_s
        while True:
            status = self.control("program_status")
            if status["number"] > after and (status["state"] != "running") != running:
                return status
            if time.monotonic() > deadline:
                raise TimeoutError(f"the program did not get there: {status}")
            time.sleep(0.02)

    def program_trace(self, every: int = 1) -> dict:
        """The whole trace of the last program (every ``every``-th sample), as arrays."""
        parts: dict[str, list] = {"t_s": [], "q_rad": [], "tcp_pose": [], "line": []}
        start = 0
        while True:
            page = self.control("program_trace", start=start, every=every)
            for name in parts:
                parts[name].extend(page[name])
            if not page["t_s"] or page["next"] >= page["total"]:
                break
            start = page["next"]
        return {name: np.array(values) for name, values in parts.items()}

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def stop(self) -> None:
        """Shut the fake down (asking first, then terminating, then killing)."""
        if self._channel is not None:
            try:
                self.control("shutdown")
            except (OSError, ValueError, RuntimeError):
                pass
            self._channel.close()
            self._channel = None
        if self.process is not None:
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.terminate()
                try:
                    self.process.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait()
            self.process = None


@pytest.fixture(scope="module")
def fake_ur_process(tmp_path_factory):
    """One fake ur5e controller for the module."""
    fake = FakeURProcess(tmp_path_factory.mktemp("fake_ur") / "fake_ur.log").start()
    yield fake
    fake.stop()


@pytest.fixture
def fake_ur(fake_ur_process):
    """The module's fake, reset (arm at home, no faults, no program) before the test. Its log
    of the test is printed at teardown: pytest shows it when the test fails."""
    fake_ur_process.control("reset")
    offset = len(fake_ur_process.log_text())
    yield fake_ur_process
    print("--- fake UR log ---\n" + fake_ur_process.log_text()[offset:])
