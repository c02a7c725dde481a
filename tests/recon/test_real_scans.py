"""Registration on scans written by real tools (``../shared/corpus/real-inputs``; skipped,
saying so, where the corpus is absent)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from drivers.scanning.pointcloud import read_scan
from recon.types import ReconParams
from service import pipelines
from tests.corpus import require_corpus
from tests.recon.test_icp import transform

FRAGMENT = "ply/open3d_coloredicp_frag_115.ply"


@pytest.fixture(scope="module")
def fragment():
    """Open3D's fused RGB-D fragment (a patterned floor with a few mm of relief), and a wavy
    0.63 m trace on it: points of its surface (means of 8 vertices) with 0.7 mm of noise."""
    scan = read_scan(require_corpus() / "real-inputs" / FRAGMENT).scan
    vertices = np.asarray(scan.points_m)
    centre = vertices.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((vertices - centre).T))
    s = np.linspace(-0.25, 0.25, 600)
    line = centre + np.outer(s, axes[:, 2]) + 0.05 * np.outer(np.sin(s * 10), axes[:, 1])
    _, near = cKDTree(vertices).query(line, k=8)
    surface = vertices[near].mean(axis=1)
    noisy = surface + np.random.default_rng(0).normal(0, 0.0007, surface.shape)
    return scan, noisy, axes[:, 0]


def _recording(points_m):
    from recon.types import Recording

    return Recording(points_m=points_m, t_s=np.arange(len(points_m)) / 100.0)


def test_a_trace_that_sits_on_a_real_fragment_is_not_reported_moved(fragment):
    """The tester's finding: "moved 13.9 mm" for a trace that sits on the scan (here it was
    10.8 mm on average, 12.3 at most, for a worse fit). Now the placement is kept, and said."""
    scan, trace, _ = fragment
    outcome = pipelines.reconstruct(_recording(trace), scan, params=ReconParams())
    registration = outcome.reconstruction.registration
    said = [line for line in outcome.lines() if line.startswith("registered")]
    print("\n" + "\n".join(said))
    assert registration.kept_initial
    assert registration.path_moved_max_m == 0.0
    assert len(said) == 1 and "kept where it was given" in said[0]


def test_a_trace_misplaced_off_a_real_fragment_is_registered_back(fragment):
    """The same trace 3 mm off the surface and tilted 0.3 deg: registered onto it."""
    scan, trace, normal = fragment
    T = transform([0.2, -0.2, 0.1], 0.003 * normal)
    centre = trace.mean(axis=0)
    misplaced = (trace - centre) @ T[:3, :3].T + centre + T[:3, 3]
    outcome = pipelines.reconstruct(_recording(misplaced), scan, params=ReconParams())
    registration = outcome.reconstruction.registration
    moved = registration.path_moved_mean_m
    print(f"\nmisplaced 3 mm: the registration moved the path {moved * 1e3:.2f} mm on average")
    assert not registration.kept_initial
    assert 2.0e-3 < moved < 4.5e-3
