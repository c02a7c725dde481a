"""Registration of a trace to a real scanner's output: the corpus's PLY fragment (a room scan
from Open3D's colored-ICP example; ``../shared/corpus/real-inputs/PROVENANCE.md``).

A trace that lies on the scan, in the scan's frame, must not be reported (nor moved) as
"moved 10.8 mm on average": the registration's iterations used to creep across the fragment's
relief to a placement that fitted worse than where they began. Skipped, saying so, where the
corpus is absent.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from drivers.scanning.pointcloud import read_scan
from recon.inputs import Recording
from recon.recon_params import ReconParams
from recon.transforms import apply_transform
from service import pipelines
from tests.corpus import require_corpus

#: Seeds of the traces laid on the fragment.
SEEDS = range(6)
#: Hand noise of the traces, RMS distance, metres.
TRACE_NOISE_M = 0.0007


@pytest.fixture(scope="module")
def fragment():
    path = require_corpus() / "real-inputs" / "ply" / "open3d_coloredicp_frag_115.ply"
    return read_scan(path).scan


def trace_on(scan, seed: int) -> np.ndarray:
    """A 150 mm wavy trace lying on the scan (each sample the mean of the 8 scan points nearest
    a wavy line through a random scan point), with hand noise; (600, 3), scan frame."""
    points = np.asarray(scan.points_m)
    tree = cKDTree(points)
    rng = np.random.default_rng(seed)
    start = points[rng.integers(len(points))]
    heading = rng.uniform(0, 2 * np.pi)
    along = np.array([np.cos(heading), np.sin(heading), 0.0])
    across = np.array([-along[1], along[0], 0.0])
    s = np.linspace(0.0, 0.15, 600)
    line = start + s[:, None] * along + 0.01 * np.sin(s / 0.15 * 4 * np.pi)[:, None] * across
    _, nearest = tree.query(line, k=8)
    on_scan = points[nearest].mean(axis=1)
    return on_scan + rng.normal(0.0, TRACE_NOISE_M / np.sqrt(3), on_scan.shape)


@pytest.mark.slow
def test_a_trace_lying_on_a_real_scan_fragment_is_left_where_it_is(fragment):
    """Before the descent test, 3-17 mm moves (median 7.4 mm) on these traces; now the
    registration moves them by about the hand noise (a few seeds slide ~2 mm along the
    nearly flat patches, where the fit is genuinely better)."""
    moved_max_m = []
    for seed in SEEDS:
        trace = trace_on(fragment, seed)
        outcome = pipelines.reconstruct(
            Recording(points_m=trace, t_s=np.arange(len(trace)) / 100.0),
            fragment,
            params=ReconParams(),
        )
        registration = outcome.reconstruction.registration
        assert registration.target == "surface"
        moved_max_m.append(registration.path_moved_max_m)
        # What moved is mostly sliding along the fragment's nearly flat patches, and the
        # report says so: off the surface by about the hand noise at most.
        assert registration.path_moved_off_feature_median_m < TRACE_NOISE_M, seed
        report = next(line for line in outcome.lines() if line.startswith("registered to"))
        assert "mm of it off the surface on median, the rest along it" in report
    assert np.median(moved_max_m) < 1.5e-3, moved_max_m
    assert max(moved_max_m) < 4e-3, moved_max_m


@pytest.mark.slow
def test_a_registered_trace_fits_the_raw_scan_no_worse_than_where_it_lies(fragment):
    """Judged independently of the ICP's own model (voxel averages and their normals): the RMS
    distance of the trace to the raw scan's tangent planes (normals by Open3D), once
    registered, against the same figure where the trace truly lies. Before the descent test the
    registration ended up to 0.06 mm worse on these traces; a scanner misplaced by
    4 mm is brought back onto the surface as well."""
    raw_m = np.array(fragment.points_m, dtype=np.float64)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(raw_m))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.02, max_nn=30))
    points, normals = np.asarray(cloud.points), np.asarray(cloud.normals)
    tree = cKDTree(points)

    def plane_rms_m(trace_scan_m):
        _, nearest = tree.query(trace_scan_m)
        offset = np.einsum("ij,ij->i", trace_scan_m - points[nearest], normals[nearest])
        return float(np.sqrt(np.mean(offset**2)))

    misplaced = np.eye(4)
    misplaced[:3, 3] = [0.003, -0.002, 0.002]
    rows = []
    for seed in SEEDS:
        trace = trace_on(fragment, seed)
        for T_scan_tracker in (np.eye(4), misplaced):
            in_tracker = apply_transform(np.linalg.inv(T_scan_tracker), trace)
            outcome = pipelines.reconstruct(
                Recording(points_m=in_tracker, t_s=np.arange(len(trace)) / 100.0),
                fragment,
                params=ReconParams(),
            )
            registered = apply_transform(outcome.reconstruction.T_scan_tracker, in_tracker)
            rows.append(
                (seed, plane_rms_m(registered), plane_rms_m(trace), plane_rms_m(in_tracker))
            )
    # Where the trace was given in place, the registration must not make its fit worse: before
    # the descent test 5 of these 6 ended 0.02-0.06 mm worse than where the trace lies (now
    # within 0.01 mm, most of them better).
    in_place = [(registered - truth) for _, registered, truth, given in rows[::2]]
    assert max(in_place) <= 1.5e-5 and np.mean(in_place) <= 5e-6, rows
    # Misplaced by 4 mm: back onto the surface (the sliding along it is not observable here).
    for _, registered, truth, given in rows[1::2]:
        assert registered <= truth + 1.5e-4 and registered <= 0.5 * given, rows
