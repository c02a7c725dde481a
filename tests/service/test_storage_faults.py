"""A full disk or a busy database: named 503s with Retry-After (never a 500, never blamed on the
upload), /health degraded while it lasts, and a clean recovery once the fault is gone."""

from __future__ import annotations

import shutil
from collections import namedtuple

import pytest
import sqlalchemy.exc
from fastapi.testclient import TestClient

from service import errors
from service.api import health as health_route
from service.app import create_app
from tests.service.conftest import AUTH, make_settings

Usage = namedtuple("Usage", "total used free")


@pytest.fixture
def app_client(tmp_path):
    app = create_app(make_settings(tmp_path / "data"))
    with TestClient(app, headers=AUTH) as client:
        yield app.state.services, client


def test_an_upload_onto_a_full_disk_is_a_503_storage_full_and_recovers(
    app_client, scene_files, monkeypatch
):
    _services, client = app_client
    sid = client.post("/sessions", json={"name": "disk"}).json()["id"]
    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda path: Usage(10**12, 10**12, 1 << 20))
    full = client.put(f"/sessions/{sid}/recording", files={"file": ("t.csv", scene_files["trace"])})
    assert full.status_code == 503, full.text
    assert full.json()["code"] == "storage_full" and "free space" in full.json()["message"]
    assert full.headers["Retry-After"] == str(errors.STORAGE_RETRY_AFTER_S)
    health = client.get("/health").json()
    assert health["status"] == "degraded" and "storage_full" in health["problems"]
    assert client.get(f"/sessions/{sid}").json()["recording_id"] is None  # nothing stored
    # Space again: the same upload is stored, and /health is ok once the window has passed.
    monkeypatch.setattr(shutil, "disk_usage", real)
    stored = client.put(
        f"/sessions/{sid}/recording", files={"file": ("t.csv", scene_files["trace"])}
    )
    assert stored.status_code == 201, stored.text
    monkeypatch.setattr(health_route, "STORAGE_FAULT_WINDOW_S", 0.0)
    assert client.get("/health").json()["status"] == "ok"


def test_a_busy_database_is_a_503_database_busy_and_loses_nothing(app_client, monkeypatch):
    services, client = app_client
    kept = client.post("/sessions", json={"name": "kept"}).json()["id"]
    store = services.store
    real = store.create_session

    def locked(*args, **kwargs):
        raise sqlalchemy.exc.OperationalError("INSERT", {}, Exception("database is locked"))

    monkeypatch.setattr(store, "create_session", locked)
    busy = client.post("/sessions", json={"name": "new"})
    assert busy.status_code == 503, busy.text
    assert busy.json()["code"] == "database_busy"
    assert busy.headers["Retry-After"] == str(errors.STORAGE_RETRY_AFTER_S)
    health = client.get("/health").json()
    assert health["status"] == "degraded" and "database_busy" in health["problems"]
    monkeypatch.setattr(store, "create_session", real)
    assert client.post("/sessions", json={"name": "new"}).status_code == 201
    assert {s["name"] for s in client.get("/sessions").json()} == {"kept", "new"}
    assert client.get(f"/sessions/{kept}").status_code == 200


def test_a_fault_is_reported_by_the_instance_that_met_it_only(app_client, monkeypatch, tmp_path):
    """The faults /health reports are the store's own: another service in the same process (a
    second instance, the next test's app) is not degraded by them."""
    services, client = app_client

    def locked(*args, **kwargs):
        raise sqlalchemy.exc.OperationalError("INSERT", {}, Exception("database is locked"))

    monkeypatch.setattr(services.store, "create_session", locked)
    assert client.post("/sessions", json={"name": "new"}).json()["code"] == "database_busy"
    assert "database_busy" in client.get("/health").json()["problems"]
    other = create_app(make_settings(tmp_path / "other"))
    with TestClient(other, headers=AUTH) as other_client:
        assert other_client.get("/health").json()["status"] == "ok"


def test_other_os_errors_stay_internal_errors_without_a_traceback(app_client, monkeypatch):
    services, client = app_client

    def broken(*args, **kwargs):
        raise PermissionError(13, "permission denied")

    monkeypatch.setattr(services.store, "create_session", broken)
    client_no_raise = TestClient(client.app, headers=AUTH, raise_server_exceptions=False)
    response = client_no_raise.post("/sessions", json={"name": "x"})
    assert response.status_code == 500 and response.json()["code"] == "internal_error"
