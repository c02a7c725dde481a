"""Tracker file reading speed (``make bench``): a 300 s take at 360 Hz per format; prints only."""

from __future__ import annotations

import statistics
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.tracking.c3d import read_c3d
from drivers.tracking.canonical_csv import read_trace_csv, write_trace_csv
from drivers.tracking.motive_csv import read_motive_csv
from recon.inputs import Recording
from tests.drivers.tracking_fixtures import PEN_MARKERS_M, helix, write_c3d, write_motive_csv

pytestmark = pytest.mark.bench

DURATION_S = 300.0
RATE_HZ = 360.0


def _median(fn, repeats=5):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def test_read_time_of_a_long_take(tmp_path):
    n = int(DURATION_S * RATE_HZ)
    t, p, q = helix(n, RATE_HZ)
    lost = np.zeros(n, bool)
    lost[np.random.default_rng(0).choice(n, n // 100, replace=False)] = True  # 1 % occluded
    files = []
    motive = write_motive_csv(tmp_path / "take.csv", t, p, q, lost=lost)
    files.append(("Motive CSV, quaternion, 1 body + 4 markers", motive, read_motive_csv))
    euler = write_motive_csv(tmp_path / "euler.csv", t, p, q, lost=lost, rotation="XYZ")
    files.append(("Motive CSV, Euler XYZ, 1 body + 4 markers", euler, read_motive_csv))
    # The pen tip and the pen's four markers as C3D points.
    rot = Rotation.from_quat(q)
    points = np.stack([p] + [p + rot.apply(offset) for offset in PEN_MARKERS_M], axis=1)
    labels = ["tip"] + [f"Pen:Marker{k}" for k in range(1, 5)]
    c3d = write_c3d(
        tmp_path / "take.c3d", labels, points, RATE_HZ, lost=lost[:, None] & [1, 0, 0, 0, 0]
    )
    files.append(("C3D, 5 markers (read: tip)", c3d, lambda f: read_c3d(f, marker="tip")))
    small = write_c3d(tmp_path / "small.c3d", labels, points[:360], RATE_HZ)
    files.append(("C3D, 1 s (child process start-up)", small, lambda f: read_c3d(f, marker="tip")))
    canonical = tmp_path / "trace.csv"
    write_trace_csv(canonical, Recording(points_m=p, t_s=t, orientations_xyzw=q))
    files.append(("canonical trace CSV (reference)", canonical, read_trace_csv))

    print(f"\n## Reading a {DURATION_S:.0f} s take at {RATE_HZ:.0f} Hz (median of 5)\n")
    print("| file | frames | MB | read s | frames/s |")
    print("|---|---:|---:|---:|---:|")
    for label, path, reader in files:
        frames = len(reader(path))
        seconds = _median(lambda: reader(path))  # noqa: B023
        size = path.stat().st_size / 1e6
        print(f"| {label} | {frames:,} | {size:.1f} | {seconds:.3f} | {frames / seconds:,.0f} |")
    print("\nTarget: the Motive CSV take in well under 2 s.")
