"""The real server (teachpath serve, uvicorn) on a free loopback port, driven over HTTP.

session -> upload -> reconstruct -> restart the server -> plan -> dry run: nothing is lost.
"""

from __future__ import annotations

import pytest

from tests.server_process import Server
from tests.service.conftest import T_BASE_TRACKER

TOKEN = "e2e-token-abcdefghijklmnop"


@pytest.fixture
def server_dir(tmp_path):
    return tmp_path / "data"


def test_whole_flow_over_http_with_a_restart(server_dir, scene_files):
    server = Server(server_dir, token=TOKEN)
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

    server = Server(server_dir, token=TOKEN)  # a new process on the same data
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
