"""Live NatNet feed under load: no frame lost while the process reconstructs (``make bench``).

Our replay server streams 60 s at 360 Hz on loopback; NatNetSource receives it (its client runs
in a child process) and a thread of this process takes the batches, as the service's capture
runner does, while the main thread reconstructs a large scene over and over. A ticker thread
measures how long the process's threads were held up (by the GIL) meanwhile.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from drivers.tracking.natnet_server import NatNetReplayServer
from drivers.tracking.natnet_source import NatNetConfig, NatNetSource
from recon import scenes
from recon.inputs import Recording
from recon.reconstruct import reconstruct

pytestmark = pytest.mark.bench

RATE_HZ = 360.0
SECONDS = 60.0


def _recording() -> Recording:
    n = int(SECONDS * RATE_HZ)
    t = np.arange(n) / RATE_HZ
    angle = 2 * np.pi * t / 4.0
    points = np.column_stack([0.4 + 0.1 * np.cos(angle), 0.1 * np.sin(angle), np.full(n, 0.05)])
    return Recording(points_m=points, t_s=100.0 + t)


def test_no_frame_lost_while_reconstructing():
    scene = scenes.long_edge(10_000, 1_000_000)
    rec = _recording()
    n = len(rec)
    counts = {"received": 0}
    done = threading.Event()
    errors: list[Exception] = []
    ticks: list[float] = []

    def consume(source: NatNetSource) -> None:
        try:
            for batch in source.batches():
                counts["received"] += len(batch)
                if source.stats.last_frame >= n:
                    break
        except Exception as exc:  # reported below with the table
            errors.append(exc)
        finally:
            done.set()

    def tick() -> None:
        while not done.is_set():
            time.sleep(0.005)
            ticks.append(time.monotonic())

    with NatNetReplayServer(rec, command_port=0) as server:
        source = NatNetSource(
            NatNetConfig(rigid_body="Pen", command_port=server.command_port, stall_timeout_s=10.0)
        )
        source.connect()
        consumer = threading.Thread(target=consume, args=(source,), daemon=True)
        ticker = threading.Thread(target=tick, daemon=True)
        consumer.start()
        ticker.start()
        runs, busy_s = 0, 0.0
        while not server.wait_done(timeout_s=0):
            start = time.perf_counter()
            reconstruct(scene.recording, scene.scan)
            busy_s += time.perf_counter() - start
            runs += 1
        done.wait(30.0)
        source.close()
        consumer.join()
        ticker.join()
        sent = server.stop()
    stats = source.stats
    stall_s = float(np.diff(ticks).max()) if len(ticks) > 1 else float("nan")
    print(f"\n## NatNet feed under load ({SECONDS:.0f} s at {RATE_HZ:.0f} Hz, loopback unicast)\n")
    print(
        "| receiver | parent work | frames sent | received | dropped | out of order | "
        "longest stall of a parent thread (s) | server's worst lateness (ms) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    print(
        f"| NatNetSource (child process) | {runs} reconstructions of {scene.name} "
        f"({busy_s / max(runs, 1):.1f} s each) | {sent.frames_sent:,} | "
        f"{stats.frames_received:,} | {stats.frames_dropped} | {stats.frames_out_of_order} | "
        f"{stall_s:.2f} | {sent.max_late_s * 1e3:.1f} |"
    )
    print("\nTarget: no frame lost (received = sent, nothing dropped).")
    assert not errors, errors
    assert stats.frames_received == counts["received"] == sent.frames_sent == n
    assert stats.frames_dropped == 0


def test_no_frame_lost_by_a_service_capture_while_it_reconstructs(tmp_path):
    """The same 60 s stream captured by the real server (REST), which meanwhile runs large
    reconstruction jobs one after another: every frame sent must be in the stored recording."""
    import tempfile
    from pathlib import Path

    from drivers.scanning.pointcloud import write_scan
    from drivers.tracking.canonical_csv import write_trace_csv
    from tests.e2e.test_server_flow import TOKEN, Server

    scene = scenes.long_edge(10_000, 1_000_000)
    with tempfile.TemporaryDirectory() as tmp:
        write_trace_csv(Path(tmp) / "trace.csv", scene.recording)
        write_scan(Path(tmp) / "scan.ply", scene.scan)
        trace, scan = (Path(tmp) / "trace.csv").read_bytes(), (Path(tmp) / "scan.ply").read_bytes()
    rec = _recording()
    server = Server(tmp_path / "data", token=TOKEN)
    jobs = []
    try:
        client = server.client
        sid = client.post("/sessions", json={"name": "bench"}).json()["id"]
        client.put(f"/sessions/{sid}/recording", files={"file": ("trace.csv", trace)})
        client.put(f"/sessions/{sid}/scan", files={"file": ("scan.ply", scan)})
        recording_id = client.get(f"/sessions/{sid}").json()["recording_id"]
        with NatNetReplayServer(rec, rigid_body="Pen", command_port=0) as natnet:
            capture = client.post(
                f"/sessions/{sid}/captures",
                json={
                    "source": {
                        "kind": "natnet",
                        "server": "127.0.0.1",
                        "rigid_body": "Pen",
                        "command_port": natnet.command_port,
                    }
                },
            ).json()
            deadline = time.monotonic() + SECONDS + 60
            while natnet.frames_sent < len(rec) and time.monotonic() < deadline:
                job = client.post(
                    f"/sessions/{sid}/reconstructions", json={"recording_id": recording_id}
                ).json()
                jobs.append(server.wait(job)["state"])
            time.sleep(1.0)  # the last batches reach the capture file
            stopped = client.post(f"/sessions/{sid}/captures/{capture['id']}/stop").json()
            stats = natnet.stop()
        stored = client.get(f"/sessions/{sid}/recordings/{stopped['recording_id']}").json()
    finally:
        server.stop()
    print(
        "\n## NatNet capture in the service while it reconstructs (60 s at 360 Hz; "
        "10k-point path against a 1M-point scan, jobs back to back)\n"
    )
    print("| frames sent | captured | in the recording | bridged | reconstructions (state) |")
    print("|---:|---:|---:|---:|---|")
    states = ", ".join(f"{jobs.count(s)} {s}" for s in sorted(set(jobs)))
    print(
        f"| {stats.frames_sent} | {stopped['n_samples']} | {stored['summary']['n_samples']} | "
        f"{stored['summary']['gaps']['n_bridged']} | {len(jobs)} ({states}) |"
    )
    print("\nTarget: none lost.")
    assert stopped["n_samples"] == stats.frames_sent == len(rec)
