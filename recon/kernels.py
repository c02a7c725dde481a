"""The scan model's hot loops, compiled, each beside the numpy reference it must agree with.

The compiled module (``recon._kernels``, from ``recon/_kernels.c``) is built by the install
(``setup.py``; ``make setup`` does it). Each function here runs it when it is there and the
numpy reference otherwise, or always the reference when the environment variable
``TEACHPATH_KERNELS`` is ``numpy`` (what the tests compare against, and a way to rule the kernels
out when a result looks wrong). A missing compiled module is logged once, never an error: the
references give the same results, only slower.

How close each kernel is to its reference (tests/recon/test_kernels.py holds them to it):

- :func:`nearest_within`: the same neighbours at the same distances, to the bit, as
  ``scipy.spatial.cKDTree.query`` with ``distance_upper_bound``; among points at exactly the
  same distance the kernel lists the smaller index first (the tree's order there is its own), so
  the sets can differ only where the k-th and the (k+1)-th neighbour are equally far.
- :func:`csr_row_sums`: scipy's product of a 0/1 CSR matrix with dense columns, to the bit.
- :func:`hough_votes`: :mod:`recon.profiles`' two ``bincount`` calls, to the bit.
- :func:`nearest_to_voxel_centres` (the collision checks' thinned scan): the reference's stable
  sort by voxel and distance to its centre, to the bit (the kernel hashes the voxels instead
  of sorting the points).
- :func:`gather_rows`: numpy's fancy indexing with the padding zeroed, to the bit (a copy).
- :func:`weighted_moments`, :func:`normal_equations`, :func:`residual_squares` (the fits' sums:
  weighted PCA, weighted least squares): the same terms added in row order where numpy's
  matmul adds them in BLAS's, so the same to rounding, not to the bit (about 1e-16 relative;
  a whole reconstruction moved 3e-15 m at most, tests/recon/test_kernels.py holds it within
  1e-12 m with every decision the same). Rows of zero weight are skipped, where numpy adds
  zero times them (NaN for a non-finite one: the callers' padding is zeros).

Why C and not numba (docs/speed.md): a C extension loads in well under a millisecond and is
compiled once at install, where numba added 0.35-0.6 s to every process start and half a minute
of compiling on first use.
"""

from __future__ import annotations

import itertools
import logging
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from recon.arrays import FloatArray

if TYPE_CHECKING:
    from scipy.sparse import csr_matrix
    from scipy.spatial import cKDTree

log = logging.getLogger(__name__)

#: Environment variable choosing the implementation: ``numpy`` for the references; anything
#: else (or unset) for the compiled kernels where they are built.
KERNELS_ENV = "TEACHPATH_KERNELS"
#: A grid never has more cells than this along an axis (the kernel refuses more): a cloud
#: spanning more than this many radii gets coarser cells, slower but still right.
MAX_CELLS_PER_AXIS = 1 << 20
#: How much wider than the radius a grid's cells are (see PointGrid).
CELL_SLACK = 1e-6
#: Queries per thread below which one thread does the whole call (starting threads costs more).
MIN_QUERIES_PER_THREAD = 2048


@cache
def _compiled_module() -> ModuleType | None:
    try:
        from recon import _kernels
    except ImportError as error:  # an install without a C compiler, or a stale build
        log.warning(
            "teachpath's compiled kernels are not built (%s): using the numpy references, "
            "several times slower; reinstall with a C compiler (make setup) to build them",
            error,
        )
        return None
    return _kernels


def compiled() -> ModuleType | None:
    """The compiled kernels, or None when they are not built or ``TEACHPATH_KERNELS=numpy``."""
    if os.environ.get(KERNELS_ENV, "").strip().lower() == "numpy":
        return None
    return _compiled_module()


@cache
def thread_pool() -> ThreadPoolExecutor:
    """The threads the kernels' callers share (one per core): a kernel releases the GIL, and
    so does numpy on the larger arrays, so parts of one stage run side by side."""
    return ThreadPoolExecutor(max_workers=os.cpu_count() or 1, thread_name_prefix="kernels")


# A process forked after the pool started inherits it without its threads: it makes its own.
os.register_at_fork(after_in_child=thread_pool.cache_clear)


def _parts(n: int) -> list[slice]:
    """Slices of ``range(n)`` for the threads (one slice when the work is small)."""
    workers = min(os.cpu_count() or 1, max(1, n // MIN_QUERIES_PER_THREAD))
    edges = np.linspace(0, n, workers + 1).astype(int)
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(edges) if b > a]


def _unsorted(rows: NDArray[Any], by_cell: NDArray[np.intp]) -> NDArray[Any]:
    """Rows computed in grid order, back in the queries' order."""
    out = np.empty_like(rows)
    out[by_cell] = rows
    return out


class PointGrid:
    """Points binned on a uniform grid, for :meth:`nearest` queries of a given radius.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3)
        Finite coordinates.
    cell_m : float
        Edge of a cell: the radius the queries will mostly use (a query reaches as many cells
        either side as its radius needs, up to 1,024; a larger radius is refused).
    """

    def __init__(self, points_m: FloatArray, cell_m: float) -> None:
        points = np.ascontiguousarray(points_m, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(points)):
            raise ValueError("grid points must be finite")
        if not cell_m > 0:
            raise ValueError(f"a grid cell must be positive, not {cell_m}")
        self.n_points = len(points)
        self.origin = points.min(axis=0) if len(points) else np.zeros(3)
        span = (points.max(axis=0) - self.origin) if len(points) else np.zeros(3)
        # A hair wider than asked: the kernel prunes with a reach a hair (1e-9) wider than the
        # radius, and a cell narrower than that reach makes it read two cells either side of the
        # query's instead of one (125 cells, not 27: three times the candidates). Coarser cells
        # where the cloud spans more than the kernel's cells per axis.
        self.cell_m = float(
            max(cell_m * (1.0 + CELL_SLACK), float(span.max()) / (MAX_CELLS_PER_AXIS - 2))
        )
        self.dims = (np.floor(span / self.cell_m).astype(np.int64) + 1).clip(1, MAX_CELLS_PER_AXIS)
        keys = self._keys(points)
        self.order = np.argsort(keys, kind="stable").astype(np.int64)
        self.points = np.ascontiguousarray(points[self.order])
        self.cell_keys, first = np.unique(keys[self.order], return_index=True)
        self.cell_starts = np.append(first, len(points)).astype(np.int64)

    def nearest(
        self, queries_m: FloatArray, *, k: int, radius_m: float
    ) -> tuple[FloatArray, NDArray[np.int64]]:
        """Each query's ``k`` nearest grid points strictly within ``radius_m``, nearest first.

        Parameters
        ----------
        queries_m : ndarray of shape (Q, 3)
        k : int
            At least 1.
        radius_m : float

        Returns
        -------
        distance_m : ndarray of shape (Q, k)
            ``inf`` past the last neighbour found.
        index : ndarray of shape (Q, k), int64
            Into the points the grid was built from; ``N`` past the last neighbour found.
        """
        kernels = compiled()
        if kernels is None:
            raise RuntimeError("the compiled kernels are not available (see compiled())")
        queries = np.asarray(queries_m, dtype=np.float64).reshape(-1, 3)
        q = len(queries)
        if self.n_points == 0:
            return np.full((q, k), np.inf), np.zeros((q, k), np.int64)
        distance, index = np.empty((q, k)), np.empty((q, k), np.int64)

        def run(sorted_queries: FloatArray, part: slice) -> None:
            kernels.grid_nearest(
                *self._grid_arguments(),
                sorted_queries[part],
                k,
                float(radius_m),
                distance[part],
                index[part],
                self.n_points,
            )

        by_cell = self._run_in_grid_order(queries, run)
        return _unsorted(distance, by_cell), _unsorted(index, by_cell)

    def ball_sums(
        self, queries_m: FloatArray, columns: FloatArray, *, k: int, radius_m: float
    ) -> tuple[FloatArray, NDArray[np.int64]]:
        """Sums of ``columns`` over each query's ball (its :meth:`nearest` neighbours), added
        nearest first from zero: ``neighbour_balls(...) @ columns`` without the matrix.

        Parameters
        ----------
        queries_m : ndarray of shape (Q, 3)
        columns : ndarray of shape (N, C)
            One row per grid point (in the order the grid was built from), C at most 64.
        k : int
        radius_m : float

        Returns
        -------
        sums : ndarray of shape (Q, C)
        counts : ndarray of shape (Q,), int64
            Points in each ball.
        """
        kernels = compiled()
        if kernels is None:
            raise RuntimeError("the compiled kernels are not available (see compiled())")
        queries = np.asarray(queries_m, dtype=np.float64).reshape(-1, 3)
        columns = np.ascontiguousarray(columns, dtype=np.float64)
        q, c = len(queries), columns.shape[1]
        if self.n_points == 0:
            return np.zeros((q, c)), np.zeros(q, np.int64)
        sums, counts = np.empty((q, c)), np.empty(q, np.int64)

        def run(sorted_queries: FloatArray, part: slice) -> None:
            kernels.grid_ball_sums(
                *self._grid_arguments(),
                sorted_queries[part],
                k,
                float(radius_m),
                columns,
                c,
                sums[part],
                counts[part],
            )

        by_cell = self._run_in_grid_order(queries, run)
        return _unsorted(sums, by_cell), _unsorted(counts, by_cell)

    def _grid_arguments(self) -> tuple[Any, ...]:
        """The grid as every grid kernel takes it first."""
        return (
            self.points,
            self.order,
            self.cell_keys,
            self.cell_starts,
            self.origin,
            self.cell_m,
            self.dims,
        )

    def _run_in_grid_order(
        self, queries: FloatArray, run: Callable[[FloatArray, slice], None]
    ) -> NDArray[np.intp]:
        """``run(sorted_queries, part)`` over the queries sorted by cell, parts on threads.

        In the grid's order neighbouring queries read the same cells, which stay in the cache
        (twice as fast on a scan's dense cloud as queries in scan order). ``run`` writes rows
        ``part`` of its outputs in that order; the permutation returned puts them back.
        """
        by_cell = np.argsort(self._keys(queries), kind="stable")
        sorted_queries = np.ascontiguousarray(queries[by_cell])
        parts = _parts(len(queries))
        if len(parts) <= 1:
            run(sorted_queries, slice(0, len(queries)))
        else:
            list(thread_pool().map(lambda part: run(sorted_queries, part), parts))
        return by_cell

    def _keys(self, points_m: FloatArray) -> NDArray[np.int64]:
        """The cell key of each point (cells clamped into the grid; for ordering only)."""
        with np.errstate(invalid="ignore"):
            scaled = np.nan_to_num((points_m - self.origin) / self.cell_m, posinf=0, neginf=0)
        cells = np.floor(scaled).clip(0, self.dims - 1).astype(np.int64)
        keys: NDArray[np.int64] = cells[:, 0] + self.dims[0] * (
            cells[:, 1] + self.dims[1] * cells[:, 2]
        )
        return keys


def nearest_within(
    points_m: FloatArray,
    queries_m: FloatArray,
    *,
    k: int,
    radius_m: float,
    grid: PointGrid | None = None,
    tree: cKDTree | None = None,
) -> tuple[FloatArray, NDArray[np.int64]]:
    """Each query's ``k`` nearest points strictly within ``radius_m``, nearest first: what
    ``cKDTree(points_m).query(queries_m, k, distance_upper_bound=radius_m)`` returns (2-D even
    for ``k`` 1).

    Parameters
    ----------
    points_m : ndarray of shape (N, 3)
    queries_m : ndarray of shape (Q, 3)
    k : int
    radius_m : float
    grid : PointGrid, optional
        Built over ``points_m`` (reused across calls); made here when None.
    tree : scipy.spatial.cKDTree, optional
        Over ``points_m``, for the reference (reused across calls); made there when None.

    Returns
    -------
    distance_m : ndarray of shape (Q, k)
        ``inf`` past the last neighbour found.
    index : ndarray of shape (Q, k), int64
        ``N`` past the last neighbour found.
    """
    if k < 1:
        raise ValueError(f"k must be at least 1, not {k}")
    if compiled() is None:
        return nearest_within_reference(points_m, queries_m, k=k, radius_m=radius_m, tree=tree)
    grid = grid if grid is not None else PointGrid(points_m, radius_m)
    return grid.nearest(queries_m, k=k, radius_m=radius_m)


def nearest_within_reference(
    points_m: FloatArray,
    queries_m: FloatArray,
    *,
    k: int,
    radius_m: float,
    tree: cKDTree | None = None,
) -> tuple[FloatArray, NDArray[np.int64]]:
    """:func:`nearest_within` by SciPy's k-d tree (the reference; ``tree`` over ``points_m``
    when the caller has one)."""
    from scipy.spatial import cKDTree

    queries = np.asarray(queries_m, dtype=np.float64).reshape(-1, 3)
    tree = tree if tree is not None else cKDTree(points_m)
    distance, index = tree.query(queries, k=k, distance_upper_bound=radius_m, workers=-1)
    shape = (len(queries), k)
    return distance.reshape(shape), index.astype(np.int64).reshape(shape)


def csr_row_sums(matrix: csr_matrix, columns: FloatArray) -> FloatArray:
    """``matrix @ columns`` for a CSR matrix of ones (each row lists a ball's points).

    Parameters
    ----------
    matrix : scipy.sparse.csr_matrix of shape (R, M)
        Every stored value 1 (the kernel does not read them).
    columns : ndarray of shape (M, C)

    Returns
    -------
    ndarray of shape (R, C)
    """
    kernels = compiled()
    if kernels is None:
        return csr_row_sums_reference(matrix, columns)
    columns = np.ascontiguousarray(columns, dtype=np.float64)
    indptr = np.ascontiguousarray(matrix.indptr, dtype=np.int64)
    indices = np.ascontiguousarray(matrix.indices, dtype=np.int32)
    out = np.empty((matrix.shape[0], columns.shape[1]))
    kernels.csr_row_sums(indptr, indices, columns, columns.shape[1], out)
    return out


def csr_row_sums_reference(matrix: csr_matrix, columns: FloatArray) -> FloatArray:
    """:func:`csr_row_sums` by scipy's sparse product (the reference)."""
    sums: FloatArray = np.asarray(matrix @ columns, dtype=np.float64)
    return sums


def hough_votes(
    x: FloatArray,
    y: FloatArray,
    phi: FloatArray,
    weight: NDArray[np.bool_],
    *,
    n_theta: int,
    half_window: int,
    radius_m: float,
    rho_bin_m: float,
    n_rho: int,
) -> FloatArray:
    """The Hough accumulator of slices' points (:func:`recon.profiles._votes` documents it).

    Parameters
    ----------
    x, y : ndarrays of shape (B, K)
        The points in their slice, metres.
    phi : ndarray of shape (B, K)
        Their normals' angles in [0, pi).
    weight : ndarray of shape (B, K), bool
        The points that vote.
    n_theta : int
        Direction bins over [0, pi).
    half_window : int
        A point votes in its own direction bin and this many either side.
    radius_m, rho_bin_m : float
        Offsets run from ``-radius_m - rho_bin_m`` in bins of ``rho_bin_m``.
    n_rho : int
        Offset bins.

    Returns
    -------
    ndarray of shape (B, n_theta, n_rho)
    """
    kernels = compiled()
    if kernels is None:
        return hough_votes_reference(
            x,
            y,
            phi,
            weight,
            n_theta=n_theta,
            half_window=half_window,
            radius_m=radius_m,
            rho_bin_m=rho_bin_m,
            n_rho=n_rho,
        )
    b, k = x.shape
    step = np.pi / n_theta
    theta = (np.arange(n_theta) + 0.5) * step
    out = np.empty((b, n_theta, n_rho))
    kernels.hough_votes(
        np.ascontiguousarray(x, dtype=np.float64),
        np.ascontiguousarray(y, dtype=np.float64),
        np.ascontiguousarray(phi, dtype=np.float64),
        np.ascontiguousarray(weight, dtype=np.uint8),
        b,
        k,
        np.cos(theta),
        np.sin(theta),
        step,
        half_window,
        radius_m,
        rho_bin_m,
        n_rho,
        out,
    )
    return out


def hough_votes_reference(
    x: FloatArray,
    y: FloatArray,
    phi: FloatArray,
    weight: NDArray[np.bool_],
    *,
    n_theta: int,
    half_window: int,
    radius_m: float,
    rho_bin_m: float,
    n_rho: int,
) -> FloatArray:
    """:func:`hough_votes` in numpy (the reference): each vote shared linearly between the two
    nearest offset bins, summed by two ``bincount`` calls."""
    b, _k = x.shape
    step = np.pi / n_theta
    window = np.arange(-half_window, half_window + 1)
    centre = np.floor(phi / step).astype(np.int64)
    t_bin = np.mod(centre[:, :, None] + window, n_theta)  # (B, K, W)
    theta = (t_bin + 0.5) * step
    rho = x[:, :, None] * np.cos(theta) + y[:, :, None] * np.sin(theta)
    position = (rho + radius_m + rho_bin_m) / rho_bin_m - 0.5
    low = np.floor(position).astype(np.int64)
    frac = position - low
    low = np.clip(low, 0, n_rho - 2)
    w = np.broadcast_to(weight[:, :, None].astype(np.float64), rho.shape)
    flat = ((np.arange(b)[:, None, None] * n_theta + t_bin) * n_rho + low).ravel()
    size = b * n_theta * n_rho
    acc = np.bincount(flat, weights=(w * (1.0 - frac)).ravel(), minlength=size)
    acc += np.bincount(flat + 1, weights=(w * frac).ravel(), minlength=size)
    return acc.astype(np.float64, copy=False).reshape(b, n_theta, n_rho)


def nearest_to_voxel_centres(
    points_m: FloatArray, origin_m: FloatArray, scale_per_m: float, dims: NDArray[np.int64]
) -> tuple[NDArray[np.int64], float]:
    """Of each voxel's points, the one nearest the voxel's centre (the smaller index among
    equals), and how far any point lies from the one kept for its voxel.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3)
    origin_m : ndarray of shape (3,)
        The grid's corner: a point's voxel is the integer part ``c`` of
        ``(p - origin_m) * scale_per_m`` (no coordinate below the origin).
    scale_per_m : float
        Voxels per metre.
    dims : ndarray of shape (3,), int
        Voxels along each axis (every point's ``c`` below them; their product below 2**62). A
        voxel's key is ``(c0 * dims[1] + c1) * dims[2] + c2``.

    Returns
    -------
    kept : ndarray of shape (V,), int64
        Indices of the points kept, in the order of their voxels' keys.
    resolution_m : float
        The largest distance of a point from the point kept for its voxel.
    """
    kernels = compiled()
    if kernels is None:
        return nearest_to_voxel_centres_reference(points_m, origin_m, scale_per_m, dims)
    points = np.ascontiguousarray(points_m, dtype=np.float64)
    kept = np.empty(len(points), np.int64)
    groups, worst2 = kernels.voxel_nearest_centre(
        points,
        np.ascontiguousarray(origin_m, dtype=np.float64),
        scale_per_m,
        np.ascontiguousarray(dims, dtype=np.int64),
        kept,
    )
    return kept[:groups].copy(), float(np.sqrt(worst2))


def nearest_to_voxel_centres_reference(
    points_m: FloatArray, origin_m: FloatArray, scale_per_m: float, dims: NDArray[np.int64]
) -> tuple[NDArray[np.int64], float]:
    """:func:`nearest_to_voxel_centres` in numpy (the reference): a sort by voxel, then by the
    distance to the voxel's centre, stable (the smaller index first among equals)."""
    points = np.asarray(points_m, dtype=np.float64)
    if len(points) == 0:
        return np.zeros(0, np.int64), 0.0
    rel = (points - origin_m) * scale_per_m
    cells = rel.astype(np.int64)  # floor: rel >= 0
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    frac = rel - cells - 0.5
    # Written out rather than as einsum, whose vector path may fuse the multiply and add: the
    # kernel rounds each product and sum as these do.
    to_centre = frac[:, 0] * frac[:, 0] + frac[:, 1] * frac[:, 1] + frac[:, 2] * frac[:, 2]
    order = np.lexsort((to_centre, keys))
    key_sorted = keys[order]
    first = np.flatnonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])
    kept = order[first].astype(np.int64)
    owner = np.repeat(kept, np.diff(np.r_[first, len(order)]))
    d = points[order] - points[owner]
    worst2 = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]).max()
    return kept, float(np.sqrt(worst2))


def gather_rows(values: FloatArray, index: NDArray[np.int64], fill_index: int) -> FloatArray | None:
    """``values[index]`` with the entries equal to ``fill_index`` read as zero rows, in one pass
    (numpy's fancy indexing and the zeroing take three), or None where the kernel does not
    apply (kernels off, ``values`` not float64 or empty, ``index`` not integers): the caller
    then runs :func:`recon.fitting.gather`'s numpy code, the reference.

    Parameters
    ----------
    values : ndarray of shape (M,) or (M, C), float64
    index : ndarray of shape (...), int
        In ``[0, M)`` or equal to ``fill_index``; anything else is a ValueError.
    fill_index : int

    Returns
    -------
    ndarray of shape (*index.shape, *values.shape[1:]), or None
    """
    kernels = compiled()
    if (
        kernels is None
        or values.dtype != np.float64
        or values.ndim not in (1, 2)
        or len(values) == 0
        or not np.issubdtype(np.asarray(index).dtype, np.integer)
    ):
        return None
    rows = np.ascontiguousarray(values).reshape(len(values), -1)
    flat = np.ascontiguousarray(index, dtype=np.int64)
    out = np.empty((*flat.shape, *values.shape[1:]))
    kernels.gather_rows(rows, len(rows), rows.shape[1], flat, int(fill_index), out)
    return out


def weighted_moments(
    points: FloatArray, weights: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray] | None:
    """Each neighbourhood's total weight, weighted mean and weighted covariance about it, in one
    compiled pass per neighbourhood, or None where the kernels are off (the caller then runs
    :func:`recon.fitting.weighted_pca`'s numpy code, the reference).

    Parameters
    ----------
    points : ndarray of shape (B, K, 3)
    weights : ndarray of shape (B, K)

    Returns
    -------
    total : ndarray of shape (B,)
    mean : ndarray of shape (B, 3)
        ``sum w p / total`` (``total`` read as 1 where it is not positive).
    covariance : ndarray of shape (B, 3, 3)
        ``sum w (p - mean)(p - mean)^T`` over the same.
    """
    kernels = compiled()
    if kernels is None:
        return None
    p = np.ascontiguousarray(points, dtype=np.float64)
    w = np.ascontiguousarray(weights, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 3 or w.shape != p.shape[:2]:
        raise ValueError(f"points {p.shape} and weights {w.shape} must be (B, K, 3) and (B, K)")
    b, k = w.shape
    total, mean, covariance = np.empty(b), np.empty((b, 3)), np.empty((b, 3, 3))
    kernels.weighted_moments(p, w, b, k, total, mean, covariance)
    return total, mean, covariance


def normal_equations(
    design: FloatArray, y: FloatArray, weights: FloatArray
) -> tuple[FloatArray, FloatArray] | None:
    """``A^T W A`` and ``A^T W y`` of each problem of a batch in one compiled pass (rows of zero
    weight skipped), or None where the kernels are off (the caller then runs
    :func:`recon.fitting.fit_linear`'s numpy code, the reference).

    Parameters
    ----------
    design : ndarray of shape (B, K, p)
    y : ndarray of shape (B, K, m)
    weights : ndarray of shape (B, K)

    Returns
    -------
    normal : ndarray of shape (B, p, p)
    rhs : ndarray of shape (B, p, m)
    """
    kernels = compiled()
    if kernels is None:
        return None
    a, yy, w, (b, k, p, m) = _least_squares_arrays(design, y, weights)
    normal, rhs = np.empty((b, p, p)), np.empty((b, p, m))
    kernels.normal_equations(a, yy, w, b, k, p, m, normal, rhs)
    return normal, rhs


def residual_squares(
    design: FloatArray, y: FloatArray, weights: FloatArray, coef: FloatArray
) -> FloatArray | None:
    """``sum w |y - A coef|^2`` of each problem of a batch (rows of zero weight skipped), or None
    where the kernels are off.

    Parameters
    ----------
    design, y, weights :
        As for :func:`normal_equations`.
    coef : ndarray of shape (B, p, m)

    Returns
    -------
    ndarray of shape (B,)
    """
    kernels = compiled()
    if kernels is None:
        return None
    a, yy, w, (b, k, p, m) = _least_squares_arrays(design, y, weights)
    c = np.ascontiguousarray(coef, dtype=np.float64)
    if c.shape != (b, p, m):
        raise ValueError(f"coef has shape {c.shape}, the problems say {(b, p, m)}")
    out = np.empty(b)
    kernels.residual_squares(a, yy, w, c, b, k, p, m, out)
    return out


def _least_squares_arrays(
    design: FloatArray, y: FloatArray, weights: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, tuple[int, int, int, int]]:
    """The arrays of a batch of least-squares problems as the kernels take them, and (B, K, p,
    m); a ValueError where the shapes disagree."""
    a = np.ascontiguousarray(design, dtype=np.float64)
    yy = np.ascontiguousarray(y, dtype=np.float64)
    w = np.ascontiguousarray(weights, dtype=np.float64)
    if a.ndim != 3 or yy.ndim != 3 or w.shape != a.shape[:2] or yy.shape[:2] != a.shape[:2]:
        raise ValueError(
            f"design {a.shape}, y {yy.shape} and weights {w.shape} must be (B, K, p), (B, K, m) "
            "and (B, K)"
        )
    b, k, p = a.shape
    return a, yy, w, (b, k, p, yy.shape[2])
