"""Surface structure of the scan near the path: crop, clean, normals, curvature, edge flags.

Curvature needs a scale. Surface variation ``l3 / (l1 + l2 + l3)`` of the local covariance is
computed in a fixed-radius ball on a cloud first averaged down to a voxel grid; with a fixed
number of nearest neighbours on a dense cloud the ball shrinks to the noise and nearly every point
looks like an edge.

The band of points flagged as edges is as wide as the curvature ball and its centroid lies inside
the corner, not on it: :mod:`recon.edge_lines` recovers the edge itself from the two faces, and
:mod:`recon.edges` thins the band to points on it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from recon.arrays import FloatArray
from recon.errors import NoOverlapError
from recon.fitting import symmetric_eig3
from recon.kernels import PointGrid, compiled, csr_row_sums, nearest_within

if TYPE_CHECKING:
    from scipy.sparse import csr_matrix

#: Surface variation never flags an edge below this: a noise-free plane has 0 and a 90-degree
#: edge about 0.1 at its crest (measured on the synthetic scenes of recon.scenes).
EDGE_CURVATURE_FLOOR = 0.03


@dataclass(frozen=True)
class ScanFeatures:
    """The processed part of a scan near the path.

    Attributes
    ----------
    points_m : ndarray of shape (M, 3), metres
        The cropped scan averaged down to the voxel grid, outliers removed: the cloud the
        normals, curvature and edge flags belong to.
    dense_points_m : ndarray of shape (D, 3), metres
        The cropped scan at full resolution (capped in density), for the fits that locate edges
        and surfaces: averaging into voxels does not reduce noise comparable to the voxel size,
        so precision comes from fitting many raw points.
    normals : ndarray of shape (M, 3)
        Unit normals from the local covariance (sign arbitrary).
    curvature : ndarray of shape (M,)
        Surface variation in [0, 1/3].
    is_edge : ndarray of shape (M,), bool
    edge_threshold : float
        The surface variation that separated edges from faces.
    n_input, n_cropped, n_outliers : int
        Points in the whole scan, near the path, and removed as outliers.
    """

    points_m: FloatArray
    dense_points_m: FloatArray
    normals: FloatArray
    curvature: FloatArray
    is_edge: NDArray[np.bool_]
    edge_threshold: float
    n_input: int
    n_cropped: int
    n_outliers: int


def crop_near(points_m: FloatArray, path_m: FloatArray, radius_m: float) -> NDArray[np.bool_]:
    """Mask of ``points_m`` near ``path_m``: within ``radius_m``, give or take half of it.

    Points are kept whose cell (edge ``radius_m / 2``) lies within two cells of a cell the path
    passes through. That keeps everything within ``radius_m`` and nothing beyond about
    ``1.9 radius_m``, without a distance computation per scan point, which keeps a 1M-point
    scan cheap (the crop only bounds the work; the fits select their own neighbours).

    Parameters
    ----------
    points_m : ndarray of shape (M, 3)
    path_m : ndarray of shape (N, 3)
    radius_m : float

    Returns
    -------
    ndarray of shape (M,), bool
    """
    cell = radius_m / 2.0
    lo = path_m.min(axis=0) - radius_m
    hi = path_m.max(axis=0) + radius_m
    in_box = np.all((points_m >= lo) & (points_m <= hi), axis=1)
    box_idx = np.flatnonzero(in_box)
    mask = np.zeros(len(points_m), dtype=bool)
    if len(box_idx) == 0:
        return mask
    dims = np.floor((hi - lo) / cell).astype(np.int64) + 5

    def key(cells: NDArray[np.int64]) -> NDArray[np.int64]:
        keys: NDArray[np.int64] = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
        return keys

    path_cells = np.unique(np.floor((path_m - lo) / cell).astype(np.int64) + 2, axis=0)
    offsets = np.stack(np.meshgrid(*[np.arange(-2, 3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    near_cells = np.unique(key((path_cells[:, None, :] + offsets[None]).reshape(-1, 3)))
    cand_cells = np.floor((points_m[box_idx] - lo) / cell).astype(np.int64) + 2
    mask[box_idx[np.isin(key(cand_cells), near_cells)]] = True
    return mask


class _NearPath:
    """Which points lie strictly within ``radius_m`` of a path's points: through the compiled
    grid (a third of the k-d tree's time on a dense cloud), or the tree where the kernels are
    off; the same points either way (:func:`recon.kernels.nearest_within`)."""

    def __init__(self, path_m: FloatArray, radius_m: float) -> None:
        self.path_m, self.radius_m = path_m, radius_m
        self.grid = PointGrid(path_m, radius_m) if compiled() is not None else None
        self.tree = cKDTree(path_m) if compiled() is None else None

    def __call__(self, points_m: FloatArray) -> NDArray[np.bool_]:
        """Mask of shape (N,) for points of shape (N, 3)."""
        dist, _ = nearest_within(
            self.path_m, points_m, k=1, radius_m=self.radius_m, grid=self.grid, tree=self.tree
        )
        near: NDArray[np.bool_] = np.isfinite(dist[:, 0])
        return near


def voxel_average(points_m: FloatArray, voxel_m: float) -> tuple[FloatArray, int]:
    """The points averaged per cell of a ``voxel_m`` grid (Open3D's ``voxel_down_sample``).

    The grid starts half a voxel below the points' minimum, as Open3D's does; the cells come out
    in the order of their grid keys, so the result does not depend on the points' order.

    Parameters
    ----------
    points_m : ndarray of shape (M, 3)
    voxel_m : float
        Cell edge; 0 or less returns the points as they are.

    Returns
    -------
    centroids_m : ndarray of shape (V, 3)
        The mean of the points in each occupied cell.
    n_voxels : int
        V.
    """
    points_m = np.asarray(points_m, dtype=np.float64)
    if voxel_m <= 0 or len(points_m) == 0:
        return points_m, len(points_m)
    origin = points_m.min(axis=0) - 0.5 * voxel_m
    cells = np.floor((points_m - origin) / voxel_m).astype(np.int64)
    dims = cells.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0**62:
        key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    else:  # a grid too large for one integer key (kilometres in millimetre voxels): rows
        _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
    sums = np.column_stack(
        [np.bincount(inverse, weights=points_m[:, k], minlength=len(counts)) for k in range(3)]
    )
    return sums / counts[:, None], len(counts)


#: Points whose neighbour lists are searched at once (bounds the (chunk, k) distance arrays).
NEIGHBOUR_CHUNK = 65_536
#: The six distinct products of a point's coordinates, as (row, column) of the 3x3 moment.
_PRODUCTS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def neighbour_balls(
    points_m: FloatArray,
    tree: cKDTree,
    *,
    radius_m: float,
    max_neighbours: int = 48,
    rows: np.ndarray | None = None,
) -> csr_matrix:
    """Each point's ball: its nearest ``max_neighbours`` points within ``radius_m`` (a hybrid
    search, as Open3D's ``estimate_covariances``), itself included.

    A face of 2 mm voxels has 50-70 points in an 8 mm ball (50 on a face along the grid, more on
    a tilted one; a median of 70 on the timing scene), so the cap of 48 truncates the ball to
    its nearest part; the cost grows with the cap.

    Parameters
    ----------
    points_m : ndarray of shape (M, 3)
    tree : cKDTree
        Over ``points_m``.
    radius_m : float
    max_neighbours : int
    rows : ndarray of shape (S,), int, optional
        Only these points' balls (their rows of the matrix; the others empty), increasing.

    Returns
    -------
    scipy.sparse.csr_matrix of shape (M, M)
        Row i holds a 1 in the column of each point of i's ball.
    """
    from scipy.sparse import csr_matrix  # loaded with scipy.spatial already

    m = len(points_m)
    k = min(max_neighbours, m)
    wanted = np.arange(m) if rows is None else np.asarray(rows, dtype=np.int64)
    # The compiled grid search where it is built (the same balls, recon.kernels), else the tree.
    grid = PointGrid(points_m, radius_m) if compiled() is not None and m else None
    counts, columns = [], []
    for start in range(0, len(wanted), NEIGHBOUR_CHUNK):
        query = points_m[wanted[start : start + NEIGHBOUR_CHUNK]]
        if grid is not None:
            distance, index = grid.nearest(query, k=k, radius_m=radius_m)
        else:
            distance, index = tree.query(query, k=k, distance_upper_bound=radius_m, workers=-1)
        inside = np.isfinite(distance.reshape(len(query), k))
        counts.append(inside.sum(axis=1))
        columns.append(index.reshape(len(query), k)[inside].astype(np.int32))
    per_row = np.zeros(m, np.int64)
    if counts:
        per_row[wanted] = np.concatenate(counts)
    row_starts = np.concatenate(([0], np.cumsum(per_row)))
    if rows is not None and len(wanted) and np.any(np.diff(wanted) <= 0):
        raise ValueError("rows must be increasing")
    index = np.concatenate(columns) if columns else np.zeros(0, np.int32)
    return csr_matrix((np.ones(len(index)), index, row_starts), shape=(m, m))


def statistical_inliers(
    points_m: FloatArray, tree: cKDTree, *, neighbours: int, std_ratio: float
) -> NDArray[np.bool_]:
    """Mask of the points that are not statistical outliers (Open3D's rule).

    A point's spread is its mean distance to its ``neighbours`` nearest points (itself among
    them, as in Open3D); it is an outlier when that exceeds the mean spread over the cloud by
    ``std_ratio`` standard deviations.

    Parameters
    ----------
    points_m : ndarray of shape (M, 3)
    tree : cKDTree
        Over ``points_m``.
    neighbours : int
    std_ratio : float

    Returns
    -------
    ndarray of shape (M,), bool
    """
    if len(points_m) <= neighbours:
        return np.ones(len(points_m), dtype=bool)
    distance, _ = tree.query(points_m, k=neighbours, workers=-1)
    spread = distance.mean(axis=1)
    inliers: NDArray[np.bool_] = spread < spread.mean() + std_ratio * spread.std(ddof=1)
    return inliers


def ball_moments(
    points_m: FloatArray,
    tree: cKDTree | None,
    *,
    radius_m: float,
    max_neighbours: int = 48,
    rows: np.ndarray | None = None,
) -> tuple[FloatArray, np.ndarray]:
    """The covariance of the balls of :func:`neighbour_balls`, of all points or of ``rows``.

    With the compiled kernels (:mod:`recon.kernels`) the balls are summed as they are found,
    without the sparse matrix; the numbers are the same to the bit as the matrix's.

    Parameters
    ----------
    points_m : ndarray of shape (M, 3)
    tree : cKDTree or None
        Over ``points_m``, for the numpy reference (built here when None and needed).
    radius_m, max_neighbours :
        As for :func:`neighbour_balls`.
    rows : ndarray of shape (S,), int, optional
        Only these points' balls, increasing.

    Returns
    -------
    covariances : ndarray of shape (S, 3, 3)
        S is M without ``rows``.
    counts : ndarray of shape (S,), int
    """
    points_m = np.asarray(points_m, dtype=np.float64)
    m = len(points_m)
    wanted = np.arange(m) if rows is None else np.asarray(rows, dtype=np.int64)
    if rows is not None and len(wanted) and np.any(np.diff(wanted) <= 0):
        raise ValueError("rows must be increasing")
    if compiled() is None or m == 0:
        balls = neighbour_balls(
            points_m,
            tree if tree is not None else cKDTree(points_m),
            radius_m=radius_m,
            max_neighbours=max_neighbours,
            rows=rows,
        )
        covariances, counts = ball_covariances(points_m, balls)
        return covariances[wanted], counts[wanted]
    columns = _moment_columns(points_m)
    grid = PointGrid(points_m, radius_m)
    sums = np.empty((len(wanted), columns.shape[1]))
    counts = np.empty(len(wanted), np.int64)
    for start in range(0, len(wanted), NEIGHBOUR_CHUNK):
        part = slice(start, start + NEIGHBOUR_CHUNK)
        sums[part], counts[part] = grid.ball_sums(
            points_m[wanted[part]], columns, k=min(max_neighbours, m), radius_m=radius_m
        )
    return _covariances_from_sums(sums, counts), counts


def _moment_columns(points_m: FloatArray) -> FloatArray:
    """The coordinates and their products whose ball sums give the balls' moments (M, 9)."""
    m = len(points_m)
    # Coordinates about the cloud's centre keep E[p p^T] - E[p] E[p]^T precise: the cloud spans
    # a metre at most and the smallest variance is about (0.1 mm)^2, far above the cancellation.
    centred = points_m - points_m.mean(axis=0) if m else points_m
    columns: FloatArray = np.column_stack(
        [centred] + [centred[:, i] * centred[:, j] for i, j in _PRODUCTS]
    )
    return columns


def _covariances_from_sums(sums: FloatArray, counts: np.ndarray) -> FloatArray:
    """Covariances (S, 3, 3) from the ball sums of :func:`_moment_columns` and the counts."""
    n = np.maximum(counts, 1)[:, None]
    mean, second = sums[:, :3] / n, sums[:, 3:] / n
    covariances = np.empty((len(sums), 3, 3))
    for c, (i, j) in enumerate(_PRODUCTS):
        covariances[:, i, j] = covariances[:, j, i] = second[:, c] - mean[:, i] * mean[:, j]
    return covariances


def ball_covariances(points_m: FloatArray, balls: csr_matrix) -> tuple[FloatArray, np.ndarray]:
    """The covariance of each point's ball (see :func:`covariance_features`).

    Returns
    -------
    covariances : ndarray of shape (M, 3, 3)
    counts : ndarray of shape (M,), int
        Points in each ball.
    """
    points_m = np.asarray(points_m, dtype=np.float64)
    balls = balls.tocsr()
    sums = csr_row_sums(balls, _moment_columns(points_m))
    counts = np.diff(balls.indptr)
    return _covariances_from_sums(sums, counts), counts


def covariance_features(points_m: FloatArray, balls: csr_matrix) -> tuple[FloatArray, FloatArray]:
    """Normals and surface variation from the covariance of each point's ball.

    The balls' first and second moments are the sparse ball matrix times the points'
    coordinates and their products: scipy sums them without gathering a (M, K, 3) array. On
    150k points: 0.2 s here after the 0.5 s neighbour search, where gathering the neighbours
    and summing them took 1.0 s after it (and Open3D 0.8 s for search and sums together).

    Parameters
    ----------
    points_m : ndarray of shape (M, 3)
    balls : scipy.sparse.csr_matrix of shape (M, M)
        Row i marks the points of i's ball (:func:`neighbour_balls`).

    Returns
    -------
    normals : ndarray of shape (M, 3)
    curvature : ndarray of shape (M,)
        ``l3 / (l1 + l2 + l3)``; 1/3 (isotropic, i.e. no surface) where a ball holds < 3 points
        (whose normal is then arbitrary, as Open3D's is).
    """
    return normals_and_curvature(*ball_covariances(points_m, balls))


def normals_and_curvature(
    covariances: FloatArray, counts: np.ndarray
) -> tuple[FloatArray, FloatArray]:
    """Normals and surface variation of balls from their covariances (S, 3, 3) and sizes (S,)
    (see :func:`covariance_features`)."""
    values, normals = symmetric_eig3(covariances)
    total = values.sum(axis=1)
    surface = (counts >= 3) & (total > 0)
    curvature = np.where(surface, values[:, 0] / np.where(surface, total, 1.0), 1.0 / 3.0)
    return normals, np.clip(curvature, 0.0, 1.0 / 3.0)


def edge_threshold(curvature: FloatArray) -> float:
    """Surface variation above which a point counts as an edge point.

    Halfway between the face level (20th percentile: faces dominate any crop) and the crest
    level (98th percentile), and at least :data:`EDGE_CURVATURE_FLOOR`. A histogram split such as
    Otsu's needs two clear modes, which a noisy scan does not have: at 1 mm of noise faces
    read 0.04-0.08 and the crest of a right-angle edge 0.12, and Otsu's threshold fell on the
    crest itself, flagging a band too narrow for a path a few millimetres off to touch. A generous
    band costs little: the edge-line fits reject points that are not between two faces.

    Parameters
    ----------
    curvature : ndarray of shape (M,)

    Returns
    -------
    float
    """
    face, crest = np.percentile(np.asarray(curvature, dtype=np.float64), [20, 98])
    return float(max(EDGE_CURVATURE_FLOOR, 0.5 * (face + crest)))


def _thin_randomly(
    points_m: FloatArray, *, n_voxels: int, voxel_m: float, spacing_m: float, seed: int
) -> FloatArray:
    """Random subset of ``points_m`` with about one point per ``spacing_m`` squared of surface.

    The surface area is estimated from the number of occupied voxels (each holds about
    ``voxel_m`` squared of surface).
    """
    if voxel_m <= 0:
        return points_m
    area_m2 = n_voxels * voxel_m**2
    cap = int(area_m2 / spacing_m**2)
    if len(points_m) <= cap:
        return points_m
    rng = np.random.default_rng(seed)
    return points_m[np.sort(rng.choice(len(points_m), size=cap, replace=False))]


def prepare_scan(
    scan_points_m: FloatArray,
    path_m: FloatArray,
    *,
    crop_margin_m: float,
    voxel_m: float,
    curvature_radius_m: float,
    edge_curvature: float | None = None,
    dense_spacing_m: float = 0.001,
    outlier_neighbours: int = 8,
    outlier_std_ratio: float = 3.0,
    seed: int = 0,
) -> ScanFeatures:
    """Crop the scan to the path's neighbourhood, clean it and compute its structure.

    Parameters
    ----------
    scan_points_m : ndarray of shape (M, 3)
        The scan, in any frame.
    path_m : ndarray of shape (N, 3)
        The path, in the same frame (a rough alignment is enough: crop_margin_m covers the rest).
    crop_margin_m : float
        Points farther than this from the path are dropped before any other work.
    voxel_m : float
        Voxel edge for averaging the cropped cloud down (0: no averaging).
    curvature_radius_m : float
        Ball radius for normals and curvature.
    edge_curvature : float, optional
        Fixed edge threshold; default :func:`edge_threshold`.
    dense_spacing_m : float
        Typical spacing the dense cloud is randomly thinned to when the scan is denser (it
        bounds the cost of the fits on very dense scans; random, not averaged, keeps the noise
        unbiased).
    outlier_neighbours, outlier_std_ratio :
        Statistical outlier removal on the voxel cloud (Open3D's rule): a point whose mean
        distance to its neighbours is more than this many standard deviations above the average
        is dropped.
        (The fits on the dense cloud reject outliers themselves.)
    seed : int
        Seed of the random thinning of the dense cloud, for reproducible results.

    Returns
    -------
    ScanFeatures

    Raises
    ------
    NoOverlapError
        Fewer than 20 scan points lie within ``crop_margin_m`` of the path.
    """
    near = crop_near(scan_points_m, path_m, crop_margin_m)
    n_cropped = int(np.count_nonzero(near))
    if n_cropped < 20:
        raise NoOverlapError(
            f"only {n_cropped} scan points lie within {crop_margin_m * 1000:.0f} mm of the path: "
            "check that path and scan are in the same frame and units, or give an initial "
            "calibration (T_scan_tracker) that brings them together"
        )
    cropped = scan_points_m[near]
    coarse, _ = voxel_average(cropped, voxel_m)
    # The cheap crop keeps a superset that depends on the axes; the statistics below (outlier
    # removal, the edge threshold's percentiles) must not, so the voxel cloud is cut exactly.
    near_path = _NearPath(path_m, crop_margin_m)
    coarse = coarse[near_path(coarse)]
    n_before = len(coarse)
    tree = cKDTree(coarse)
    inliers = statistical_inliers(
        coarse, tree, neighbours=outlier_neighbours, std_ratio=outlier_std_ratio
    )
    points = coarse[inliers]
    if not np.all(inliers):
        tree = cKDTree(points)
    normals, curvature = normals_and_curvature(
        *ball_moments(points, tree, radius_m=curvature_radius_m)
    )
    threshold = edge_curvature if edge_curvature is not None else edge_threshold(curvature)
    dense = _thin_randomly(
        cropped, n_voxels=n_before, voxel_m=voxel_m, spacing_m=dense_spacing_m, seed=seed
    )
    # The dense cloud cut exactly too: the fits reach out to the margin, and a superset that
    # depends on the axes would make the result depend on them.
    dense = dense[near_path(dense)]
    return ScanFeatures(
        points_m=points,
        dense_points_m=dense,
        normals=normals,
        curvature=curvature,
        is_edge=curvature > threshold,
        edge_threshold=float(threshold),
        n_input=len(scan_points_m),
        n_cropped=n_cropped,
        n_outliers=n_before - len(points),
    )
