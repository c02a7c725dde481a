"""What the reconstruction methods share: the per-segment result, N_P's frame and path fit,
N_S on an edge, and the chunking that bounds memory.

Every function works on one segment at a time, vectorised over its points in chunks of
:data:`CHUNK` rows (no Python loop per point).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from recon.arrays import FloatArray
from recon.fitting import (
    PCA,
    LinearFit,
    fit_linear,
    gather,
    poly_design,
    weighted_pca,
    window_indices,
)
from recon.results import PointMode, PointReason
from recon.scan_model import ScanModel

#: What a hand trace is off by where nothing but the trace says where the path is, 1 sigma
#: across the path: the paper measured operators' errors at a standard deviation of 0.5-1 mm
#: (Sec. VI; our scenes' traces: 0.9 mm RMS). A local smoother removes the tremor but not the slow
#: drift, which is most of it.
HAND_ERROR_PRIOR_M = 0.8e-3


def prior_variance(prior_variance_m2: FloatArray | None, n: int) -> FloatArray:
    """What only the path decides is off by across it, per point (see :data:`HAND_ERROR_PRIOR_M`;
    the fused demonstrations' variance where given).

    Parameters
    ----------
    prior_variance_m2 : ndarray of shape (n,) or None
    n : int

    Returns
    -------
    ndarray of shape (n,), m^2
    """
    if prior_variance_m2 is None:
        return np.full(n, HAND_ERROR_PRIOR_M**2)
    return np.asarray(prior_variance_m2, dtype=np.float64)


#: Rows processed at once; bounds memory (a chunk holds chunk x K neighbours, and on a dense
#: surface K is hundreds). It is also the unit in which lift-off runs are judged
#: (anchored._explained: a run across a chunk's boundary is judged in two halves), so it is
#: not only a speed setting: 512 rows measured 17.9 s and 0.52 GB against 23.3 s and 1.33 GB
#: on a 10 m serpentine trace over a 1M-point scan (identical outputs there, a scene without
#: lift-offs), but it would cut segments longer than 0.5 m instead of 2 m. Judging lift-offs
#: over the whole segment first is the change that lets the chunks shrink.
CHUNK = 2048
#: Edge points whose direction differs from the path's by more than this are another edge
#: (the other leg of a corner) and are left out of N_S.
EDGE_DIRECTION_TOLERANCE_DEG = 30.0


@dataclass
class SegmentResult:
    """What a method gives for one segment, one row per point (scan frame while it works).

    Attributes
    ----------
    points : ndarray of shape (n, 3), metres
    mode : ndarray of shape (n,), int8
        :class:`recon.results.PointMode` of each point.
    n_path, n_surface : ndarray of shape (n,), int
        Sizes of N_P and N_S.
    residual_path, residual_surface : ndarray of shape (n,), metres
        RMS residuals of the path and scan fits (NaN where there was none).
    alpha : ndarray of shape (n,)
        The path weight used.
    variance_m2 : ndarray of shape (n,), m^2
        Variance of each point's position across the path (both cross-track directions
        together), from the fits, the estimated noise of the path and, where the path alone
        decided, :data:`HAND_ERROR_PRIOR_M` (the registration's share is added by the caller).
    reason : ndarray of shape (n,), int8
        :class:`recon.results.PointReason` of each point.
    """

    points: FloatArray
    mode: NDArray[np.int8]
    n_path: NDArray[np.int64]
    n_surface: NDArray[np.int64]
    residual_path: FloatArray
    residual_surface: FloatArray
    alpha: FloatArray
    variance_m2: FloatArray
    reason: NDArray[np.int8]

    @classmethod
    def unchanged(cls, points: FloatArray) -> SegmentResult:
        """The points passed through as they are (mode UNCHANGED, alpha 1), as uncertain as a
        hand trace is (:data:`HAND_ERROR_PRIOR_M`)."""
        n = len(points)
        return cls(
            points=points.copy(),
            mode=np.full(n, PointMode.UNCHANGED, np.int8),
            n_path=np.zeros(n, np.int64),
            n_surface=np.zeros(n, np.int64),
            residual_path=np.full(n, np.nan),
            residual_surface=np.full(n, np.nan),
            alpha=np.ones(n),
            variance_m2=np.full(n, HAND_ERROR_PRIOR_M**2),
            reason=np.full(n, PointReason.NONE, np.int8),
        )


def path_frame(neighbourhoods: FloatArray) -> PCA:
    """PCA of N_P with C^x pointing along the direction of travel (right-handed frame)."""
    pca = weighted_pca(neighbourhoods)
    axes = pca.axes.copy()
    travel = neighbourhoods[:, -1] - neighbourhoods[:, 0]
    flip = np.einsum("bi,bi->b", axes[:, :, 0], travel) < 0
    axes[flip, :, 0] *= -1
    axes[:, :, 2] = np.cross(axes[:, :, 0], axes[:, :, 1])
    return PCA(mean=pca.mean, axes=axes, variances=pca.variances, weight=pca.weight)


def edge_neighbourhoods(
    centres: FloatArray,
    path_direction: FloatArray,
    model: ScanModel,
    radius_m: float,
    *,
    corners: tuple[int, ...] | None = None,
    max_points: int = 64,
    wider: tuple[FloatArray, NDArray[np.int64]] | None = None,
) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """N_S on an edge: thinned edge points within ``radius_m`` that run along the path.

    Parameters
    ----------
    centres : ndarray of shape (B, 3), metres
        Scan frame.
    path_direction : ndarray of shape (B, 3)
        Unit direction of the path at each centre.
    model : ScanModel
        With a non-empty thinned edge.
    radius_m : float
    corners : tuple of int, optional
        Only the points of these corners (the segment's, see :func:`recon.classify
        .classify_segments`); every edge when not given.
    max_points : int
        At most this many (the nearest).
    wider : (distance, index), optional
        The edge tree's answer to the same centres with at least ``max_points`` neighbours and
        at least ``radius_m`` (nearest first, as :func:`edge_query` returns it): the
        neighbours are read from it rather than queried again. Its first ``max_points``
        columns closer than ``radius_m`` are the same neighbours.

    Returns
    -------
    points : ndarray of shape (B, K, 3)
    weights : ndarray of shape (B, K)
    index : ndarray of shape (B, K), int
        Into ``model.edges``; ``len(model.edges)`` marks padding.
    """
    edges, tree = model.edges, model.edge_tree
    if tree is None:
        raise ValueError("the scan model has no edge points to take N_S from")
    k = min(max_points, len(edges))
    if wider is None:
        dist, idx = edge_query(model, centres, k=k, radius_m=radius_m)
    else:
        dist, idx = wider[0][:, :k], wider[1][:, :k]
        if dist.shape[1] < k:
            raise ValueError(f"the wider query has {dist.shape[1]} neighbours, not {k}")
        outside = ~(dist < radius_m)
        dist = np.where(outside, np.inf, dist)
        idx = np.where(outside, len(edges), idx)
    pts = gather(edges.points_m, idx, fill_index=len(edges))
    dirs = gather(edges.directions, idx, fill_index=len(edges))
    along = np.abs(np.einsum("bki,bi->bk", dirs, path_direction))
    weights = np.isfinite(dist) & (along >= np.cos(np.radians(EDGE_DIRECTION_TOLERANCE_DEG)))
    if corners is not None:
        # Samples of no known corner (a confirmed corner's edge lines, filled in up to it)
        # belong to whichever edge they run along.
        sample_corner = gather(edges.corner_labels(), idx, fill_index=len(edges))
        weights &= np.isin(sample_corner, corners) | (sample_corner == -1)
    return pts, weights.astype(np.float64), idx


def edge_query(
    model: ScanModel, centres: FloatArray, *, k: int, radius_m: float
) -> tuple[FloatArray, NDArray[np.int64]]:
    """The ``k`` nearest thinned edge points within ``radius_m`` of each centre, nearest first.

    Returns
    -------
    distance_m : ndarray of shape (B, k)
        ``inf`` past the last one found.
    index : ndarray of shape (B, k), int
        Into ``model.edges``; ``len(model.edges)`` past the last one found.
    """
    tree = model.edge_tree
    if tree is None:
        raise ValueError("the scan model has no edge points to take N_S from")
    k = min(k, len(model.edges))
    dist, idx = tree.query(centres, k=k, distance_upper_bound=radius_m, workers=-1)
    return dist.reshape(len(centres), k), idx.reshape(len(centres), k).astype(np.int64)


@dataclass(frozen=True)
class PathFit:
    """N_P's principal frame and the polynomial fit of its transverse components, for a chunk.

    Attributes
    ----------
    frame : PCA
        One frame per point (B of them).
    x_i : ndarray of shape (B,), metres
        The points' first principal coordinates.
    design_at : ndarray of shape (B, degree + 1)
        The polynomial basis at ``x_i``.
    fit : LinearFit
    """

    frame: PCA
    x_i: FloatArray
    design_at: FloatArray
    fit: LinearFit


def path_fit(
    points: FloatArray,
    windows: NDArray[np.int64],
    rows: slice,
    *,
    degree: int,
    scale: float,
    outputs: int,
) -> PathFit:
    """N_P's principal frame and a polynomial fit of its transverse components.

    Parameters
    ----------
    points : ndarray of shape (n, 3), metres
        The segment.
    windows : ndarray of shape (B, w), int
        N_P of the chunk's points.
    rows : slice
        The chunk's points.
    degree : int
        Of the polynomial.
    scale : float, metres
        Abscissae are divided by it (conditioning).
    outputs : {1, 2}
        Fit the second principal component only (Eq. 3), or the second and third.

    Returns
    -------
    PathFit
    """
    neighbourhood = points[windows]
    frame = path_frame(neighbourhood)
    local = frame.to_local(neighbourhood)
    x_i = frame.to_local(points[rows])[:, 0]
    design_at = poly_design(x_i, degree=degree, scale=scale)
    fit = fit_linear(
        poly_design(local[..., 0], degree=degree, scale=scale), local[..., 1 : 1 + outputs], None
    )
    return PathFit(frame=frame, x_i=x_i, design_at=design_at, fit=fit)


def chunks(n: int) -> Iterator[slice]:
    """Slices of at most :data:`CHUNK` rows covering ``range(n)``."""
    for start in range(0, n, CHUNK):
        yield slice(start, min(start + CHUNK, n))


#: At most this many chunks at once: each holds its neighbours (tens of MB on a surface), and
#: the tree queries inside a chunk use every core again.
MAX_CHUNK_THREADS = 4


def _cores() -> int:
    """The cores this process may run on (its affinity, which a container may narrow)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def balanced_chunks(n: int, threads: int) -> list[slice]:
    """Slices of at most :data:`CHUNK` rows covering ``range(n)``, equal to a row; more than
    one only where ``n`` exceeds :data:`CHUNK`, and then as many as a multiple of ``threads``
    (every thread gets the same share: five chunks of 2,048 on two threads left one idle for a
    fifth of the stage).

    Where a segment is cut matters a little: the anchored method judges a lift-off's run of
    points within one chunk (:func:`recon.methods.anchored.weigh_evidence`), so a segment is cut
    no more often than :data:`CHUNK` asks (a segment of up to 2,048 points not at all)."""
    if n <= 0:
        return []
    count = -(-n // CHUNK)
    if count > 1:
        count = -(-count // threads) * threads
    size = -(-n // count)
    return [slice(start, min(start + size, n)) for start in range(0, n, size)]


def for_each_chunk(work: Callable[[slice], None], n: int) -> None:
    """Run ``work(rows)`` for every chunk of ``range(n)`` (:func:`balanced_chunks`), on as many
    threads as there are cores.

    ``work`` must only write its own rows of shared arrays (a row's result may depend on the
    other rows of its chunk only as the lift-off runs do, see :func:`balanced_chunks`). numpy's
    batched arithmetic, matmul, eigh and SciPy's tree queries release the GIL, so chunks run in
    parallel (the per-point stage of a 10k-point edge: 0.29 s on one thread, 0.21 s on two; the
    same points).
    """
    rows = balanced_chunks(n, min(MAX_CHUNK_THREADS, _cores()))
    if len(rows) <= 1:
        for r in rows:
            work(r)
        return
    with ThreadPoolExecutor(max_workers=min(len(rows), MAX_CHUNK_THREADS, _cores())) as pool:
        # list(): re-raise the first exception of any chunk here.
        list(pool.map(work, rows))


#: The windows :func:`adaptive_smoothing` chooses among, as multiples of N_P's half-width (wider
#: than 8 did not help: the hand's slow drift, which no window removes, is most of the error).
ADAPTIVE_FACTORS = (1, 2, 4, 8)
#: Two estimates agree when they lie within this many of their standard deviations (summed, per
#: component, against the distance across the path) of each other: the intersection-of-
#: confidence-intervals rule. Measured on rounded bends of 15 and 40 mm and a free 3-D curve
#: without a scan (10 seeds, mean error over the best Savitzky-Golay's): 1.0 gave 1.01-1.04 at
#: median, 1.5 1.01-1.04, 2.0 1.02-1.05, 3.0 1.04-1.10 (wider windows chosen, bends cut).
ADAPTIVE_GAMMA = 1.0


@dataclass(frozen=True)
class Smoothing:
    """A segment's path smoothed by local 3-D polynomials.

    Attributes
    ----------
    points_m : ndarray of shape (n, 3)
    variance_m2 : ndarray of shape (n,)
        The fit's own variance at each point (residual variance times leverage).
    half_width : ndarray of shape (n,), int
        The window used at each point, in points either side.
    rms_m : ndarray of shape (n,)
        The fit's residual RMS.
    """

    points_m: FloatArray
    variance_m2: FloatArray
    half_width: NDArray[np.int64]
    rms_m: FloatArray


def smoothing(points: FloatArray, half_width: int, *, degree: int, scale: float) -> Smoothing:
    """The path smoothed with windows of ``half_width`` points either side (shifted inwards at
    the ends): each coordinate a polynomial of arc length over the window (a Savitzky-Golay
    filter in 3-D).

    Arc length, not the window's principal axis, is the abscissa: a wide window on a bend turns
    through tens of degrees, and a polynomial of the chord's direction follows such a window
    worse (measured on the real-parts benchmark at 129 points: 2.4 % more error at median than
    Savitzky-Golay's own per-axis filter, 0.0 % with arc length).
    """
    n = len(points)
    windows = window_indices(n, half_width)
    deg = min(degree, windows.shape[1] - 2)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    out = np.empty_like(points)
    variance, rms = np.empty(n), np.empty(n)
    for rows in chunks(n):
        u = arc[windows[rows]] - arc[rows][:, None]
        fit = fit_linear(poly_design(u, degree=deg, scale=scale), points[windows[rows]], None)
        at = poly_design(np.zeros(len(u)), degree=deg, scale=scale)
        out[rows] = fit.predict(at)
        # Per component, as the fit's noise: what the windows are compared by.
        variance[rows] = fit.rms**2 * fit.leverage(at)
        rms[rows] = fit.rms
    return Smoothing(out, variance, np.full(n, windows.shape[1] // 2, np.int64), rms)


def adaptive_smoothing(
    points: FloatArray, half_width: int, *, degree: int, scale: float
) -> Smoothing:
    """The path smoothed with the widest window that does not bend it, point by point.

    Windows of :data:`ADAPTIVE_FACTORS` times ``half_width`` are fitted; at each point the widest
    whose estimate agrees with every narrower one (within :data:`ADAPTIVE_GAMMA` of their summed
    standard deviations: the intersection of confidence intervals, Goldenshluger and Nemirovski
    1997) is kept. On a straight stretch that is the widest, which averages the most tremor
    away; on a tight bend a wide window cuts the corner and disagrees with the narrow ones, which
    are kept there. A fixed wide window would round a 15 mm bend off; a fixed narrow one leaves
    the tremor.

    Parameters
    ----------
    points : ndarray of shape (n, 3)
    half_width : int
        The narrowest window, in points either side.
    degree : int
    scale : float
        Abscissa scale of the narrowest window's polynomial (metres).

    Returns
    -------
    Smoothing
    """
    n = len(points)
    fits = [smoothing(points, half_width, degree=degree, scale=scale)]
    for factor in ADAPTIVE_FACTORS[1:]:
        if 2 * half_width * factor + 1 > n:
            break
        fits.append(
            smoothing(points, int(round(half_width * factor)), degree=degree, scale=scale * factor)
        )
    # Each window's standard deviation from the trace's noise, which the narrowest fit measures
    # best: a wide window's own residual includes its misfit to a bend, and would widen its
    # interval to agree with the narrow ones exactly where it should not.
    noise2 = np.maximum(fits[0].rms_m, 1e-300) ** 2
    sigma = [np.sqrt(noise2 * f.variance_m2 / np.maximum(f.rms_m, 1e-300) ** 2) for f in fits]
    chosen = np.zeros(n, dtype=np.int64)
    agreeing = np.ones(n, dtype=bool)
    for j in range(1, len(fits)):
        for i in range(j):
            gap = np.linalg.norm(fits[j].points_m - fits[i].points_m, axis=1)
            agreeing &= gap <= ADAPTIVE_GAMMA * (sigma[i] + sigma[j])
        chosen = np.where(agreeing, j, chosen)
    rows = np.arange(n)
    stack = np.stack([f.points_m for f in fits])
    return Smoothing(
        points_m=stack[chosen, rows],
        variance_m2=np.stack([f.variance_m2 for f in fits])[chosen, rows],
        half_width=np.stack([f.half_width for f in fits])[chosen, rows],
        rms_m=np.stack([f.rms_m for f in fits])[chosen, rows],
    )
