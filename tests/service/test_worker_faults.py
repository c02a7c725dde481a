"""A worker process that dies (kill -9, the OOM killer) and a server that dies under its
workers: the pool is replaced, the job it held fails with a clear error, queued work goes on,
and no worker outlives its server."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import psutil
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.jobs import JobManager
from service.store import Store
from tests.service.conftest import AUTH, make_settings
from tests.service.job_targets import Pid, Sleep


def _until(predicate, timeout_s: float = 30.0, what: str = "the condition"):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"{what} did not happen within {timeout_s} s")


def _started(pid_file: Path) -> psutil.Process:
    """The worker process running a :class:`Sleep` that writes ``pid_file``."""
    text = _until(lambda: pid_file.exists() and pid_file.read_text(), what="the task starting")
    return psutil.Process(int(text))


@pytest.fixture
def manager(tmp_path):
    store = Store(tmp_path, f"sqlite:///{tmp_path / 'db.sqlite'}")
    session = store.create_session("faults")
    jobs = JobManager(store, workers=1)
    yield store, jobs, session.id
    jobs.shutdown()


def _submit(store, jobs, session_id, task, results):
    return jobs.submit(session_id, "test", {}, task, lambda value: results.append(value) or value)


def test_a_killed_worker_fails_its_job_and_the_queued_jobs_run_on_a_new_pool(manager, tmp_path):
    store, jobs, session_id = manager
    results = []
    pid_file = tmp_path / "pid"
    running = _submit(store, jobs, session_id, Sleep(30.0, pid_file=str(pid_file)), results)
    queued = _submit(store, jobs, session_id, Pid(), results)
    assert store.job(running.id).state == "running" and store.job(queued.id).state == "queued"
    worker = _started(pid_file)
    worker.send_signal(signal.SIGKILL)
    failed = _until(
        lambda: (row := store.job(running.id)).state in ("failed", "succeeded") and row,
        what="the running job ending",
    )
    assert failed.state == "failed" and failed.error["code"] == "worker_died", failed.error
    assert "died" in failed.error["message"] and "run the job again" in failed.error["message"]
    # The job that had not started runs on the new pool, in a new process.
    done = _until(
        lambda: (row := store.job(queued.id)).state in ("failed", "succeeded") and row,
        what="the queued job ending",
    )
    assert done.state == "succeeded", done.error
    assert done.result["pid"] != worker.pid
    _until(lambda: not jobs.degraded, what="the new pool answering")
    # And new work is taken as before.
    later = _submit(store, jobs, session_id, Pid(), results)
    assert _until(lambda: store.job(later.id).state == "succeeded", what="a later job")
    assert [job.state for job in store.jobs()].count("queued") == 0


def _parse_child(timeout_s: float = 60.0) -> psutil.Process:
    """The child process this (test) process parses an upload in (see drivers.isolation)."""

    def find():
        for child in psutil.Process().children(recursive=True):
            try:
                if "drivers.isolation" in " ".join(child.cmdline()):
                    return child
            except psutil.NoSuchProcess:
                continue
        return None

    return _until(find, timeout_s, what="the parse child starting")


def test_an_upload_whose_parse_child_is_killed_is_refused_and_the_next_upload_works(
    tmp_path, scene_files
):
    from concurrent.futures import ThreadPoolExecutor

    app = create_app(make_settings(tmp_path))
    with TestClient(app, headers=AUTH) as client, ThreadPoolExecutor(1) as pool:
        sid = client.post("/sessions", json={"name": "killed parse"}).json()["id"]
        upload = pool.submit(
            client.put,
            f"/sessions/{sid}/recording",
            files={"file": ("trace.csv", scene_files["trace"])},
        )
        child = _parse_child()
        # Below the server, as the pool's workers are: requests (a Stop) come first.
        assert _until(lambda: child.nice() >= 10, 10.0, what="the parse child niced")
        child.send_signal(signal.SIGKILL)  # what the out-of-memory killer does
        refused = upload.result(timeout=60)
        assert refused.status_code == 422, refused.text
        body = refused.json()
        assert body["code"] == "invalid_file"
        assert "crashed (SIGKILL" in body["message"] and "out-of-memory" in body["message"]
        assert client.get(f"/sessions/{sid}/recordings").json() == []
        assert app.state.services.store.remove_unnamed_files() == []  # no file left behind
        stored = client.put(
            f"/sessions/{sid}/recording", files={"file": ("trace.csv", scene_files["trace"])}
        )
        assert stored.status_code == 201, stored.text
        assert client.get("/health").json()["status"] == "ok"  # the job pool was never touched


def test_an_upload_is_parsed_while_the_job_pool_is_busy(tmp_path, scene_files):
    app = create_app(make_settings(tmp_path))
    with TestClient(app, headers=AUTH) as client:
        jobs = app.state.services.jobs
        sid = client.post("/sessions", json={"name": "busy pool"}).json()["id"]
        pid_file = tmp_path / "pid"
        busy = [jobs.submit(sid, "test", {}, Sleep(60.0, pid_file=str(pid_file)), lambda v: v)]
        busy += [jobs.submit(sid, "test", {}, Sleep(60.0), lambda v: v) for _ in range(3)]
        _started(pid_file)
        stored = client.put(
            f"/sessions/{sid}/recording", files={"file": ("trace.csv", scene_files["trace"])}
        )
        assert stored.status_code == 201, stored.text
        # Answered while the pool's one worker still sleeps and three jobs wait behind it.
        states = [client.get(f"/jobs/{job.id}").json()["state"] for job in busy]
        assert states == ["running", "queued", "queued", "queued"]
        for job in busy[1:]:
            client.post(f"/jobs/{job.id}/cancel")
        _started(pid_file).kill()  # the sleeping one: it would outlive the test by a minute


def test_health_says_degraded_until_a_new_worker_answers(tmp_path, monkeypatch):
    app = create_app(make_settings(tmp_path))
    with TestClient(app, headers=AUTH) as client:
        jobs = app.state.services.jobs
        assert client.get("/health").json()["status"] == "ok"
        # Hold the new pool's first answer back, so the degraded state can be seen.
        release = []
        original = JobManager._new_pool

        def slow_pool(self):
            pool = original(self)
            real_submit = pool.submit

            def submit(fn, *args):
                if fn.__name__ == "_ready" and not release:
                    release.append(True)
                    return real_submit(_sleep_then_ready)
                return real_submit(fn, *args)

            pool.submit = submit
            return pool

        monkeypatch.setattr(JobManager, "_new_pool", slow_pool)
        sid = client.post("/sessions", json={"name": "h"}).json()["id"]
        pid_file = tmp_path / "pid"
        job = jobs.submit(sid, "test", {}, Sleep(30.0, pid_file=str(pid_file)), lambda v: v)
        _started(pid_file).send_signal(signal.SIGKILL)
        _until(lambda: client.get("/health").json()["status"] == "degraded", what="degraded")
        assert client.get(f"/jobs/{job.id}").json()["error"]["code"] == "worker_died"
        _until(lambda: client.get("/health").json()["status"] == "ok", what="ok again")


def _sleep_then_ready():
    time.sleep(1.0)
    return os.getpid()


SERVER = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {root!r})
    from service.jobs import JobManager
    from service.store import Store
    from tests.service.job_targets import Sleep

    if __name__ == "__main__":
        store = Store({data!r}, "sqlite:///{data}/db.sqlite")
        session = store.create_session("orphans")
        jobs = JobManager(store, workers=1)
        task = Sleep(4.0, marker={marker!r}, pid_file={pid_file!r})
        jobs.submit(session.id, "test", {{}}, task, lambda v: v)
        print("submitted", flush=True)
        time.sleep(60)
    """
)


def test_workers_end_with_a_killed_server_and_write_nothing(tmp_path):
    marker = tmp_path / "written-by-an-orphan"
    script = tmp_path / "server.py"
    root = str(Path(__file__).resolve().parents[2])
    pid_file = tmp_path / "pid"
    script.write_text(
        SERVER.format(root=root, data=str(tmp_path), marker=str(marker), pid_file=str(pid_file))
    )
    server = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        assert server.stdout.readline().strip() == "submitted"
        worker = _started(pid_file)
        others = [p for p in psutil.Process(server.pid).children() if p.pid != worker.pid]
        server.send_signal(signal.SIGKILL)  # what an OOM kill of the server does
        server.wait(timeout=10)
        started = time.monotonic()
        worker.wait(timeout=5)
        print(f"worker ended {time.monotonic() - started:.2f} s after the server")
        for process in others:  # the resource tracker ends when its last user is gone
            process.wait(timeout=10)
        time.sleep(4.5)  # past the moment the task would have written its file
        assert not marker.exists()
    finally:
        if server.poll() is None:
            server.kill()
