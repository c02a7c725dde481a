"""The real server (``teachpath serve``, uvicorn) in a child process on a free port of
127.0.0.1, for the end-to-end, schemathesis and browser tests."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx


class Server:
    """``teachpath serve`` on a free loopback port with ``token``, answering ``/health``.

    Parameters
    ----------
    data_dir : Path
    token : str or None
        None: the server's own (generated on first start in ``data_dir/token``).
    demo : bool
        Seed the demo session (``--demo``).
    timeout_s : float
        Bound on each request of :attr:`client`.
    settings : dict, optional
        More ``TEACHPATH_*`` settings (e.g. ``{"TEACHPATH_UR_HOST": fake.host}``, a fake
        controller on loopback); without one, no controller of the environment is used.
    """

    def __init__(
        self,
        data_dir: Path,
        *,
        token: str | None,
        demo: bool = False,
        timeout_s: float = 60.0,
        settings: dict[str, str] | None = None,
    ) -> None:
        env = {**os.environ, "TEACHPATH_TOKEN": token or ""}
        if token is None:
            env.pop("TEACHPATH_TOKEN")
        env.pop("TEACHPATH_UR_HOST", None)  # never a real controller from a test
        # The suites start dozens of servers, most never running a job: a warm start would
        # import the pipelines in a worker beside each (CPU the real-time tests next to them
        # need). The warm start has its own tests (tests/service/test_warm_workers.py).
        env.setdefault("TEACHPATH_WARM_WORKERS", "false")
        env.update(settings or {})
        command = [sys.executable, "-m", "service.cli", "serve", "--port", "0"]
        command += ["--data-dir", str(data_dir)] + (["--demo"] if demo else [])
        self.process = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
        )
        try:
            self._start(token, timeout_s)
        except BaseException:
            self.process.kill()  # a server that did not come up is not left behind
            self.process.wait()
            raise
        # Keep reading its output, so that a chatty server never blocks on a full pipe.
        self.output: list[str] = []
        threading.Thread(target=self._drain, name="server output", daemon=True).start()

    def _drain(self) -> None:
        for line in self.process.stdout:
            self.output.append(line)

    def _start(self, token: str | None, timeout_s: float) -> None:
        deadline = time.monotonic() + 60
        self.url = None
        #: The pairing code the server printed (the last of its start-up lines).
        self.pairing_code = None
        while self.pairing_code is None:
            assert time.monotonic() < deadline, "the server did not print its URL and code"
            line = self.process.stdout.readline()
            assert line or self.process.poll() is None, "the server exited"
            match = re.search(r"open (http://127\.0\.0\.1:\d+)/\?token=(\S+)", line)
            if match:
                self.url = match.group(1)
                assert token is None or match.group(2) == token
                token = match.group(2)
            code = re.search(r"pairing code for another screen: ([0-9]{6}) ", line)
            if code:
                self.pairing_code = code.group(1)
        self.token = token
        self.client = httpx.Client(
            base_url=self.url, timeout=timeout_s, headers={"Authorization": f"Bearer {token}"}
        )
        for _ in range(100):
            try:
                if self.client.get("/health").status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        raise AssertionError("the server did not answer /health")

    @property
    def start_url(self) -> str:
        """The page's address with the token, as the server prints it."""
        return f"{self.url}/?token={self.token}"

    def wait(self, job: dict, timeout_s: float = 120.0) -> dict:
        """Poll a job until it has finished."""
        deadline = time.monotonic() + timeout_s
        while job["state"] not in ("succeeded", "failed", "cancelled"):
            assert time.monotonic() < deadline, f"job {job['id']} did not finish"
            time.sleep(0.2)
            job = self.client.get(f"/jobs/{job['id']}").json()
        return job

    def stop(self) -> None:
        """Interrupt it as Ctrl-C does; kill it if it has not ended within 30 s."""
        self.client.close()
        self.process.send_signal(signal.SIGINT)
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
