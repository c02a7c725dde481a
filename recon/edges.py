"""The thinned edge: points sampled along the local edge lines near a path.

Registration (point-to-line ICP) and the reconstruction's edge targets use these points rather
than the curvature band, whose centroid lies inside the corner (about a millimetre off).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from recon.edge_lines import EdgeLineFit, fit_edge_lines
from recon.features import ScanFeatures
from recon.types import FloatArray

#: Variance of an edge point from its line fit per unit of face variance over face points
#: (see :attr:`EdgePoints.variance_m2`).
EDGE_VARIANCE_FACTOR = 20.0


@dataclass(frozen=True)
class EdgePoints:
    """The thinned edge: points on the local edge lines, one per processed band point.

    Attributes
    ----------
    points_m : ndarray of shape (E, 3)
    directions : ndarray of shape (E, 3)
    residual_m : ndarray of shape (E,)
        Face-fit residual at each point (a noise level for alpha="auto").
    n_points : ndarray of shape (E,), int
        Points on the smaller face of each point's fit.
    """

    points_m: FloatArray
    directions: FloatArray
    residual_m: FloatArray
    n_points: NDArray[np.int64]

    @classmethod
    def empty(cls) -> EdgePoints:
        """No edge points (a scan without edges near the path)."""
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.points_m)

    @property
    def variance_m2(self) -> FloatArray:
        """Variance of each point's position from its line fit, ``K sigma^2 / n``.

        An edge point is where two noisy faces, fitted off the crest, are extrapolated to meet;
        the extrapolation multiplies the faces' noise. K = 20 is the factor measured on
        right-angle edges (per-fit scatter 0.22-0.33 mm at sigma = 1 mm with about 250 points
        per face).
        """
        return EDGE_VARIANCE_FACTOR * self.residual_m**2 / np.maximum(self.n_points, 1)


def _every(path_m: FloatArray, spacing_m: float) -> FloatArray:
    """Points of a polyline, one at each multiple of ``spacing_m`` of arc length (and the end)."""
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(path_m, axis=0), axis=1))))
    stations = np.append(np.arange(0.0, arc[-1], spacing_m), arc[-1])
    index = np.unique(np.searchsorted(arc, stations))
    return path_m[np.clip(index, 0, len(path_m) - 1)]


def _beyond_ends(path_m: FloatArray, spacing_m: float, reach_m: float) -> FloatArray:
    """Points past both ends of a path, along its end directions, every ``spacing_m`` up to
    ``reach_m`` (the directions from the last ``reach_m`` of the path, where there is that much).

    Returns
    -------
    ndarray of shape (Q, 3)
        Empty for a path shorter than two points.
    """
    if len(path_m) < 2 or reach_m <= 0:
        return np.zeros((0, 3))
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(path_m, axis=0), axis=1))))
    steps = np.arange(spacing_m, reach_m + 1e-12, spacing_m)
    out = []
    for end, inner in (
        (0, np.searchsorted(arc, min(reach_m, arc[-1]))),
        (len(path_m) - 1, np.searchsorted(arc, max(arc[-1] - reach_m, 0.0))),
    ):
        inner = int(np.clip(inner, 0, len(path_m) - 1))
        direction = path_m[end] - path_m[inner]
        norm = np.linalg.norm(direction)
        if norm > 1e-9:
            out.append(path_m[end] + np.outer(steps, direction / norm))
    return np.concatenate(out) if out else np.zeros((0, 3))


#: Where a fit in the full ball fails, one in a ball this much smaller is tried.
SMALL_BALL_FRACTION = 0.5
#: A fitted edge point must have a scan point within this many face-fit sigmas of it (and at
#: least :data:`EDGE_GAP_FLOOR_M`): the crest is scanned too.
EDGE_GAP_SIGMAS = 2.0
EDGE_GAP_FLOOR_M = 1e-3


def _fit_and_judge(queries, features, radius_m, trees, *, typical):
    """Edge-line fits at the queries, and which to keep: well-posed, near their query, and (a fit
    spanning three faces near a box corner has a large residual) not much worse than typical
    (the median of the kept ones, unless given)."""
    fit = fit_edge_lines(queries, features, radius_m=radius_m, trees=trees)
    moved = np.linalg.norm(fit.points_m - queries, axis=1)
    keep = fit.ok & (moved <= 0.5 * radius_m)
    if np.any(keep):
        if typical is None:
            typical = float(np.median(fit.residual_m[keep]))
        keep &= fit.residual_m <= 2.0 * typical + 1e-6
    # Two faces that met where the scan has no points (in the air, or inside the workpiece)
    # were extrapolated from a ball that holds no two flat faces: a tight bend seen whole.
    dense_tree = trees[1] if trees is not None else cKDTree(features.dense_points_m)
    gap, _ = dense_tree.query(fit.points_m, workers=-1)
    keep &= gap <= np.maximum(EDGE_GAP_FLOOR_M, EDGE_GAP_SIGMAS * fit.residual_m)
    return fit, keep


def _with_rows(fit: EdgeLineFit, rows, other: EdgeLineFit, other_keep) -> EdgeLineFit:
    """``fit`` with the kept ones of ``other`` in place of ``rows``."""
    take = rows[other_keep]
    arrays = {}
    for name in (
        "points_m",
        "directions",
        "residual_m",
        "n_points",
        "dihedral_deg",
        "ok",
        "bisector",
    ):
        values = getattr(fit, name).copy()
        values[take] = getattr(other, name)[other_keep]
        arrays[name] = values
    return EdgeLineFit(**arrays)


def thin_edges(
    features: ScanFeatures,
    near_m: FloatArray,
    *,
    radius_m: float,
    query_spacing_m: float,
    sample_spacing_m: float,
    trees: tuple[cKDTree, cKDTree] | None = None,
    beyond_ends_m: float = 0.0,
) -> EdgePoints:
    """Thin the band of edge points to the edge itself, along a path that follows it.

    Edge lines are fitted (:func:`fit_edge_lines`) at points of ``near_m`` spaced
    ``query_spacing_m`` apart, where the band of edge points is within reach; each fitted line
    is then sampled every ``sample_spacing_m`` over the stretch its query stands for. Querying
    along the path rather than at every band point avoids fitting the same stretch of edge many
    times over across the band's width, and sampling the local lines gives registration a
    continuous edge rather than isolated points.

    Parameters
    ----------
    features : ScanFeatures
    near_m : ndarray of shape (N, 3)
        An ordered path near the edges of interest (the trace, roughly aligned). Queries are
        taken along it by arc length, which does not depend on the frame (a voxel grid would).
    radius_m : float
        Neighbourhood radius of the two-face fits.
    query_spacing_m : float
        Distance between fits along ``near_m``.
    sample_spacing_m : float
        Spacing of the returned points along each local line.
    trees : (cKDTree, cKDTree), optional
        Trees over the voxel and dense clouds, to reuse (see :func:`fit_edge_lines`).
    beyond_ends_m : float
        Fits are also made this far past both ends of ``near_m``, along its end directions: an
        edge usually runs on past where an operator starts and stops, and a point near the end
        of the path then has the edge on both sides of it, as every other point has (rather
        than a fit extrapolated past its data). Where the edge ends, these fits find none.

    Returns
    -------
    EdgePoints
        Possibly empty.
    """
    empty = EdgePoints.empty()
    if not np.any(features.is_edge) or len(near_m) == 0:
        return empty
    near_m = np.asarray(near_m, np.float64)
    queries = np.concatenate(
        [_every(near_m, query_spacing_m), _beyond_ends(near_m, query_spacing_m, beyond_ends_m)]
    )
    # Only where the band of edge points is within half a ball: elsewhere the ball would reach a
    # distant edge, or none.
    band = features.points_m[features.is_edge]
    band_dist, _ = cKDTree(band).query(queries, distance_upper_bound=0.5 * radius_m, workers=-1)
    queries = queries[np.isfinite(band_dist)]
    if len(queries) == 0:
        return empty
    fit, keep = _fit_and_judge(queries, features, radius_m, trees, typical=None)
    if not np.any(keep):
        return empty
    # Where the edge bends tightly (a rounded corner of 15 mm radius) a ball of the full radius
    # holds no two flat faces and its fit is dropped; a ball half as wide often does.
    retry = ~keep
    if np.any(retry):
        typical = float(np.median(fit.residual_m[keep]))
        small, small_keep = _fit_and_judge(
            queries[retry], features, SMALL_BALL_FRACTION * radius_m, trees, typical=typical
        )
        fit = _with_rows(fit, np.flatnonzero(retry), small, small_keep)
        keep[retry] = small_keep
    half = 0.5 * query_spacing_m
    offsets = np.arange(-half, half + 1e-12, sample_spacing_m)
    centres, directions = fit.points_m[keep], fit.directions[keep]
    samples = centres[:, None, :] + offsets[None, :, None] * directions[:, None, :]
    count = len(offsets)
    return EdgePoints(
        points_m=samples.reshape(-1, 3),
        directions=np.repeat(directions, count, axis=0),
        residual_m=np.repeat(fit.residual_m[keep], count),
        n_points=np.repeat(fit.n_points[keep], count),
    )
