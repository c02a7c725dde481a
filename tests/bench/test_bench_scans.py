"""Scan readers: read time per format at realistic sizes, and how RGB-D fusion trades speed for
accuracy (``make bench``). Printed as tables; no time is asserted (shared, noisy machines).

Inputs are generated: random clouds for the point-cloud formats and E57, and the analytic
plane-with-ridge scene of ``tests/drivers/test_scan_readers.py`` rendered into 640 x 480 depth
PNGs for RGB-D (one frame, and 30 frames on a circle around the workpiece).
"""

from __future__ import annotations

import json
import shutil
import statistics
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from drivers.scanning.base import read_scan
from drivers.scanning.pointcloud import write_scan
from recon.inputs import Scan
from tests.drivers.test_scan_readers import (
    intrinsics_json,
    render_depth,
    sequence_poses,
    surface_distance,
    to_raw,
    write_e57,
    write_open3d_log,
    write_png,
    zip_folder,
)

pytestmark = pytest.mark.bench

REPEATS = 5
N_POINTS = 1_000_000
N_FRAMES = 30


def _median_time(read) -> tuple[float, object]:
    times, result = [], None
    for _ in range(REPEATS):
        start = time.perf_counter()
        result = read()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def _size(path: Path) -> float:
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 2**20
    return path.stat().st_size / 2**20


def _noisy_sequence(root: Path, sigma_at_half_metre_m: float, n_frames: int = N_FRAMES) -> Path:
    """Like make_sequence, with depth noise growing with the square of the depth (as in
    structured-light and stereo cameras) and a fixed seed. Noise also gives the PNGs the size
    real ones have (smooth synthetic depth compresses about 20 times better)."""
    rng = np.random.default_rng(0)
    root.mkdir(parents=True)
    (root / "intrinsics.json").write_text(json.dumps(intrinsics_json()))
    poses = sequence_poses(n_frames)
    for i, T in enumerate(poses):
        depth = render_depth(T)
        noise = rng.normal(0.0, 1.0, depth.shape) * sigma_at_half_metre_m * (depth / 0.5) ** 2
        write_png(root / "depth" / f"{i:06d}.png", to_raw(depth + np.nan_to_num(noise)))
    write_open3d_log(root / "trajectory.log", poses)
    return root


@pytest.fixture(scope="module")
def noisy(tmp_path_factory) -> Path:
    return _noisy_sequence(tmp_path_factory.mktemp("bench") / "noisy", 0.001)


def _reader(source, **kwargs):
    return lambda: read_scan(source, **kwargs)


def test_read_times(tmp_path, noisy):
    rng = np.random.default_rng(0)
    cloud = Scan(points_m=rng.uniform(-0.5, 0.5, (N_POINTS, 3)))
    write_scan(tmp_path / "cloud.ply", cloud)  # Open3D writes binary PLY by default
    o3d.io.write_point_cloud(
        str(tmp_path / "cloud.pcd"),
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(cloud.points_m))),
        write_ascii=False,
    )
    write_scan(tmp_path / "cloud.xyz", cloud)
    half = N_POINTS // 2
    write_e57(
        tmp_path / "cloud.e57",
        [
            (cloud.points_m[:half], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0], None),
            (cloud.points_m[half:], [0.0, 0.0, 0.0, 1.0], [1.0, 2.0, 3.0], None),
        ],
    )
    frame = tmp_path / "frame"
    frame.mkdir()
    (frame / "intrinsics.json").write_text(json.dumps(intrinsics_json()))
    shutil.copy(noisy / "depth" / "000000.png", frame / "depth.png")
    archive = zip_folder(noisy, tmp_path / "sequence.zip")
    upload = archive.read_bytes()
    ply, pcd, xyz, e57 = (tmp_path / f"cloud.{s}" for s in ("ply", "pcd", "xyz", "e57"))
    frames = f"{N_FRAMES} x 640x480"
    rows = [
        ("PLY, binary", "1M points", ply, _reader(ply)),
        ("PCD, binary", "1M points", pcd, _reader(pcd)),
        ("XYZ, text", "1M points", xyz, _reader(xyz)),
        ("E57", "1M points, 2 posed scans", e57, _reader(e57)),
        ("RGB-D, one frame", "640x480", frame, _reader(frame)),
        ("RGB-D folder, TSDF (default)", frames, noisy, _reader(noisy)),
        (
            "RGB-D folder, points + 2 mm voxels",
            frames,
            noisy,
            _reader(noisy, options={"fusion": "points"}),
        ),
        ("RGB-D zip upload (bytes), TSDF", frames, archive, _reader(upload, name="s.zip")),
    ]
    print(f"\n## Scan read time (median of {REPEATS})\n")
    print("| format | input | MiB | points read | time (s) |")
    print("|---|---|---:|---:|---:|")
    for label, size, path, read in rows:
        seconds, result = _median_time(read)
        print(f"| {label} | {size} | {_size(path):.1f} | {len(result.scan):,} | {seconds:.2f} |")
    print(
        "| RealSense .bag | - | - | - | not measured: nothing here can record a bag; only the "
        "child process start (about 1.5 s) is known |"
    )


def test_fusion_accuracy(tmp_path, noisy):
    """Why TSDF is the default: distance of the fused points to the analytic surface."""
    print(f"\n## RGB-D fusion of {N_FRAMES} frames: error against the true surface (mm)\n")
    print("| depth noise at 0.5 m | fusion | points | RMS | 99th pct | max | time (s) |")
    print("|---:|---|---:|---:|---:|---:|---:|")
    for sigma in (0.0, 0.001):
        root = noisy if sigma else _noisy_sequence(tmp_path / "exact", 0.0)
        for fusion in ("tsdf", "points"):
            start = time.perf_counter()
            result = read_scan(root, options={"fusion": fusion})
            seconds = time.perf_counter() - start
            points = result.scan.points_m
            # The workpiece region: the ridge and the plane around it, seen by every camera.
            near = np.linalg.norm(points[:, :2], axis=1) < 0.15
            d = surface_distance(points[near]) * 1e3
            print(
                f"| {sigma * 1e3:.1f} mm | {fusion} | {near.sum():,} | "
                f"{np.sqrt(np.mean(d**2)):.2f} | {np.percentile(d, 99):.2f} | {d.max():.2f} | "
                f"{seconds:.1f} |"
            )
