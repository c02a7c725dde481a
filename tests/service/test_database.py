"""The database: Alembic migrations on SQLite and a real PostgreSQL server, and several service
instances on one PostgreSQL database and one data folder.

The PostgreSQL server is Debian's, started here in a temporary folder on a unix socket
(:mod:`tests.postgres`). Two ``teachpath serve`` processes share it and a data folder: jobs run
once each, a restart of one never fails the other's running jobs, concurrent calibration updates
and uploads to one session from both lose nothing.
"""

from __future__ import annotations

import concurrent.futures
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext

from drivers.scanning.pointcloud import write_scan
from drivers.tracking.canonical_csv import write_trace_csv
from recon import scenes
from service.store import Base, Store, database_url, schema_revision
from tests.postgres import PostgresServer

pytestmark = pytest.mark.timeout(600)

HEAD = "0003"


@pytest.fixture(scope="module")
def postgres():
    server = PostgresServer()
    yield server
    server.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def url_of(request, tmp_path, postgres):
    """A function: a data folder -> the URL of a fresh database for it (SQLite inside it, or a
    new database on the PostgreSQL server)."""

    def make(data: Path) -> str:
        if request.param == "sqlite":
            data.mkdir(parents=True, exist_ok=True)
            return f"sqlite:///{data / 'teachpath.db'}"
        return postgres.new_database()

    make.dialect = request.param
    return make


def test_a_new_database_is_at_the_newest_migration_and_matches_the_models(url_of, tmp_path):
    store = Store(tmp_path / "d", url_of(tmp_path / "d"))
    assert schema_revision(store.engine) == HEAD
    with store.engine.connect() as connection:
        differences = compare_metadata(MigrationContext.configure(connection), Base.metadata)
    assert differences == []


def _release_schema(engine, *, drop_columns=()) -> None:
    """The tables as the release before Alembic made them (its create_all; optionally an older
    release's, lacking nullable columns added since), with a session, an artifact and a job."""
    from importlib import import_module

    baseline = import_module("service.migrations.versions.0001_baseline")
    tables = baseline._tables()
    for table in tables:
        for name in drop_columns:
            if name in table.c:
                table._columns.remove(table.c[name])
    tables[0].metadata.create_all(engine)
    when = "2026-01-02 03:04:05+00:00"
    with engine.begin() as connection:
        connection.execute(
            sa.text("INSERT INTO sessions (id, name, created_at) VALUES (:i, 'old', :w)"),
            {"i": "ses_0123456789ab", "w": when},
        )
        connection.execute(
            sa.text(
                "INSERT INTO artifacts (id, session_id, kind, created_at, inputs, params, summary,"
                " path, sha256, size) VALUES ('rec_0123456789ab', 'ses_0123456789ab', "
                "'recording', :w, '{}', '{\"format\": \"csv\"}', '{}', 'arrays/x.npz', :s, 10)"
            ),
            {"w": when, "s": "0" * 64},
        )
        connection.execute(
            sa.text(
                "INSERT INTO jobs (id, session_id, kind, state, progress, created_at, params) "
                "VALUES ('job_0123456789ab', 'ses_0123456789ab', 'reconstruction', 'running', "
                "0.5, :w, '{}')"
            ),
            {"w": when},
        )


@pytest.mark.parametrize("older", [False, True], ids=["current release", "older release"])
def test_a_database_of_an_earlier_release_is_upgraded_and_keeps_its_rows(url_of, tmp_path, older):
    data = tmp_path / "d"
    url = url_of(data)
    engine = sa.create_engine(database_url(url))
    dropped = ("calibration_report", "tip_offset_m", "source_name") if older else ()
    _release_schema(engine, drop_columns=dropped)
    assert schema_revision(engine) is None
    engine.dispose()
    store = Store(data, url)
    assert schema_revision(store.engine) == HEAD
    (session,) = store.sessions()
    assert session.id == "ses_0123456789ab" and session.calibration_report is None
    (artifact,) = store.artifacts(session.id)
    assert artifact.params == {"format": "csv"}
    # The job the old release left running has no owner: failed on start, said why.
    assert store.fail_interrupted_jobs() == 1
    job = store.job("job_0123456789ab")
    assert job.state == "failed" and job.error["code"] == "interrupted"
    # What the upgrade added works: owners, instances, sizes past 2**31.
    store.update_job(job.id, owner="elsewhere")
    store.heartbeat()
    assert store.instance_id in store.live_instances()
    with store.db.begin() as db:
        db.get(type(artifact), artifact.id).size = 5 * 2**30
    assert store.artifact(artifact.id).size == 5 * 2**30
    with store.engine.connect() as connection:
        assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
    # Opening it again changes nothing.
    assert schema_revision(Store(data, url).engine) == HEAD


def test_instances_starting_together_migrate_once(url_of, tmp_path):
    data = tmp_path / "d"
    url = url_of(data)
    with concurrent.futures.ThreadPoolExecutor(4) as pool:
        stores = list(pool.map(lambda _: Store(data, url), range(4)))
    assert {schema_revision(s.engine) for s in stores} == {HEAD}


def test_a_crashed_instance_on_this_host_is_known_at_once(postgres, tmp_path):
    """Its heartbeat is fresh, but its process is gone: its jobs are failed on the next start,
    while a live instance's are not."""
    url = postgres.new_database()
    alive = Store(tmp_path / "d", url)
    alive.heartbeat()
    session = alive.create_session("s")
    kept = alive.create_job(session.id, "reconstruction", {})
    alive.update_job(kept.id, state="running")
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    crashed = Store(tmp_path / "d", url, instance_id=f"crashed:{gone.stdout.strip()}")
    crashed.heartbeat()
    with crashed.db.begin() as db:
        from service.store import InstanceRow

        db.get(InstanceRow, crashed.instance_id).pid = int(gone.stdout)
    lost = crashed.create_job(session.id, "plan", {})
    starting = Store(tmp_path / "d", url)
    starting.heartbeat()
    assert starting.fail_interrupted_jobs() == 1
    assert starting.job(lost.id).state == "failed"
    assert starting.job(kept.id).state == "running"


def test_calibration_reports_written_at_once_by_two_stores_keep_every_entry(postgres, tmp_path):
    """Fifty report entries written concurrently through two stores (two instances' worth of
    connections) on one session: each read-merge-write holds the row, none is lost. (Without
    the row lock, PostgreSQL's read committed loses most of them: measured 9 of 50 kept.)"""
    url = postgres.new_database()
    stores = [Store(tmp_path / "d", url) for _ in range(2)]
    sid = stores[0].create_session("s").id

    def record(i: int) -> None:
        stores[i % 2].record_calibration(sid, f"entry{i}", {"i": i}, tip_offset_m=[0, 0, i])

    with concurrent.futures.ThreadPoolExecutor(10) as pool:
        list(pool.map(record, range(50)))
    session = stores[1].session(sid)
    assert set(session.calibration_report) == {f"entry{i}" for i in range(50)}


# -- two service processes on one PostgreSQL database --------------------------------------------

TOKEN = "two-instances-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class Served:
    """A ``teachpath serve`` process on 127.0.0.1 with a port of its own."""

    def __init__(self, data: Path, url: str, log: Path) -> None:
        env = {
            **os.environ,
            "TEACHPATH_DATABASE_URL": url,
            "TEACHPATH_TOKEN": TOKEN,
            "TEACHPATH_CPU_WORKERS": "1",
        }
        self.log = log.open("w")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve", "--host", "127.0.0.1", "--port", "0",
             "--data-dir", str(data)],
            stdout=subprocess.PIPE, stderr=self.log, text=True, env=env,
        )  # fmt: skip
        self.base = None
        deadline = time.monotonic() + 60
        while self.base is None:
            line = self.process.stdout.readline()
            assert line or self.process.poll() is None, log.read_text()
            assert time.monotonic() < deadline, "the server did not start"
            if line.startswith("open http://"):
                self.base = line.split()[1].split("/?")[0]
        self.client = httpx.Client(base_url=self.base, headers=AUTH, timeout=60)
        # The URL is printed once the port is bound; requests are served after start-up (the
        # migrations, the recovery).
        while True:
            try:
                if self.client.get("/health").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert self.process.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.1)

    def kill(self) -> None:
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(30)
        self.client.close()

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
        self.client.close()
        self.log.close()


def _wait(client: httpx.Client, job: dict, timeout_s: float = 180) -> dict:
    deadline = time.monotonic() + timeout_s
    while job["state"] not in ("succeeded", "failed", "cancelled"):
        assert time.monotonic() < deadline, f"job {job['id']} did not finish"
        time.sleep(0.2)
        job = client.get(f"/jobs/{job['id']}").json()
    return job


@pytest.fixture(scope="module")
def scene_bytes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    small, large = scenes.box_corner(0), scenes.long_edge(4000, 400_000)
    out = {}
    for name, scene in (("small", small), ("large", large)):
        write_trace_csv(folder / f"{name}.csv", scene.recording)
        write_scan(folder / f"{name}.ply", scene.scan)
        out[name] = ((folder / f"{name}.csv").read_bytes(), (folder / f"{name}.ply").read_bytes())
    return out


@pytest.fixture
def two(postgres, tmp_path):
    data, url = tmp_path / "shared", postgres.new_database()
    servers = [Served(data, url, tmp_path / f"server{i}.log") for i in range(2)]
    yield servers, data, url
    for server in servers:
        server.stop()


def _session(client: httpx.Client, files: tuple[bytes, bytes], name: str = "s") -> str:
    sid = client.post("/sessions", json={"name": name}).json()["id"]
    assert client.put(f"/sessions/{sid}/recording", files={"file": ("t.csv", files[0])}).is_success
    assert client.put(f"/sessions/{sid}/scan", files={"file": ("s.ply", files[1])}).is_success
    return sid


def test_jobs_submitted_to_two_instances_each_run_exactly_once(two, scene_bytes):
    (a, b), _, _ = two
    sid = _session(a.client, scene_bytes["small"])
    assert b.client.get(f"/sessions/{sid}").json()["id"] == sid  # one database
    jobs = [
        server.client.post(f"/sessions/{sid}/reconstructions", json={}).json()
        for server in (a, b, a, b)
    ]
    done = [_wait(a.client, job) for job in jobs]
    assert [job["state"] for job in done] == ["succeeded"] * 4
    made = [job["result"]["reconstruction_id"] for job in done]
    artifacts = a.client.get(f"/sessions/{sid}/reconstructions").json()
    assert sorted(r["id"] for r in artifacts) == sorted(made)  # one artifact per job, no more
    # Each instance ran its own; both see every result, and its CSV.
    for rid in made:
        for server in (a, b):
            csv = server.client.get(f"/sessions/{sid}/reconstructions/{rid}/csv")
            assert csv.status_code == 200 and csv.text.count("\n") > 100


def test_restarting_one_instance_never_fails_the_others_running_job(two, scene_bytes, tmp_path):
    (a, b), data, url = two
    sid = _session(a.client, scene_bytes["large"], "large")
    job = a.client.post(f"/sessions/{sid}/reconstructions", json={}).json()
    deadline = time.monotonic() + 60
    while a.client.get(f"/jobs/{job['id']}").json()["state"] == "queued":
        assert time.monotonic() < deadline
        time.sleep(0.05)
    # B crashes and comes back while A's job runs: its start-up recovery must leave A's job be.
    b.kill()
    restarted = Served(data, url, tmp_path / "restarted.log")
    try:
        assert a.client.get(f"/jobs/{job['id']}").json()["state"] == "running"
        assert _wait(restarted.client, job)["state"] == "succeeded"
    finally:
        restarted.stop()


def test_a_crashed_instances_job_is_failed_by_the_one_still_running(two, scene_bytes):
    (a, b), _, _ = two
    sid = _session(a.client, scene_bytes["large"], "large")
    job = b.client.post(f"/sessions/{sid}/reconstructions", json={}).json()
    b.kill()
    # A's heartbeat finds B gone (its process, on this host) and fails B's job: a client
    # waiting on it is told, rather than waiting forever.
    failed = _wait(a.client, job, timeout_s=60)
    assert failed["state"] == "failed" and failed["error"]["code"] == "interrupted"


def test_concurrent_calibration_updates_from_two_instances_lose_nothing(two, tmp_path):
    """Point-pair and pivot calibrations land at once on both instances: each writes its entry
    into the session's calibration report (read, merged, written): with the row locked, both
    entries survive every round, and the fields hold a value one of the requests wrote."""
    from drivers.tracking.canonical_csv import write_trace_csv
    from recon.inputs import Recording
    from tests.recon.test_calibrate import pivot_recording

    (a, b), _, _ = two
    position, quat = pivot_recording(0)
    pivot_file = tmp_path / "pivot.csv"
    write_trace_csv(
        pivot_file,
        Recording(points_m=position, t_s=np.arange(len(position)) / 240.0, orientations_xyzw=quat),
    )
    pivot = pivot_file.read_bytes()
    base = np.array([[0.4, 0.1, 0.0], [0.5, 0.1, 0.0], [0.4, 0.3, 0.0], [0.45, 0.2, 0.1]])
    pairs = [{"base": (p + [0.3, 0, 0]).tolist(), "tracker": p.tolist()} for p in base]

    def calibrate(job: tuple[str, int]):
        sid, i = job
        if i % 2 == 0:
            return a.client.post(f"/sessions/{sid}/calibration/base", json={"pairs": pairs})
        return b.client.post(
            f"/sessions/{sid}/calibration/pivot", files={"file": ("pivot.csv", pivot)}
        )

    sessions = [a.client.post("/sessions", json={"name": f"cal{k}"}).json()["id"] for k in range(6)]
    with concurrent.futures.ThreadPoolExecutor(8) as pool:
        responses = list(pool.map(calibrate, [(sid, i) for sid in sessions for i in range(4)]))
    assert all(r.status_code == 200 for r in responses), [r.text for r in responses][:3]
    for sid in sessions:
        session = b.client.get(f"/sessions/{sid}").json()
        assert set(session["calibration_report"]) == {"base", "pivot"}
        assert session["T_base_tracker"] is not None and session["tip_offset_m"] is not None


def test_uploads_to_one_session_from_two_instances_are_serialised(two, scene_bytes):
    (a, b), _, _ = two
    sid = a.client.post("/sessions", json={"name": "up"}).json()["id"]
    trace = scene_bytes["small"][0]

    def upload(i: int) -> str:
        server = (a, b)[i % 2]
        response = server.client.put(
            f"/sessions/{sid}/recording", files={"file": (f"t{i}.csv", trace)}
        )
        assert response.status_code in (200, 201), response.text
        return response.json()["id"]

    with concurrent.futures.ThreadPoolExecutor(6) as pool:
        ids = list(pool.map(upload, range(12)))
    recordings = a.client.get(f"/sessions/{sid}/recordings").json()
    assert sorted(r["id"] for r in recordings) == sorted(ids)  # every upload kept
    newest = max(recordings, key=lambda r: r["created_at"])
    assert b.client.get(f"/sessions/{sid}").json()["recording_id"] == newest["id"]


def test_a_stop_sent_to_the_instance_that_does_not_drive_the_arm_is_refused(two):
    """An execution runs on the instance that drives the arm; another cannot stop it and says
    so (409), rather than answering as if the arm had stopped."""
    (a, _), data, url = two
    sid = a.client.post("/sessions", json={"name": "arm"}).json()["id"]
    driver = Store(data, url, instance_id="the-arms-instance")
    driver.heartbeat()
    job = driver.create_job(sid, "execution", {"execution_id": "exe_0123456789ab"})
    driver.update_job(job.id, state="running")
    refused = a.client.post("/executions/exe_0123456789ab/stop")
    assert refused.status_code == 409, refused.text
    assert refused.json()["code"] == "other_instance"
    assert "the-arms-instance" in refused.json()["message"]
    assert driver.job(job.id).state == "running"  # nothing was pretended


def test_an_update_of_a_row_that_is_gone_names_it(url_of, tmp_path):
    """An update of a session, job or capture deleted meanwhile is a lookup error naming the
    row (404 ``not_found`` from a route), never an AttributeError deep in the store."""
    from service.errors import classify
    from service.store import RowGoneError

    store = Store(tmp_path / "data", url_of(tmp_path / "data"))
    try:
        for update, table in (
            (lambda: store.update_session("ses_gone", name="x"), "sessions"),
            (lambda: store.record_calibration("ses_gone", "pivot", {}), "sessions"),
            (lambda: store.update_job("job_gone", state="failed"), "jobs"),
            (lambda: store.update_capture("cap_gone", n_samples=1), "captures"),
        ):
            with pytest.raises(RowGoneError, match=rf"{table} '\w+_gone' no longer exists") as gone:
                update()
            assert classify(gone.value) == (404, "not_found")
        assert store.count_jobs("running") == 0
    finally:
        store.engine.dispose()
