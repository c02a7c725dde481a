"""Service fixtures: an app on a temporary data folder, driven in-process with httpx."""

from __future__ import annotations

import os
import time

import pytest
from fastapi.testclient import TestClient

from drivers.scanning.pointcloud import write_scan
from drivers.tracking.canonical_csv import write_trace_csv
from recon import scenes
from service.app import create_app
from service.settings import Settings

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
#: Where the box-corner scene sits in front of a UR5e (base frame).
T_BASE_TRACKER = [[1, 0, 0, 0.35], [0, 1, 0, -0.05], [0, 0, 1, 0.1], [0, 0, 0, 1]]


#: ``TEACHPATH_TEST_DATABASE=postgresql``: every service these tests start uses a fresh database
#: of a real PostgreSQL server (``make test`` runs the store and API suites so, after SQLite).
ON_POSTGRES = os.environ.get("TEACHPATH_TEST_DATABASE") == "postgresql"
_postgres: list = []  # the server, once started


def test_database_url() -> str | None:
    """A fresh PostgreSQL database's URL when the suites run on PostgreSQL; else None (SQLite in
    the data folder)."""
    if not ON_POSTGRES:
        return None
    if not _postgres:
        from tests.postgres import PostgresServer

        _postgres.append(PostgresServer())
    return _postgres[0].new_database()


test_database_url.__test__ = False  # a helper, not a test


@pytest.fixture(scope="session", autouse=True)
def _stop_postgres():
    yield
    while _postgres:
        _postgres.pop().stop()


def make_settings(data_dir, **overrides) -> Settings:
    url = test_database_url()
    if url is not None:
        overrides.setdefault("database_url", url)
    # A worker warmed at start imports the pipelines (about a second of CPU): hundreds of test
    # apps that never run a job would pay it; the warm start has its own test.
    overrides.setdefault("warm_workers", False)
    return Settings(data_dir=data_dir, token=TOKEN, cpu_workers=1, max_upload_mb=5, **overrides)


@pytest.fixture(scope="session")
def scene_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    scene = scenes.box_corner(0)
    write_trace_csv(folder / "trace.csv", scene.recording)
    write_scan(folder / "scan.ply", scene.scan)
    return {
        "trace": (folder / "trace.csv").read_bytes(),
        "scan": (folder / "scan.ply").read_bytes(),
    }


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    app = create_app(make_settings(tmp_path_factory.mktemp("data")))
    with TestClient(app, headers=AUTH) as test_client:
        yield test_client


def wait(client, job: dict, timeout_s: float = 120.0) -> dict:
    """Poll a job until it has finished."""
    deadline = time.monotonic() + timeout_s
    while job["state"] not in ("succeeded", "failed", "cancelled"):
        assert time.monotonic() < deadline, f"job {job['id']} did not finish"
        time.sleep(0.1)
        job = client.get(f"/jobs/{job['id']}").json()
    return job


def planned_session(
    client, scene_files, speeds_m_s, name="arm", *, start_q_rad=None
) -> tuple[str, dict]:
    """A calibrated session with the box-corner trace and scan, reconstructed and planned at
    each speed (from ``start_q_rad``, default: where the service's arm is). Returns the session
    id and {speed: trajectory id}."""
    sid = client.post("/sessions", json={"name": name}).json()["id"]
    client.put(f"/sessions/{sid}/recording", files={"file": ("t.csv", scene_files["trace"])})
    client.put(f"/sessions/{sid}/scan", files={"file": ("s.ply", scene_files["scan"])})
    client.put(f"/sessions/{sid}/calibration", json={"T_base_tracker": T_BASE_TRACKER})
    recon = wait(client, client.post(f"/sessions/{sid}/reconstructions", json={}).json())
    trajectories = {}
    for speed in speeds_m_s:
        body = {"reconstruction_id": recon["result"]["reconstruction_id"], "speed_m_s": speed}
        if start_q_rad is not None:
            body["start_q_rad"] = list(start_q_rad)
        job = wait(client, client.post(f"/sessions/{sid}/trajectories", json=body).json())
        trajectories[speed] = job["result"]["trajectory_id"]
    return sid, trajectories


@pytest.fixture(scope="module")
def session(client, scene_files):
    """A session with the box-corner trace and scan uploaded and its calibration set."""
    sid = client.post("/sessions", json={"name": "box"}).json()["id"]
    assert (
        client.put(
            f"/sessions/{sid}/recording", files={"file": ("trace.csv", scene_files["trace"])}
        ).status_code
        == 201
    )
    assert (
        client.put(
            f"/sessions/{sid}/scan", files={"file": ("scan.ply", scene_files["scan"])}
        ).status_code
        == 201
    )
    assert (
        client.put(
            f"/sessions/{sid}/calibration", json={"T_base_tracker": T_BASE_TRACKER}
        ).status_code
        == 200
    )
    return sid
