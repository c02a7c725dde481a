"""Scan structure: cropping, curvature, edge-line fits on analytic edges."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from recon.edge_lines import fit_edge_lines
from recon.edges import thin_edges
from recon.errors import NoOverlapError
from recon.features import crop_near, edge_threshold, prepare_scan


def dihedral(
    rng, *, angle_deg, sigma_m, concave=False, length_m=0.06, width_m=0.03, density_per_mm2=2.0
):
    """Two faces meeting along the x axis at ``angle_deg`` (180 = flat), with normal noise.

    Face A lies in the xy half-plane y >= 0; face B leaves the x axis at ``angle_deg`` to it,
    going down (convex, like a box's top edge) or up (concave, like a weld seam).
    """
    n = int(length_m * width_m * 1e6 * density_per_mm2)
    x = rng.uniform(-length_m / 2, length_m / 2, (2, n))
    d = rng.uniform(0, width_m, (2, n))
    a = np.radians(angle_deg)
    sign = 1.0 if concave else -1.0
    face_a = np.column_stack([x[0], d[0], np.zeros(n)])
    direction_b = np.array([0.0, np.cos(a), sign * np.sin(a)])
    face_b = np.column_stack([x[1], np.zeros(n), np.zeros(n)]) + d[1][:, None] * direction_b
    normal_b = np.cross([1.0, 0.0, 0.0], direction_b)
    face_a[:, 2] += rng.normal(0, sigma_m, n)
    face_b += rng.normal(0, sigma_m, n)[:, None] * normal_b
    return np.concatenate([face_a, face_b])


def features_of(points, path):
    return prepare_scan(points, path, crop_margin_m=0.025, voxel_m=0.002, curvature_radius_m=0.008)


def test_crop_keeps_everything_within_the_radius_and_nothing_far_beyond():
    rng = np.random.default_rng(0)
    scan = rng.uniform(-0.2, 0.2, (200_000, 3))
    path = np.column_stack([np.linspace(-0.1, 0.1, 200), np.zeros(200), np.zeros(200)])
    mask = crop_near(scan, path, 0.02)
    dist, _ = cKDTree(path).query(scan)
    assert np.all(mask[dist <= 0.02])
    assert not np.any(mask[dist > 0.02 * 1.9])


@pytest.mark.parametrize("angle_deg, concave", [(90, False), (120, False), (90, True)])
def test_edge_lines_are_found_on_analytic_edges(angle_deg, concave):
    rng = np.random.default_rng(1)
    scan = dihedral(rng, angle_deg=angle_deg, sigma_m=0.0002, concave=concave)
    # Queries a few millimetres off the edge, as a drifting trace would be.
    xs = np.linspace(-0.02, 0.02, 11)
    queries = np.column_stack([xs, np.full(11, 0.002), np.full(11, 0.0015)])
    feats = features_of(scan, queries)
    fit = fit_edge_lines(queries, feats, radius_m=0.016)
    assert fit.ok.all()
    # The true edge is the x axis: the fitted points must sit on it, the lines along it.
    off_axis = np.linalg.norm(fit.points_m[:, 1:], axis=1)
    assert off_axis.max() < 1e-4, off_axis
    assert np.abs(fit.directions[:, 0]).min() > 0.999
    assert fit.dihedral_deg == pytest.approx(np.full(11, 180 - angle_deg), abs=2.0)


def test_a_flat_surface_has_no_edge_lines_and_few_edge_points():
    rng = np.random.default_rng(2)
    scan = dihedral(rng, angle_deg=180, sigma_m=0.0005)  # two coplanar halves: a plane
    path = np.column_stack([np.linspace(-0.02, 0.02, 41), np.full(41, 0.01), np.zeros(41)])
    feats = features_of(scan, path)
    assert feats.is_edge.mean() < 0.1
    assert (
        len(thin_edges(feats, path, radius_m=0.016, query_spacing_m=0.004, sample_spacing_m=0.001))
        == 0
    )


def test_edge_threshold_separates_faces_from_crests():
    rng = np.random.default_rng(3)
    faces = rng.uniform(0.0, 0.01, 900)
    crests = rng.uniform(0.09, 0.12, 100)
    threshold = edge_threshold(np.concatenate([faces, crests]))
    assert 0.01 < threshold < 0.09


def test_a_scan_far_from_the_path_is_refused():
    rng = np.random.default_rng(4)
    scan = dihedral(rng, angle_deg=90, sigma_m=0.0002)
    path = np.column_stack([np.linspace(0, 0.05, 50), np.full(50, 1.0), np.zeros(50)])
    with pytest.raises(NoOverlapError, match="same frame and units"):
        features_of(scan, path)
