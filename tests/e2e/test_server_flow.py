"""The real server (teachpath serve, uvicorn) on a free loopback port, driven over HTTP.

session -> upload -> reconstruct -> restart the server -> plan -> dry run: nothing is lost.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import httpx
import pytest

from tests.service.conftest import T_BASE_TRACKER

TOKEN = "e2e-token-abcdefghijklmnop"


class Server:
    def __init__(self, data_dir) -> None:
        env = {**os.environ, "TEACHPATH_TOKEN": TOKEN}
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "service.cli",
                "serve",
                "--port",
                "0",
                "--data-dir",
                str(data_dir),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        deadline = time.monotonic() + 60
        self.url = None
        while self.url is None:
            assert time.monotonic() < deadline, "the server did not print its URL"
            line = self.process.stdout.readline()
            assert line or self.process.poll() is None, "the server exited"
            match = re.search(r"open (http://127\.0\.0\.1:\d+)/\?token=(\S+)", line)
            if match:
                self.url = match.group(1)
                assert match.group(2) == TOKEN
        self.client = httpx.Client(
            base_url=self.url, timeout=60, headers={"Authorization": f"Bearer {TOKEN}"}
        )
        for _ in range(100):
            try:
                if self.client.get("/health").status_code == 200:
                    return
            except httpx.TransportError:
                time.sleep(0.1)
        raise AssertionError("the server did not answer /health")

    def wait(self, job: dict) -> dict:
        deadline = time.monotonic() + 120
        while job["state"] not in ("succeeded", "failed", "cancelled"):
            assert time.monotonic() < deadline
            time.sleep(0.2)
            job = self.client.get(f"/jobs/{job['id']}").json()
        return job

    def stop(self) -> None:
        self.client.close()
        self.process.send_signal(signal.SIGINT)
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


@pytest.fixture
def server_dir(tmp_path):
    return tmp_path / "data"


def test_whole_flow_over_http_with_a_restart(server_dir, scene_files):
    server = Server(server_dir)
    try:
        assert server.url.startswith("http://127.0.0.1:")
        assert server.client.get("/sessions", headers={"Authorization": ""}).status_code == 401
        sid = server.client.post("/sessions", json={"name": "e2e"}).json()["id"]
        assert (
            server.client.put(
                f"/sessions/{sid}/recording", files={"file": ("trace.csv", scene_files["trace"])}
            ).status_code
            == 201
        )
        assert (
            server.client.put(
                f"/sessions/{sid}/scan", files={"file": ("scan.ply", scene_files["scan"])}
            ).status_code
            == 201
        )
        server.client.put(f"/sessions/{sid}/calibration", json={"T_base_tracker": T_BASE_TRACKER})
        job = server.wait(server.client.post(f"/sessions/{sid}/reconstructions", json={}).json())
        assert job["state"] == "succeeded", job
        reconstruction = job["result"]["reconstruction_id"]
    finally:
        server.stop()

    server = Server(server_dir)  # a new process on the same data
    try:
        assert server.client.get(f"/sessions/{sid}").json()["name"] == "e2e"
        listed = server.client.get(f"/sessions/{sid}/reconstructions").json()
        assert [r["id"] for r in listed] == [reconstruction]
        job = server.wait(
            server.client.post(
                f"/sessions/{sid}/trajectories",
                json={"reconstruction_id": reconstruction, "robot": "ur5e", "speed_m_s": 0.05},
            ).json()
        )
        assert job["state"] == "succeeded", job
        trajectory = job["result"]["trajectory_id"]
        job = server.wait(
            server.client.post(
                f"/sessions/{sid}/executions", json={"trajectory_id": trajectory, "backend": "sim"}
            ).json()
        )
        assert job["state"] == "succeeded", job
        report = server.client.get(
            f"/sessions/{sid}/executions/{job['result']['execution_id']}"
        ).json()
        assert report["summary"]["completed"]
        page = server.client.get("/", headers={"Authorization": ""})
        assert page.status_code == 200 and "teachpath" in page.text
    finally:
        server.stop()
