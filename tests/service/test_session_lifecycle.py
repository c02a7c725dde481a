"""What the service keeps and refuses around its data: private files, deleted sessions that
receive nothing, captures recovered with what their file holds, requests nested too deeply,
files left by a crash cleaned on the next start."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.capture_runner import HEADER
from service.store import FINISHED
from tests.service.conftest import AUTH, ON_POSTGRES, make_settings
from tests.service.job_targets import Pid, Sleep


def _until(predicate, timeout_s=30.0, what="the condition"):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if value := predicate():
            return value
        time.sleep(0.05)
    raise AssertionError(f"{what} did not happen within {timeout_s} s")


def _finished(client, job_id: str, *, what: str) -> dict:
    """The job once it has finished (bounded wait)."""
    return _until(
        lambda: (r := client.get(f"/jobs/{job_id}").json())["state"] in FINISHED and r,
        what=what,
    )


@pytest.fixture
def app_client(tmp_path):
    app = create_app(make_settings(tmp_path / "data"))
    with TestClient(app, headers=AUTH) as client:
        yield app.state.services, client


def test_the_data_folder_and_every_stored_file_are_private(app_client, scene_files):
    services, client = app_client
    sid = client.post("/sessions", json={"name": "private"}).json()["id"]
    client.put(f"/sessions/{sid}/recording", files={"file": ("t.csv", scene_files["trace"])})
    client.put(f"/sessions/{sid}/scan", files={"file": ("s.ply", scene_files["scan"])})
    # A reconstruction: its arrays and its preview picture (0644 before) are written by a worker.
    job = client.post(f"/sessions/{sid}/reconstructions", json={}).json()
    assert _until(
        lambda: client.get(f"/jobs/{job['id']}").json()["state"] == "succeeded",
        timeout_s=120,
        what="the reconstruction",
    )
    assert any(services.store.data_dir.rglob("*.png"))
    data = services.store.data_dir
    modes = {
        str(path.relative_to(data)): path.stat().st_mode & 0o777
        for path in [data, *data.rglob("*")]
    }
    assert modes["."] == 0o700 if "." in modes else (data.stat().st_mode & 0o777) == 0o700
    loose = {
        name: oct(mode)
        for name, mode in modes.items()
        if mode != (0o700 if (data / name).is_dir() else 0o600)
    }
    assert not loose, loose
    # On PostgreSQL the database is the server's; the files are still the data folder's.
    assert ({"arrays", "uploads"} if ON_POSTGRES else {"teachpath.db", "arrays", "uploads"}) <= set(
        modes
    )


def test_deleting_a_session_cancels_its_jobs_and_nothing_lands_in_it(app_client, tmp_path):
    services, client = app_client
    sid = client.post("/sessions", json={"name": "doomed"}).json()["id"]
    other = client.post("/sessions", json={"name": "kept"}).json()["id"]
    out_id = "rec_deadbeef0000"
    output = services.array_path(out_id)
    record = services.record_when_done(
        sid, "reconstruction", out_id, inputs={}, params={}, result=lambda s: {"id": out_id}
    )
    pid_file = tmp_path / "pid"
    running = services.jobs.submit(
        sid,
        "reconstruction",
        {},
        Sleep(1.5, marker=output, pid_file=str(pid_file)),
        lambda summary: record({}),
        outputs=(output,),
    )
    queued = services.jobs.submit(sid, "reconstruction", {}, Pid(), lambda v: v)
    elsewhere = services.jobs.submit(other, "reconstruction", {}, Pid(), lambda v: v)
    _until(pid_file.exists, what="the job starting")
    assert client.delete(f"/sessions/{sid}").status_code == 204
    for job in (running, queued):
        row = _until(
            lambda job=job: (
                (r := client.get(f"/jobs/{job.id}").json())["state"]
                in ("succeeded", "failed", "cancelled")
                and r
            ),
            what="the job ending",
        )
        assert row["state"] == "cancelled", row
    assert client.get(f"/jobs/{running.id}").json()["error"]["code"] == "session_deleted"
    # The worker's file is gone, no artifact names it, and the other session's job ran.
    assert not os.path.exists(output)
    assert services.store.artifact(out_id) is None
    assert _until(lambda: client.get(f"/jobs/{elsewhere.id}").json()["state"] == "succeeded")
    assert client.get(f"/sessions/{sid}").status_code == 404


def test_nothing_is_added_to_a_deleted_session(app_client):
    from service.store import SessionDeletedError

    services, client = app_client
    sid = client.post("/sessions", json={"name": "gone"}).json()["id"]
    client.delete(f"/sessions/{sid}")
    with pytest.raises(SessionDeletedError):
        services.store.add_arrays_artifact(
            artifact_id="rec_0123456789ab",
            session_id=sid,
            kind="recording",
            arrays={"points_m": np.zeros((3, 3))},
        )
    assert not (services.store.data_dir / "arrays" / "rec_0123456789ab.npz").exists()
    # An upload parsed while its session was deleted: refused, its files removed again.
    with pytest.raises(SessionDeletedError):
        services.store.add_upload_artifact(
            artifact_id="rec_0123456789ac",
            session_id=sid,
            kind="recording",
            arrays={"points_m": np.zeros((3, 3))},
            upload_path="uploads/rec_0123456789ac/trace.csv",
            content=b"x,y,z\n0,0,0\n",
            session_fields={"recording_id": "rec_0123456789ac"},
        )
    assert not (services.store.data_dir / "arrays" / "rec_0123456789ac.npz").exists()
    assert not (services.store.data_dir / "uploads" / "rec_0123456789ac").exists()
    assert services.store.artifact("rec_0123456789ac") is None


def test_a_capture_interrupted_by_a_crash_counts_what_its_file_holds(tmp_path):
    settings = make_settings(tmp_path)
    with TestClient(create_app(settings), headers=AUTH) as first:
        store = first.app.state.services.store
        sid = first.post("/sessions", json={"name": "crash"}).json()["id"]
        row = store.create_capture(sid, {"kind": "replay", "recording_id": "x"})
        t = np.arange(547) / 240.0
        lines = "".join(f"{v:.6f},{0.05 * v:.9g},0,0,0,0,0,1,1\n" for v in t)
        (store.data_dir / row.path).write_text(HEADER + lines)
        store.update_capture(row.id, n_samples=517)  # the runner's last count before the crash
    with TestClient(create_app(settings), headers=AUTH) as second:
        capture = second.get(f"/sessions/{sid}/captures/{row.id}").json()
        assert capture["state"] == "interrupted" and capture["n_samples"] == 547, capture
        recording = second.get(f"/sessions/{sid}/recordings").json()[0]
        assert recording["summary"]["n_samples"] == 547


def test_files_no_artifact_names_are_removed_on_the_next_start(tmp_path, scene_files):
    settings = make_settings(tmp_path)
    with TestClient(create_app(settings), headers=AUTH) as first:
        sid = first.post("/sessions", json={"name": "kept"}).json()["id"]
        kept = first.put(
            f"/sessions/{sid}/recording", files={"file": ("t.csv", scene_files["trace"])}
        ).json()["id"]
    arrays = tmp_path / "arrays"
    # What a worker that outlived its server, or a write cut short, would leave.
    (arrays / "rec_0rphan000000.npz").write_bytes(b"orphan")
    (arrays / "rec_0rphan000000.png").write_bytes(b"orphan")
    (arrays / f".{kept}.npz.tmp123.npz").write_bytes(b"torn")
    (tmp_path / "uploads" / "scn_0rphan000000").mkdir()
    with TestClient(create_app(settings), headers=AUTH) as second:
        left = sorted(p.name for p in arrays.iterdir())
        assert left == [f"{kept}.npz"], left
        assert sorted(p.name for p in (tmp_path / "uploads").iterdir()) == [kept]
        csv = second.get(f"/sessions/{sid}/recordings/{kept}/csv")
        assert csv.status_code == 200


DEEP = 50_000


@pytest.mark.parametrize(
    "body",
    [
        "[" * DEEP + "]" * DEEP,
        '{"name": ' + "[" * DEEP + "]" * DEEP + "}",
        '{"name": ' + "9" * 5000 + "}",
        '{"name": "' + "x" * 100_000 + '"}',
    ],
    ids=["deep-array", "deep-field", "huge-integer", "long-string"],
)
def test_hostile_json_bodies_are_client_errors(app_client, body):
    _services, client = app_client
    before = client.get("/sessions").json()
    response = client.post("/sessions", content=body, headers={"Content-Type": "application/json"})
    assert 400 <= response.status_code < 500, response.text
    assert set(response.json()) == {"code", "message", "detail"}
    assert client.get("/sessions").json() == before
    assert client.get("/health").json()["status"] == "ok"


@pytest.mark.parametrize(
    "options, words",
    [
        ('{"a": ' + "[" * DEEP + "]" * DEEP + "}", "longer than"),
        ("[" * 2000 + "]" * 2000, "nested too deeply"),
        ('{"depth_scale": ' + "9" * 4400 + "}", "longer than"),
        ('{"depth_scale": 1e999}', "depth_scale"),
        ("[1, 2]", "must be a JSON object"),
    ],
    ids=["deep", "deep-short", "huge-number-long", "huge-number", "not-object"],
)
def test_hostile_reader_options_are_refused_before_the_file_is_read(
    app_client, scene_files, options, words
):
    import sys

    _services, client = app_client
    sid = client.post("/sessions", json={"name": "options"}).json()["id"]
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(1000)  # what the server runs with; the test runner raises it
    try:
        response = client.put(
            f"/sessions/{sid}/scan",
            files={"file": ("s.ply", scene_files["scan"])},
            data={"options": options},
        )
    finally:
        sys.setrecursionlimit(limit)
    assert response.status_code == 422, response.text
    assert words in response.json()["message"], response.json()
    assert client.get(f"/sessions/{sid}/scans").json() == []


def test_confirm_is_only_the_json_boolean(app_client):
    _services, client = app_client
    sid = client.post("/sessions", json={"name": "confirm"}).json()["id"]
    for value in ("yes", 1, "true", None):
        body = json.dumps({"trajectory_id": "trj_x", "mode": "servoj", "confirm": value})
        response = client.post(
            f"/sessions/{sid}/executions",
            content=body,
            headers={"Content-Type": "application/json"},
        )
        assert response.status_code == 422, (value, response.text)


def test_a_dry_run_stopped_while_it_runs_ends_cancelled_and_never_counts(app_client, tmp_path):
    """Stopping a running dry run answered 200, yet the dry run completed and counted as passed.
    Now its result is discarded: the job ends cancelled, nothing is recorded."""
    services, client = app_client
    sid = client.post("/sessions", json={"name": "dry"}).json()["id"]
    recorded = []
    pid_file = tmp_path / "pid"
    job = services.jobs.submit(
        sid,
        "execution",
        {"backend": "sim", "mode": "servoj", "execution_id": "exe_stopped00001"},
        Sleep(1.5, pid_file=str(pid_file)),
        lambda summary: recorded.append(summary) or {"execution_id": "exe_stopped00001"},
    )
    _until(pid_file.exists, what="the dry run starting")
    stopped = client.post("/executions/exe_stopped00001/stop")
    assert stopped.status_code == 200 and stopped.json()["already_ended"] is False
    row = _finished(client, job.id, what="the dry run ending")
    assert row["state"] == "cancelled" and row["error"]["code"] == "stopped", row
    assert recorded == []  # never recorded, so never a passed dry run


def test_cancelling_a_running_execution_stops_it_instead_of_saying_it_finished(
    app_client, tmp_path
):
    services, client = app_client
    sid = client.post("/sessions", json={"name": "cancel"}).json()["id"]
    pid_file = tmp_path / "pid"
    job = services.jobs.submit(
        sid,
        "execution",
        {"backend": "sim", "mode": "servoj", "execution_id": "exe_cancelled0001"},
        Sleep(1.5, pid_file=str(pid_file)),
        lambda summary: {"execution_id": "exe_cancelled0001"},
    )
    _until(pid_file.exists, what="the execution starting")
    answer = client.post(f"/jobs/{job.id}/cancel")
    assert answer.status_code == 200, answer.text
    row = _finished(client, job.id, what="the execution ending")
    assert row["state"] == "cancelled"
