"""Archived sessions: replay throughput on 1 and 2 Dask workers, and bundle export and import
of a session with a 1M-point scan, timed as a user times them (the whole command).

The 100 demo-sized sessions are 10 distinct ones made through the service (the box-corner and
cylinder scenes, seeds 0-4, uploaded, reconstructed and planned) each archived 10 times: replay
does the full work for every bundle, whatever its id.
"""

from __future__ import annotations

import shutil
import statistics

import pytest
from fastapi.testclient import TestClient

from drivers.scanning.pointcloud import write_scan
from drivers.tracking.canonical_csv import write_trace_csv
from recon import scenes
from service.app import create_app
from service.settings import Settings
from tests.bench.test_bench_speed import TEACHPATH, timed_runs
from tests.service.conftest import AUTH, T_BASE_TRACKER, TOKEN, wait

pytestmark = [pytest.mark.bench, pytest.mark.timeout(3600)]

#: Archived sessions replayed.
N_SESSIONS = 100
DISTINCT = 10
#: Runs of each worker count, alternating (the machine's speed drifts by a third over minutes).
REPLAY_RUNS = 3


def _settings(data) -> Settings:
    return Settings(data_dir=data, token=TOKEN, max_upload_mb=200, max_uploads_in_flight_mb=400)


def _session(client, folder, scene, name) -> str:
    trace, scan = folder / f"{name}.csv", folder / f"{name}.ply"
    write_trace_csv(trace, scene.recording)
    write_scan(scan, scene.scan)
    sid = client.post("/sessions", json={"name": name}).json()["id"]
    client.put(f"/sessions/{sid}/recording", files={"file": (trace.name, trace.read_bytes())})
    client.put(f"/sessions/{sid}/scan", files={"file": (scan.name, scan.read_bytes())})
    client.put(f"/sessions/{sid}/calibration", json={"T_base_tracker": T_BASE_TRACKER})
    job = wait(client, client.post(f"/sessions/{sid}/reconstructions", json={}).json(), 600)
    assert job["state"] == "succeeded", job
    return sid


def test_replay_of_archived_sessions_on_one_and_two_workers(tmp_path):
    data, files, archive = tmp_path / "data", tmp_path / "files", tmp_path / "archive"
    files.mkdir()
    archive.mkdir()
    made = []
    with TestClient(create_app(_settings(data)), headers=AUTH) as client:
        for seed in range(DISTINCT // 2):
            for maker in (scenes.box_corner, scenes.cylinder_edge):
                name = f"{maker.__name__}_{seed}"
                made.append((name, _session(client, files, maker(seed), name)))
        for name, sid in made:
            (files / f"{name}.zip").write_bytes(client.get(f"/sessions/{sid}/bundle").content)
    for copy in range(N_SESSIONS // DISTINCT):
        for name, _ in made:
            shutil.copy(files / f"{name}.zip", archive / f"{name}_{copy}.zip")
    print(
        f"\n## Replay of {N_SESSIONS} archived sessions (demo-sized: 10 distinct, box corner "
        f"and cylinder, reconstruction only), whole command, {REPLAY_RUNS} runs each, 1 and 2 "
        "workers alternating\n"
    )
    print("| workers | median s | min | max | sessions/s | speed-up |")
    print("|---:|---:|---:|---:|---:|---:|")
    seconds: dict[int, list[float]] = {1: [], 2: []}
    for _ in range(REPLAY_RUNS):
        for workers in (1, 2):
            argv = [TEACHPATH, "replay", str(archive), "--workers", str(workers)]
            argv += ["--report", str(tmp_path / f"report_{workers}.csv")]
            seconds[workers] += timed_runs(argv, 1)[0]
    medians = {workers: statistics.median(runs) for workers, runs in seconds.items()}
    for workers, runs in seconds.items():
        print(
            f"| {workers} | {medians[workers]:.1f} | {min(runs):.1f} | {max(runs):.1f} | "
            f"{N_SESSIONS / medians[workers]:.2f} | {medians[1] / medians[workers]:.2f}x |"
        )


def test_bundle_export_and_import_of_a_million_point_scan(tmp_path):
    scene = scenes.long_edge(10_000, 1_000_000)
    trace, scan = tmp_path / "trace.csv", tmp_path / "scan.ply"
    write_trace_csv(trace, scene.recording)
    write_scan(scan, scene.scan)
    data = tmp_path / "data"
    with TestClient(create_app(_settings(data)), headers=AUTH) as client:
        sid = client.post("/sessions", json={"name": "1M"}).json()["id"]
        client.put(f"/sessions/{sid}/recording", files={"file": ("t.csv", trace.read_bytes())})
        put = client.put(f"/sessions/{sid}/scan", files={"file": ("s.ply", scan.read_bytes())})
        assert put.status_code in (200, 201), put.text
        job = wait(client, client.post(f"/sessions/{sid}/reconstructions", json={}).json(), 600)
        assert job["state"] == "succeeded", job
    bundle = tmp_path / "s.zip"
    export = [TEACHPATH, "bundle", "export", sid, "--data-dir", str(data), "--out", str(bundle)]
    export_s, export_peak = timed_runs(export, 5)
    import_s, import_peak = [], []
    for run in range(5):
        target = tmp_path / f"import_{run}"
        seconds, peak = timed_runs(
            [TEACHPATH, "bundle", "import", str(bundle), "--data-dir", str(target)], 1
        )
        import_s += seconds
        import_peak += peak
    size_mb = bundle.stat().st_size / 1e6
    print(
        f"\n## Bundle of a session with a 1M-point scan ({size_mb:.0f} MB zip: the upload, the "
        "arrays, the reconstruction with its scan model), whole command, 5 runs\n"
    )
    print("| command | median s | min | max | peak MiB |")
    print("|---|---:|---:|---:|---:|")
    for label, seconds, peak in (
        ("`teachpath bundle export`", export_s, export_peak),
        ("`teachpath bundle import` (into an empty data folder)", import_s, import_peak),
    ):
        print(
            f"| {label} | {statistics.median(seconds):.2f} | {min(seconds):.2f} | "
            f"{max(seconds):.2f} | {max(peak):.0f} |"
        )
