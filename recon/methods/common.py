"""What the reconstruction methods share: the per-segment result, N_P's frame and path fit,
N_S on an edge, and the chunking that bounds memory.

Every function works on one segment at a time, vectorised over its points in chunks of
:data:`CHUNK` rows (no Python loop per point).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from recon.fitting import PCA, LinearFit, fit_linear, gather, poly_design, weighted_pca
from recon.scan_model import ScanModel
from recon.types import FloatArray, PointMode

#: What a hand trace is off by where nothing but the trace says where the path is, 1 sigma
#: across the path: the paper measured operators' errors at a standard deviation of 0.5-1 mm
#: (Sec. VI; our scenes' traces: 0.9 mm RMS). A local smoother removes the tremor but not the slow
#: drift, which is most of it.
HAND_ERROR_PRIOR_M = 0.8e-3
#: Rows processed at once; bounds memory (a chunk holds chunk x K neighbours).
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
        :class:`recon.types.PointMode` of each point.
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
    """

    points: FloatArray
    mode: NDArray[np.int8]
    n_path: NDArray[np.int64]
    n_surface: NDArray[np.int64]
    residual_path: FloatArray
    residual_surface: FloatArray
    alpha: FloatArray
    variance_m2: FloatArray

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
    centres: FloatArray, path_direction: FloatArray, model: ScanModel, radius_m: float
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

    Returns
    -------
    points : ndarray of shape (B, K, 3)
    weights : ndarray of shape (B, K)
    index : ndarray of shape (B, K), int
        Into ``model.edges``; ``len(model.edges)`` marks padding.
    """
    edges = model.edges
    k = min(64, len(edges))
    dist, idx = model.edge_tree.query(centres, k=k, distance_upper_bound=radius_m, workers=-1)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    pts = gather(edges.points_m, idx, fill_index=len(edges))
    dirs = gather(edges.directions, idx, fill_index=len(edges))
    along = np.abs(np.einsum("bki,bi->bk", dirs, path_direction))
    weights = np.isfinite(dist) & (along >= np.cos(np.radians(EDGE_DIRECTION_TOLERANCE_DEG)))
    return pts, weights.astype(np.float64), idx


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
