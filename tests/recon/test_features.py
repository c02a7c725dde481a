"""Scan structure: cropping, curvature, edge-line fits on analytic edges."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from recon.edge_lines import fit_edge_lines
from recon.errors import NoOverlapError
from recon.features import (
    covariance_features,
    crop_near,
    edge_threshold,
    neighbour_balls,
    prepare_scan,
    statistical_inliers,
    voxel_average,
)
from recon.fitting import symmetric_eig3
from recon.inputs import Scan
from recon.recon_params import ReconParams
from recon.scan_model import build_scan_model


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
    model = build_scan_model(Scan(points_m=scan), path, ReconParams())
    # Every slice holds one line (the plane) and no corner, so there is no edge.
    profiles = model.profiles
    assert np.all(profiles.line_ok.sum(axis=1)[: len(profiles) - 12] >= 1)
    assert not profiles.corner_ok.any()
    assert len(model.edges) == 0


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


# --- The scan's preparation in numpy and SciPy, against Open3D (the independent method it
# replaced: importing Open3D took 0.9 s of every command) and against analytic surfaces.


def _open3d_cloud(points):
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(points)))


def _sorted_rows(points):
    return points[np.lexsort(points.T)]


def test_voxel_averaging_matches_open3d():
    rng = np.random.default_rng(3)
    points = dihedral(rng, angle_deg=90, sigma_m=0.5e-3) + [0.4, -0.2, 0.1]
    mine, count = voxel_average(points, 0.002)
    theirs = np.asarray(_open3d_cloud(points).voxel_down_sample(0.002).points)
    assert count == len(mine) == len(theirs)
    np.testing.assert_allclose(_sorted_rows(mine), _sorted_rows(theirs), rtol=0, atol=1e-12)
    # The result does not depend on the points' order.
    again, _ = voxel_average(points[rng.permutation(len(points))], 0.002)
    np.testing.assert_allclose(again, mine, rtol=0, atol=1e-12)


def test_statistical_outliers_are_the_ones_open3d_removes():
    rng = np.random.default_rng(4)
    faces, _ = voxel_average(dihedral(rng, angle_deg=90, sigma_m=0.3e-3), 0.002)
    # Stray points 3-6 mm above face A: outliers with neighbours (Open3D's statistic decides).
    stray = np.column_stack(
        [rng.uniform(-0.02, 0.02, 40), rng.uniform(0.005, 0.025, 40), rng.uniform(3e-3, 6e-3, 40)]
    )
    points = np.concatenate([faces, stray])
    keep = statistical_inliers(points, cKDTree(points), neighbours=8, std_ratio=3.0)
    _, kept = _open3d_cloud(points).remove_statistical_outlier(8, 3.0)
    assert set(np.flatnonzero(keep)) == set(kept)
    assert np.count_nonzero(~keep[len(faces) :]) > 20  # most of the stray points
    assert np.count_nonzero(~keep[: len(faces)]) < 0.01 * len(faces)  # hardly any face point
    # Isolated points far from the faces.
    points = np.concatenate([points, rng.uniform(0.1, 0.2, (5, 3))])
    keep = statistical_inliers(points, cKDTree(points), neighbours=8, std_ratio=3.0)
    _, kept = _open3d_cloud(points).remove_statistical_outlier(8, 3.0)
    assert set(np.flatnonzero(keep)) == set(kept)
    assert not np.any(keep[-5:])


def test_normals_and_curvature_match_open3d_and_the_analytic_plane():
    rng = np.random.default_rng(5)
    points, _ = voxel_average(dihedral(rng, angle_deg=90, sigma_m=0.5e-3), 0.002)
    normals, curvature = _normals(points)
    cloud = _open3d_cloud(points)
    cloud.estimate_covariances(o3d_hybrid(0.008, 48))
    values, expected_normals = symmetric_eig3(np.asarray(cloud.covariances))
    expected = values[:, 0] / values.sum(axis=1)
    # Balls of fewer than 3 points have no surface (1/3 here; Open3D's identity gives 1/3 too).
    np.testing.assert_allclose(curvature, expected, rtol=0, atol=1e-9)
    surface = curvature < 1 / 3
    cosine = np.abs(np.einsum("ij,ij->i", normals[surface], expected_normals[surface]))
    assert cosine.min() > 1 - 1e-9
    # Far from the crest, face A's normal is +-z and its variation that of the noise.
    on_a = (points[:, 1] > 0.012) & (np.abs(points[:, 2]) < 0.002)
    assert np.abs(normals[on_a, 2]).min() > 0.99
    assert np.median(curvature[on_a]) < 0.02


def test_a_noise_free_plane_has_no_curvature_and_its_normal_far_from_the_origin():
    rng = np.random.default_rng(6)
    xy = rng.uniform(0, 0.05, (3000, 2))
    tilt = np.array([0.2, -0.1])
    points = np.column_stack([xy, xy @ tilt]) + [120.0, -80.0, 40.0]  # far away: precision
    normals, curvature = _normals(points)
    expected = np.array([-tilt[0], -tilt[1], 1.0]) / np.linalg.norm([*tilt, 1.0])
    assert np.abs(normals @ expected).min() > 1 - 1e-6
    assert curvature.max() < 1e-6


def _normals(points):
    balls = neighbour_balls(points, cKDTree(points), radius_m=0.008, max_neighbours=48)
    return covariance_features(points, balls)


def o3d_hybrid(radius_m, max_nn):
    import open3d as o3d

    return o3d.geometry.KDTreeSearchParamHybrid(radius_m, max_nn)


def test_small_and_degenerate_clouds():
    # Nothing, or no averaging: the points as they are.
    empty, count = voxel_average(np.zeros((0, 3)), 0.002)
    assert empty.shape == (0, 3) and count == 0
    points = np.random.default_rng(7).normal(size=(5, 3))
    same, count = voxel_average(points, 0.0)
    np.testing.assert_array_equal(same, points)
    assert count == 5
    # A grid too large for one integer key (kilometres in 1 mm voxels) still averages exactly.
    far = np.array([[0.0, 0.0, 0.0], [0.0002, 0.0, 0.0], [3e6, 4e6, 5e6]])
    centroids, count = voxel_average(far, 0.001)
    assert count == 2
    np.testing.assert_allclose(_sorted_rows(centroids), [[0.0001, 0.0, 0.0], [3e6, 4e6, 5e6]])
    # Fewer points than the cap, down to one: balls of what there is; no surface in them.
    for m in (1, 2, 5):
        cloud = points[:m] * 1e-3
        balls = neighbour_balls(cloud, cKDTree(cloud), radius_m=0.008, max_neighbours=48)
        assert balls.shape == (m, m)
        normals, curvature = covariance_features(cloud, balls)
        assert normals.shape == (m, 3) and np.all(np.isfinite(normals))
        assert np.all(curvature[np.diff(balls.indptr) < 3] == 1 / 3)
    # Outlier statistics need more points than neighbours: fewer are all kept.
    few = points[:5]
    assert statistical_inliers(few, cKDTree(few), neighbours=8, std_ratio=3.0).all()
