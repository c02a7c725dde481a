"""Collision checking of whole motions: scan preprocessing and check time (``make bench``).

A UR5e plan at 500 Hz: transit from home, approach, a 350 mm S-curve on a scanned workpiece
(tool in contact), retract, return; 10,000 samples, and the same program ten times over for
100,000. The cell: the mounting plane, two keep-out boxes and a 1,000,000-point scan of the
workpiece and the table around it. Printed as tables (median, min and max of 5 runs); no time is
asserted (shared, noisy machines).
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.collision import Box, CapsuleTool, Cell, ContactZone, Phase, check_motion
from recon.kinematics import follow_path, model

pytestmark = pytest.mark.bench

REPEATS = 5
RATE_HZ = 500.0
N_SCAN = 1_000_000


def _timed(fn, repeats=REPEATS):
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), min(times), max(times), result


def _scan(rng: np.random.Generator) -> np.ndarray:
    """A box workpiece (top and sides) with a dome on top, and the table around it."""
    n_table, n_dome = N_SCAN // 5, N_SCAN // 10
    n_box = N_SCAN - n_table - n_dome
    lo, hi = np.array([0.30, -0.35, 0.0]), np.array([0.60, 0.05, 0.10])
    size = hi - lo
    areas = np.array(
        [size[0] * size[1], size[1] * size[2], size[1] * size[2]] + [size[0] * size[2]] * 2
    )
    face = rng.choice(5, n_box, p=areas / areas.sum())
    p = lo + rng.uniform(0, 1, (n_box, 3)) * size
    p[face == 0, 2] = hi[2]
    p[face == 1, 0] = lo[0]
    p[face == 2, 0] = hi[0]
    p[face == 3, 1] = lo[1]
    p[face == 4, 1] = hi[1]
    d = rng.normal(size=(n_dome, 3))
    d[:, 2] = np.abs(d[:, 2])
    dome = np.array([0.56, 0.0, hi[2]]) + 0.04 * d / np.linalg.norm(d, axis=1, keepdims=True)
    table = np.c_[rng.uniform(0.1, 0.8, (n_table, 2)) - [0.0, 0.45], np.zeros(n_table)]
    pts = np.vstack([p, dome, table])
    return pts + rng.normal(scale=0.0003, size=pts.shape)


def _cosine(a, b, n):
    s = 0.5 - 0.5 * np.cos(np.pi * np.linspace(0.0, 1.0, n))
    return a + s[:, None] * (b - a)


def _plan(arm):
    """One program: 10,000 samples at 500 Hz, with phases, and its process path."""
    top = 0.10
    u = np.linspace(0.0, 1.0, 3500)  # 7 s of process at about 50 mm/s
    process = np.c_[0.42 + 0.05 * np.sin(2 * np.pi * u), -0.30 + 0.30 * u, np.full_like(u, top)]
    up = np.array([0.0, 0.0, 0.05])
    approach = _cosine(process[0] + up, process[0], 500)[:-1]
    retract = _cosine(process[-1], process[-1] + up, 501)[1:]
    tcp = np.vstack([approach, process, retract])
    T_ft = np.eye(4)
    T_ft[2, 3] = 0.15
    T = np.tile(np.eye(4), (len(tcp), 1, 1))
    T[:, :3, :3] = Rotation.from_matrix(np.diag([1.0, -1.0, -1.0])).as_matrix()
    T[:, :3, 3] = tcp
    q_cart = follow_path(arm, T @ np.linalg.inv(T_ft), allowed_branches=(5, 7)).q_rad  # elbow up
    home = q_cart[0] + np.array([0.9, 0.35, -0.5, 0.2, 0.0, 0.6])  # turned away and raised
    n_transit = (10_000 - len(q_cart)) // 2
    transit = _cosine(home, q_cart[0], n_transit + 1)[:-1]
    back = _cosine(q_cart[-1], home, 10_000 - len(q_cart) - n_transit + 1)[1:]
    q = np.vstack([transit, q_cart, back])
    phase = np.r_[
        np.full(len(transit), Phase.TRANSIT),
        np.full(len(approach), Phase.APPROACH),
        np.full(len(process), Phase.PROCESS),
        np.full(len(retract), Phase.RETRACT),
        np.full(len(back), Phase.RETURN),
    ]
    return q, phase, T_ft, process


def test_collision_check_speed():
    rng = np.random.default_rng(0)
    arm = model("ur5e")
    scan = _scan(rng)
    boxes = (
        Box([-0.45, 0.35, 0.0], [-0.25, 0.60, 0.80], name="column"),
        Box([0.55, 0.25, 0.0], [0.85, 0.45, 0.30], name="feeder"),
    )
    print(f"\n## Collision check (UR5e, {N_SCAN:,}-point scan + plane + 2 boxes; 2 cores)\n")
    print("| step | samples | checked configurations | median s | min s | max s |")
    print("|---|---:|---:|---:|---:|---:|")
    med, lo, hi, cell = _timed(lambda: Cell(boxes=boxes, scan_points_m=scan, voxel_m=0.002))
    print(
        f"| scan preprocessing (1M points, 2 mm voxels) | - | - | {med:.3f} | {lo:.3f} | {hi:.3f} |"
    )
    q, phase, T_ft, _process = _plan(arm)
    zone = ContactZone.of_process(arm, q[phase == Phase.PROCESS], T_ft)
    for copies in (1, 10):
        qq, pp = np.tile(q, (copies, 1)), np.tile(phase, copies)
        t = np.arange(len(qq)) / RATE_HZ

        def run(qq=qq, pp=pp, t=t, workers=-1):
            return check_motion(
                arm,
                qq,
                pp,
                cell,
                T_flange_tcp=T_ft,
                tool=CapsuleTool(0.02),
                margin_m=0.01,
                contact_zone=zone,
                t_s=t,
                workers=workers,
            )

        med, lo, hi, report = _timed(run)
        print(
            f"| check_motion | {len(qq):,} | {len(report.checked_samples):,} | "
            f"{med:.3f} | {lo:.3f} | {hi:.3f} |"
        )
        if copies == 1:
            med1, lo1, hi1, _ = _timed(lambda run=run: run(workers=1))
            print(
                f"| check_motion, 1 thread | {len(qq):,} | | {med1:.3f} | {lo1:.3f} | {hi1:.3f} |"
            )
    print(
        f"\nScan after preprocessing: {len(cell.scan_m):,} points ({cell.scan_dropped:,} dropped "
        f"as the table), resolution {cell.scan_resolution_m * 1000:.2f} mm. "
        f"Motion bound {report.motion_bound_m * 1000:.2f} mm, tolerance "
        f"{report.tolerance_m * 1000:.2f} mm. Result: {report.lines()[0]}"
    )
    print("Target: 10k samples against a 1M-point scan in <= 0.3 s (preprocessing separate).")
