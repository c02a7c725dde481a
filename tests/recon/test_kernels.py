"""The compiled kernels (recon/_kernels.c) against their numpy references (recon/kernels.py),
bit for bit where the arithmetic is the same, and against hostile arguments.

``make setup`` builds the kernels; without them every function falls back to its reference, so
the first test fails loudly when the build did not happen (every comparison below would
otherwise compare the reference with itself).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from recon import kernels
from recon.features import ball_covariances, ball_moments, neighbour_balls
from recon.kernels import (
    KERNELS_ENV,
    PointGrid,
    csr_row_sums,
    csr_row_sums_reference,
    hough_votes,
    hough_votes_reference,
    nearest_within,
    nearest_within_reference,
)

MM = 1e-3


@pytest.fixture
def reference_only(monkeypatch):
    """Every kernel runs its numpy reference for the duration of the test."""
    monkeypatch.setenv(KERNELS_ENV, "numpy")


def _surface_cloud(n: int, seed: int) -> np.ndarray:
    """A scan-like cloud: two noisy faces meeting at an edge, 0.1 m long (about a point per
    square millimetre, as a depth camera's)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(0.0, 0.1, n)
    v = rng.uniform(0.0, 0.02, n)
    wall = rng.random(n) < 0.5
    points = np.column_stack([u, np.where(wall, 0.0, v), np.where(wall, v, 0.0)])
    return points + rng.normal(0.0, 0.2 * MM, points.shape)


def test_the_compiled_kernels_are_built():
    """make setup compiles recon/_kernels.c; a missing build would silently run the
    references (and make every comparison here compare them with themselves)."""
    assert kernels.compiled() is not None, "recon._kernels is not built: run make setup"


def test_the_environment_variable_selects_the_references(monkeypatch):
    monkeypatch.setenv(KERNELS_ENV, "numpy")
    assert kernels.compiled() is None
    monkeypatch.setenv(KERNELS_ENV, "")
    assert kernels.compiled() is not None


@pytest.mark.parametrize(
    ("n", "k", "radius_m"),
    [(20_000, 16, 4 * MM), (20_000, 48, 8 * MM), (5_000, 1, 2 * MM), (3_000, 768, 12.6 * MM)],
)
def test_nearest_within_is_the_trees_answer_to_the_bit(n, k, radius_m):
    points = _surface_cloud(n, seed=k)
    rng = np.random.default_rng(1)
    # The points themselves, points near them, and queries far outside the cloud.
    queries = np.concatenate(
        [points[::3], points[::7] + rng.normal(0, 2 * MM, (len(points[::7]), 3)), [[5.0, 5, 5]]]
    )
    distance, index = nearest_within(points, queries, k=k, radius_m=radius_m)
    tree_distance, tree_index = nearest_within_reference(points, queries, k=k, radius_m=radius_m)
    np.testing.assert_array_equal(distance, tree_distance)
    np.testing.assert_array_equal(index, tree_index)
    assert np.all(np.isinf(distance[-1])) and np.all(index[-1] == n)


def test_nearest_within_keeps_the_radius_strict_and_breaks_ties_by_index():
    """On a lattice many neighbours are equally far: the distances are still the tree's, and
    among equals the smaller index comes first (the tree's own order there is arbitrary)."""
    axis = np.arange(12) * MM
    points = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    queries = points[::17]
    for k, radius_m in ((7, 1.0 * MM), (7, 1.0001 * MM), (30, 2.5 * MM)):
        distance, index = nearest_within(points, queries, k=k, radius_m=radius_m)
        tree_distance, _ = nearest_within_reference(points, queries, k=k, radius_m=radius_m)
        np.testing.assert_array_equal(distance, tree_distance)
        found = np.isfinite(distance)
        # Exactly one millimetre away is not within one millimetre.
        assert np.all(distance[found] < radius_m)
        d0, d1, i0, i1 = distance[:, :-1], distance[:, 1:], index[:, :-1], index[:, 1:]
        ordered = (d0 < d1) | ((d0 == d1) & (i0 < i1))
        assert np.all(ordered[found[:, 1:]])
        assert np.any((d0 == d1) & found[:, 1:]), "the lattice has equally far neighbours"
        # Each neighbour listed really is at that distance.
        rows = np.nonzero(found)
        gap = np.linalg.norm(points[index[rows]] - queries[rows[0]], axis=1)
        np.testing.assert_array_equal(gap, distance[rows])


def test_nearest_within_answers_queries_that_find_nothing():
    points = _surface_cloud(500, seed=3)
    queries = np.array([[np.nan, 0, 0], [np.inf, 0, 0], [-1e300, 1e300, 0], [0.05, 0.0, 0.0]])
    distance, index = nearest_within(points, queries, k=4, radius_m=3 * MM)
    assert np.all(np.isinf(distance[:3])) and np.all(index[:3] == len(points))
    assert np.isfinite(distance[3, 0])
    empty_distance, empty_index = PointGrid(np.zeros((0, 3)), 0.001).nearest(
        queries, k=2, radius_m=0.001
    )
    assert np.all(np.isinf(empty_distance)) and empty_index.shape == (4, 2)


def test_a_grid_spanning_more_cells_than_the_kernel_allows_coarsens():
    """A cloud kilometres wide with a millimetre radius: the grid takes coarser cells (at most
    2**20 per axis) and still answers right."""
    points = np.array([[0.0, 0, 0], [0.0005, 0, 0], [3000.0, 0, 0]])
    grid = PointGrid(points, 0.001)
    assert grid.cell_m > 0.001 and np.all(grid.dims <= kernels.MAX_CELLS_PER_AXIS)
    distance, index = grid.nearest(points[:1], k=3, radius_m=0.001)
    assert list(index[0]) == [0, 1, 3] and distance[0, 1] == 0.0005


def test_ball_sums_are_the_sparse_products_to_the_bit():
    points = _surface_cloud(30_000, seed=5)
    columns = np.column_stack([points, points**2, points[:, :1] * points[:, 1:]])
    balls = neighbour_balls(points, cKDTree(points), radius_m=4 * MM, max_neighbours=16)
    expected = csr_row_sums_reference(balls, columns)
    sums, counts = PointGrid(points, 4 * MM).ball_sums(points, columns, k=16, radius_m=4 * MM)
    np.testing.assert_array_equal(sums, expected)
    np.testing.assert_array_equal(counts, np.diff(balls.indptr))
    np.testing.assert_array_equal(csr_row_sums(balls, columns), expected)


@pytest.mark.parametrize("rows", [None, "some"])
def test_ball_moments_are_the_references_to_the_bit(rows, monkeypatch):
    points = _surface_cloud(30_000, seed=6)
    wanted = None if rows is None else np.arange(0, len(points), 5)
    covariances, counts = ball_moments(points, None, radius_m=8 * MM, rows=wanted)
    monkeypatch.setenv(KERNELS_ENV, "numpy")
    ref_covariances, ref_counts = ball_moments(
        points, cKDTree(points), radius_m=8 * MM, rows=wanted
    )
    np.testing.assert_array_equal(covariances, ref_covariances)
    np.testing.assert_array_equal(counts, ref_counts)
    # And the sparse route of the tests and tools that build the matrix themselves.
    balls = neighbour_balls(points, cKDTree(points), radius_m=8 * MM, rows=wanted)
    matrix_covariances, _ = ball_covariances(points, balls)
    selected = slice(None) if wanted is None else wanted
    np.testing.assert_array_equal(matrix_covariances[selected], ref_covariances)


def test_ball_moments_refuse_rows_out_of_order():
    points = _surface_cloud(100, seed=7)
    with pytest.raises(ValueError, match="increasing"):
        ball_moments(points, None, radius_m=8 * MM, rows=np.array([5, 3]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hough_votes_are_the_references_to_the_bit(seed):
    rng = np.random.default_rng(seed)
    b, k = 40, 300
    x = rng.uniform(-0.012, 0.012, (b, k))
    y = rng.uniform(-0.012, 0.012, (b, k))
    phi = rng.uniform(0.0, np.pi, (b, k))
    phi[:, :3] = [0.0, np.nextafter(np.pi, 0), np.pi / 30 * 7]  # the bins' borders
    weight = rng.random((b, k)) < 0.7
    grid = {"n_theta": 30, "half_window": 1, "radius_m": 0.012, "rho_bin_m": 0.0005, "n_rho": 50}
    np.testing.assert_array_equal(
        hough_votes(x, y, phi, weight, **grid), hough_votes_reference(x, y, phi, weight, **grid)
    )


#: How far the whole reconstruction may move between the kernels and the references: the fits'
#: sums (weighted PCA, normal equations) add the same terms in another order, about 1e-16 m
#: apart; the benched scenes' paths moved 3e-15 m at most. Every other kernel is exact.
WHOLE_RECONSTRUCTION_TOLERANCE_M = 1e-12


@pytest.mark.parametrize("scene_name", ["long_edge", "box_corner", "flat_liftoff"])
def test_the_reconstruction_is_the_same_with_and_without_the_kernels(scene_name, monkeypatch):
    """The whole reconstruction of a scene: every decision the same (flags, labels, counts to
    the bit), every number within rounding (WHOLE_RECONSTRUCTION_TOLERANCE_M)."""
    from recon import scenes
    from recon.reconstruct import reconstruct

    if scene_name == "long_edge":
        scene = scenes.long_edge(600, 40_000, seed=2)
    else:
        scene = scenes.SCENES[scene_name](0)
    compiled = reconstruct(scene.recording, scene.scan)
    monkeypatch.setenv(KERNELS_ENV, "numpy")
    reference = reconstruct(scene.recording, scene.scan)
    tolerance = WHOLE_RECONSTRUCTION_TOLERANCE_M
    np.testing.assert_allclose(compiled.points_m, reference.points_m, rtol=0, atol=tolerance)
    np.testing.assert_allclose(
        compiled.uncertainty_m, reference.uncertainty_m, rtol=0, atol=tolerance
    )
    np.testing.assert_array_equal(compiled.mode, reference.mode)
    ours, theirs = compiled.scan_model.to_arrays(), reference.scan_model.to_arrays()
    assert ours.keys() == theirs.keys()
    for key in ours:
        if ours[key].dtype.kind == "f":
            # Metres, unit vectors, squared metres: all far below a millimetre's scale.
            np.testing.assert_allclose(
                ours[key], theirs[key], rtol=1e-9, atol=tolerance, err_msg=key
            )
        else:
            np.testing.assert_array_equal(ours[key], theirs[key], err_msg=key)


def _neighbourhoods(b: int, k: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Batches as the fits see them: points a metre from the origin, centimetres apart, weights
    0 (padding) and 1, a few fractional; one empty row and one of a single point."""
    rng = np.random.default_rng(seed)
    points = 1.0 + rng.normal(0.0, 0.01, (b, k, 3))
    weights = (rng.random((b, k)) < 0.7).astype(np.float64)
    if b >= 4 and k >= 4:
        weights[: b // 4] *= rng.uniform(0.1, 2.0, (b // 4, k))
        weights[-1] = 0.0
        weights[-2] = 0.0
        weights[-2, 3] = 1.0
    return points, weights


@pytest.mark.parametrize("shape", [(200, 768), (7, 1), (0, 5), (3, 0)])
def test_weighted_pca_is_the_references_to_rounding(shape, monkeypatch):
    from recon.fitting import weighted_pca

    points, weights = _neighbourhoods(*shape, seed=21)
    assert kernels.weighted_moments(points, weights) is not None
    compiled = weighted_pca(points, weights)
    monkeypatch.setenv(KERNELS_ENV, "numpy")
    assert kernels.weighted_moments(points, weights) is None
    reference = weighted_pca(points, weights)
    np.testing.assert_allclose(compiled.weight, reference.weight, rtol=1e-13, atol=0)
    whole = slice(len(points) // 4, None)  # 0/1 weights: their sums are exact
    np.testing.assert_array_equal(compiled.weight[whole], reference.weight[whole])
    np.testing.assert_allclose(compiled.mean, reference.mean, rtol=0, atol=1e-14)
    # Variances of (1 cm)^2 to 1e-16 of a square metre; axes agree up to sign where their
    # variances are apart.
    np.testing.assert_allclose(compiled.variances, reference.variances, rtol=1e-9, atol=1e-18)
    if len(points):
        dots = np.abs(np.einsum("bij,bij->bj", compiled.axes, reference.axes))
        distinct = np.diff(reference.variances[:, ::-1], axis=1).min(axis=1) > 1e-9
        np.testing.assert_allclose(dots[distinct], 1.0, atol=1e-9)


@pytest.mark.parametrize("outputs", [1, 2, 3])
def test_weighted_least_squares_are_the_references_to_rounding(outputs, monkeypatch):
    from recon.fitting import fit_linear, poly_design

    points, weights = _neighbourhoods(300, 129, seed=22)
    design = poly_design(points[..., 0] - 1.0, degree=2, scale=0.01)  # (B, K, 3)
    y = points[..., 1 : 1 + outputs] if outputs > 1 else points[..., 1]
    assert kernels.normal_equations(design, y[..., None] if y.ndim == 2 else y, weights)
    compiled = fit_linear(design, y, weights)
    monkeypatch.setenv(KERNELS_ENV, "numpy")
    reference = fit_linear(design, y, weights)
    ok = reference.dof > 0
    np.testing.assert_array_equal(compiled.dof, reference.dof)
    np.testing.assert_allclose(compiled.coef[ok], reference.coef[ok], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(compiled.rms[ok], reference.rms[ok], rtol=1e-7, atol=1e-15)
    np.testing.assert_allclose(
        compiled.normal_inverse[ok], reference.normal_inverse[ok], rtol=1e-9, atol=1e-9
    )


def test_the_fit_kernels_refuse_shapes_that_lie():
    module = kernels.compiled()
    points, weights = _neighbourhoods(4, 10, seed=23)
    out = (np.empty(4), np.empty((4, 3)), np.empty((4, 3, 3)))
    with pytest.raises(ValueError, match="points holds"):
        module.weighted_moments(points, weights, 4, 11, *out)  # k says 11
    with pytest.raises(ValueError, match="out_cov holds"):
        module.weighted_moments(points, weights, 4, 10, out[0], out[1], np.empty((3, 3, 3)))
    with pytest.raises(ValueError, match="b and k"):
        module.weighted_moments(points, weights, -1, 10, *out)
    with pytest.raises(ValueError, match="b and k"):
        module.weighted_moments(points, weights, 2**40, 2**40, *out)  # overflows
    with pytest.raises(ValueError, match="must be"):
        kernels.weighted_moments(points[..., :2], weights)
    design, y = np.ones((4, 10, 3)), np.ones((4, 10, 2))
    normal, rhs = np.empty((4, 3, 3)), np.empty((4, 3, 2))
    with pytest.raises(ValueError, match="y holds"):
        module.normal_equations(design, np.ones((4, 9, 2)), weights, 4, 10, 3, 2, normal, rhs)
    with pytest.raises(ValueError, match="p and m"):
        module.normal_equations(design, y, weights, 4, 10, 0, 2, normal, rhs)
    with pytest.raises(ValueError, match="p and m"):
        module.normal_equations(design, y, weights, 4, 10, 3, 65, normal, rhs)
    with pytest.raises(ValueError, match="out_rhs holds"):
        module.normal_equations(design, y, weights, 4, 10, 3, 2, normal, np.empty((4, 2, 2)))
    with pytest.raises(ValueError, match="coef holds"):
        module.residual_squares(design, y, weights, np.empty((4, 3)), 4, 10, 3, 2, np.empty(4))
    with pytest.raises(ValueError, match="must be"):
        kernels.normal_equations(design, y[:, :9], weights)
    with pytest.raises(ValueError, match="coef has shape"):
        kernels.residual_squares(design, y, weights, np.empty((4, 2, 2)))


# Hostile arguments straight to the compiled module: shapes that lie, indices out of range,
# sizes that overflow. Each is refused with a ValueError, never a read past a buffer.


def _grid_arguments(n: int = 50):
    grid = PointGrid(_surface_cloud(n, seed=8), 2 * MM)
    return [
        grid.points,
        grid.order,
        grid.cell_keys,
        grid.cell_starts,
        grid.origin,
        grid.cell_m,
        grid.dims,
    ]


def _nearest(arguments, queries, k=4, radius=2 * MM, distance=None, index=None, n=50):
    distance = np.empty((len(queries), k)) if distance is None else distance
    index = np.empty((len(queries), k), np.int64) if index is None else index
    kernels.compiled().grid_nearest(*arguments, queries, k, radius, distance, index, n)
    return distance, index


def test_the_kernels_refuse_buffers_whose_shapes_lie():
    arguments = _grid_arguments()
    queries = np.zeros((3, 3))
    with pytest.raises(ValueError, match="out_distance"):
        _nearest(arguments, queries, distance=np.empty((2, 4)))
    with pytest.raises(ValueError, match="order"):
        _nearest([arguments[0], arguments[1][:-1], *arguments[2:]], queries)
    with pytest.raises(ValueError, match="queries"):
        _nearest(
            arguments, np.zeros(7), distance=np.empty((2, 4)), index=np.empty((2, 4), np.int64)
        )
    with pytest.raises(ValueError, match="k must be"):
        _nearest(arguments, queries, k=2**62, distance=np.empty(1), index=np.empty(1, np.int64))
    with pytest.raises(ValueError, match="k must be"):
        _nearest(arguments, queries, k=0)


def test_the_kernels_refuse_a_grid_that_does_not_hold_together():
    points, order, keys, starts, origin, cell, dims = _grid_arguments()
    queries = np.zeros((2, 3))
    bad_starts = starts.copy()
    bad_starts[1] = 10**9
    with pytest.raises(ValueError, match="cell_keys must increase|cell_starts"):
        _nearest([points, order, keys, bad_starts, origin, cell, dims], queries)
    bad_keys = keys[::-1].copy()
    with pytest.raises(ValueError, match="cell_keys must increase"):
        _nearest([points, order, bad_keys, starts, origin, cell, dims], queries)
    with pytest.raises(ValueError, match="grid dimension"):
        _nearest([points, order, keys, starts, origin, cell, np.array([1, 1, 2**40])], queries)
    with pytest.raises(ValueError, match="1024 cells"):
        _nearest([points, order, keys, starts, origin, cell, dims], queries, radius=1e6)
    for radius in (np.nan, np.inf, -1.0):
        with pytest.raises(ValueError, match="radius"):
            _nearest([points, order, keys, starts, origin, cell, dims], queries, radius=radius)
    bad_order = order.copy()
    bad_order[0] = 10**12
    with pytest.raises(ValueError, match="order must hold"):
        kernels.compiled().grid_ball_sums(
            points, bad_order, keys, starts, origin, cell, dims, queries, 4, 0.002,
            np.zeros((len(points), 9)), 9, np.empty((2, 9)), np.empty(2, np.int64),
        )  # fmt: skip


def test_the_sparse_sums_refuse_indices_out_of_range():
    columns = np.ones((3, 2))
    matrix = csr_matrix((np.ones(2), np.array([0, 2]), np.array([0, 1, 2])), shape=(2, 3))
    out = np.empty((2, 2))
    module = kernels.compiled()
    with pytest.raises(ValueError, match="out of range"):
        module.csr_row_sums(np.array([0, 1, 2]), np.array([0, 7], np.int32), columns, 2, out)
    with pytest.raises(ValueError, match="out of range"):
        module.csr_row_sums(np.array([0, 5, 2]), np.array([0, 2], np.int32), columns, 2, out)
    with pytest.raises(ValueError, match="columns"):
        module.csr_row_sums(np.array([0, 1, 2]), np.array([0, 2], np.int32), columns, 4, out)
    np.testing.assert_array_equal(csr_row_sums(matrix, columns), [[1.0, 1.0], [1.0, 1.0]])


def test_the_hough_kernel_refuses_a_grid_that_overflows():
    module = kernels.compiled()
    small = np.zeros(4)
    with pytest.raises(ValueError, match="too large|shape says"):
        module.hough_votes(
            small, small, small, np.zeros(4, np.uint8), 2, 2, np.ones(30), np.ones(30),
            0.1, 1, 0.012, 0.0005, 2**61, np.empty(1),
        )  # fmt: skip
    with pytest.raises(ValueError, match="x holds"):
        module.hough_votes(
            small, small, small, np.zeros(4, np.uint8), 3, 2, np.ones(30), np.ones(30),
            0.1, 1, 0.012, 0.0005, 50, np.empty(3 * 30 * 50),
        )  # fmt: skip
    with pytest.raises(ValueError, match="Hough grid"):
        module.hough_votes(
            small, small, small, np.zeros(4, np.uint8), 2, 2, np.ones(30), np.ones(30),
            0.1, 1, 0.012, 0.0005, 1, np.empty(2 * 30),
        )  # fmt: skip


def test_the_references_run_when_selected(reference_only):
    """With TEACHPATH_KERNELS=numpy nothing touches the compiled module."""
    points = _surface_cloud(2_000, seed=9)
    distance, index = nearest_within(points, points[:10], k=5, radius_m=3 * MM)
    tree_distance, tree_index = cKDTree(points).query(points[:10], k=5, distance_upper_bound=3 * MM)
    np.testing.assert_array_equal(distance, tree_distance)
    np.testing.assert_array_equal(index, tree_index)
    with pytest.raises(RuntimeError, match="not available"):
        PointGrid(points, 0.003).nearest(points[:2], k=1, radius_m=0.003)


def _voxel_grid(points: np.ndarray, voxel_m: float):
    origin = points.min(axis=0)
    scale = 1.0 / voxel_m
    cells = ((points - origin) * scale).astype(np.int64)
    dims = cells.max(axis=0) + 1
    return origin, scale, dims, (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]


@pytest.mark.parametrize("voxel_m", [0.5 * MM, 2 * MM, 10 * MM, 1.0])
def test_voxel_centres_are_the_references_to_the_bit(voxel_m):
    points = _surface_cloud(40_000, seed=10)
    points[:500] = points[500:1000]  # repeated points: equally near their centre
    origin, scale, dims, keys = _voxel_grid(points, voxel_m)
    kept, resolution = kernels.nearest_to_voxel_centres(points, origin, scale, dims)
    ref_kept, ref_resolution = kernels.nearest_to_voxel_centres_reference(
        points, origin, scale, dims
    )
    np.testing.assert_array_equal(kept, ref_kept)
    assert resolution == ref_resolution
    # One point per voxel, each the nearest of its voxel to the centre, none missing.
    assert len(np.unique(keys[kept])) == len(kept) == len(np.unique(keys))
    assert np.all(np.diff(keys[kept]) > 0)
    assert resolution <= np.sqrt(3) * voxel_m
    # Of the repeated points, the smaller index is the one kept.
    assert not np.isin(kept, np.arange(500, 1000)[np.isin(np.arange(500), kept)]).any()


def test_voxel_centres_of_one_point_and_of_points_in_one_voxel():
    one = np.array([[0.1, 0.2, 0.3]])
    assert kernels.nearest_to_voxel_centres(one, one[0], 500.0, np.ones(3, np.int64)) == (
        [0],
        0.0,
    )
    same = np.repeat(one, 7, axis=0)
    kept, resolution = kernels.nearest_to_voxel_centres(same, one[0], 500.0, np.ones(3, np.int64))
    np.testing.assert_array_equal(kept, [0])
    assert resolution == 0.0


def test_the_voxel_kernel_refuses_points_outside_its_grid_and_shapes_that_lie():
    points = _surface_cloud(10, seed=11)
    origin, scale, dims, _ = _voxel_grid(points, 2 * MM)
    module = kernels.compiled()
    out = np.empty(10, np.int64)
    with pytest.raises(ValueError, match="outside the voxel grid"):
        module.voxel_nearest_centre(points, origin + 1.0, scale, dims, out)  # below the origin
    with pytest.raises(ValueError, match="outside the voxel grid"):
        module.voxel_nearest_centre(points, origin, scale, np.ones(3, np.int64), out)
    nan = points.copy()
    nan[4, 1] = np.nan
    with pytest.raises(ValueError, match="point 4 lies outside"):
        module.voxel_nearest_centre(nan, origin, scale, dims, out)
    with pytest.raises(ValueError, match="out_kept holds"):
        module.voxel_nearest_centre(points, origin, scale, dims, np.empty(5, np.int64))
    with pytest.raises(ValueError, match="points holds"):
        module.voxel_nearest_centre(points.ravel()[:-1], origin, scale, dims, out)
    with pytest.raises(ValueError, match="dims holds"):
        module.voxel_nearest_centre(points, origin, scale, dims[:2], out)
    with pytest.raises(ValueError, match="at least 1"):
        module.voxel_nearest_centre(points, origin, scale, np.array([0, 5, 5]), out)
    with pytest.raises(ValueError, match="too many"):
        module.voxel_nearest_centre(points, origin, scale, np.full(3, 2**21), out)
    with pytest.raises(ValueError, match="scale"):
        module.voxel_nearest_centre(points, origin, np.nan, dims, out)


def test_a_scan_too_wide_for_its_voxels_is_refused_before_any_cast():
    from recon.collision import Cell

    with pytest.raises(ValueError, match="too many"):
        Cell(scan_points_m=np.array([[0.0, 0.0, 0.1], [1e300, 1e300, 1e300]]))
    with pytest.raises(ValueError, match="millimetres"):
        Cell(scan_points_m=np.array([[0.0, 0.0, 0.1], [4e6, 4e6, 4e6]]), voxel_m=0.002)


def test_a_forked_process_runs_the_threaded_kernels():
    """The kernels' thread pool does not survive a fork; a forked child makes its own rather
    than waiting forever on threads it does not have."""
    import multiprocessing

    points = _surface_cloud(20_000, seed=12)
    expected = nearest_within(points, points, k=8, radius_m=3 * MM)  # the parent's pool starts
    with multiprocessing.get_context("fork").Pool(1) as pool:
        distance, index = pool.apply_async(
            nearest_within, (points, points), {"k": 8, "radius_m": 3 * MM}
        ).get(timeout=120)
    np.testing.assert_array_equal(distance, expected[0])
    np.testing.assert_array_equal(index, expected[1])


@pytest.mark.parametrize("columns", [None, 1, 3, 7])
def test_gathered_rows_are_numpys_to_the_bit(columns, monkeypatch):
    """recon.fitting.gather through the kernel and through numpy's indexing: the same copy,
    padding (the fill index) as zeros, for the shapes the callers use."""
    from recon.fitting import gather

    rng = np.random.default_rng(11)
    shape = (500,) if columns is None else (500, columns)
    values = rng.normal(size=shape)
    index = rng.integers(0, 501, size=(40, 33))  # 500 is the fill index
    index[:, -5:] = 500
    assert kernels.gather_rows(values, index, 500) is not None
    compiled = gather(values, index, fill_index=500)
    monkeypatch.setenv(KERNELS_ENV, "numpy")
    assert kernels.gather_rows(values, index, 500) is None
    reference = gather(values, index, fill_index=500)
    assert compiled.shape == reference.shape == (40, 33, *shape[1:])
    np.testing.assert_array_equal(compiled, reference)
    assert not np.any(compiled[:, -5:])


def test_gathered_rows_leave_other_types_to_numpy():
    """Integer or boolean values (corner labels), empty tables: the numpy path, as before."""
    from recon.fitting import gather

    labels = np.array([3, -1, 7])
    assert kernels.gather_rows(labels, np.array([0, 3]), 3) is None
    np.testing.assert_array_equal(gather(labels, np.array([[0, 3, 2]]), fill_index=3), [[3, 0, 7]])
    assert kernels.gather_rows(np.zeros((0, 3)), np.array([0]), 0) is None
    np.testing.assert_array_equal(gather(np.zeros((0, 3)), np.array([[0]]), fill_index=0), 0.0)


def test_the_gather_kernel_refuses_indices_out_of_range_and_lying_shapes():
    module = kernels.compiled()
    values = np.ones((4, 3))
    out = np.empty((2, 3))
    with pytest.raises(ValueError, match="outside"):
        module.gather_rows(values, 4, 3, np.array([0, 9]), 4, out)
    with pytest.raises(ValueError, match="outside"):
        module.gather_rows(values, 4, 3, np.array([-1, 0]), 4, out)
    with pytest.raises(ValueError, match="values holds"):
        module.gather_rows(values, 5, 3, np.array([0, 1]), 5, out)
    with pytest.raises(ValueError, match="out holds"):
        module.gather_rows(values, 4, 3, np.array([0, 1, 2]), 4, out)
    with pytest.raises(ValueError, match="c in"):
        module.gather_rows(values, 4, 2**40, np.array([0, 1]), 4, out)
    # Through recon.fitting.gather a bad index is an error too, never a read past the table.
    from recon.fitting import gather

    with pytest.raises(ValueError, match="outside"):
        gather(values, np.array([[0, 7]]), fill_index=4)


def test_the_reference_search_reuses_a_callers_tree(reference_only):
    """nearest_within with the caller's tree (find_profiles passes the scan model's) answers as
    with the tree it would build."""
    points = _surface_cloud(3_000, seed=12)
    queries = points[::50] + 0.3 * MM
    own = nearest_within(points, queries, k=7, radius_m=2 * MM)
    given = nearest_within(points, queries, k=7, radius_m=2 * MM, tree=cKDTree(points))
    for a, b in zip(own, given, strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.isfinite(own[0]).any() and own[1].dtype == np.int64
