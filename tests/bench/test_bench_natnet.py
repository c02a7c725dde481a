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
from recon.reconstruct import reconstruct
from recon.types import Recording

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
