"""The thinned edge: points on the scan's edges near a path, grouped into tracks.

Every corner of the scan's cross-sections along the path (:mod:`recon.profiles`) is an edge
point: where two faces of the slice meet, the trace's feature or one beside it. Corners of
neighbouring slices that line up are one edge, a *track*: the two edges of a thin wall, the top
and the foot of a step, the two borders of a chamfer are separate tracks, so a segment can follow
one of them all the way rather than hop between them point by point.

Registration (point-to-line ICP), the segments' classification and the reconstruction's edge
targets use these points rather than the curvature band, whose centroid lies inside the corner
(about a millimetre off).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from recon.arrays import FloatArray
from recon.edge_lines import EdgeLineFit, fit_edge_lines
from recon.features import ScanFeatures
from recon.fitting import gather, weighted_pca
from recon.profiles import Profiles

#: Variance of an edge point from its line fit per unit of face variance over face points,
#: for edge points stored without their own variance (models stored by an earlier version).
EDGE_VARIANCE_FACTOR = 20.0
#: Corners of slices this close (across the edge) and this near (along it, bridging a few slices
#: without a corner) are one edge.
TRACK_OFFSET_M = 0.0008
TRACK_LINK_M = 0.010
#: An edge point's direction comes from its track's corners within this distance.
DIRECTION_REACH_M = 0.005
#: Each corner stands for this much of its edge, sampled every millimetre either side of it.
SAMPLE_OFFSETS_M = (-0.001, 0.0, 0.001)


@dataclass(frozen=True)
class EdgePoints:
    """The thinned edge: points on the scan's edges, grouped into tracks.

    Attributes
    ----------
    points_m : ndarray of shape (E, 3)
    directions : ndarray of shape (E, 3)
    residual_m : ndarray of shape (E,)
        RMS scatter of the faces' points about them where the point was found (a noise level).
    n_points : ndarray of shape (E,), int
        Points on the smaller of the two faces.
    track : ndarray of shape (E,), int
        Which edge the point belongs to (-1: not known, e.g. a corner's edge lines filled in).
    corner : ndarray of shape (E,), int
        The corner (of one slice, or refined in 3-D) the point was sampled from: a segment
        chooses the corners it follows (:mod:`recon.classify`), and its edge targets use their
        points alone (-1: not known, used by every segment along it).
    variance_m2 : ndarray of shape (E,)
        Variance of the point's position across the edge, both directions together.
    """

    points_m: FloatArray
    directions: FloatArray
    residual_m: FloatArray
    n_points: NDArray[np.int64]
    track: NDArray[np.int64] | None = None
    variance_m2: FloatArray | None = None
    corner: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        n = len(self.points_m)
        if self.track is None:
            object.__setattr__(self, "track", np.full(n, -1, np.int64))
        if self.corner is None:
            object.__setattr__(self, "corner", np.full(n, -1, np.int64))
        if self.variance_m2 is None:
            legacy = EDGE_VARIANCE_FACTOR * self.residual_m**2 / np.maximum(self.n_points, 1)
            object.__setattr__(self, "variance_m2", np.asarray(legacy, dtype=np.float64))

    def corner_labels(self) -> NDArray[np.int64]:
        """``corner`` as ``__post_init__`` left it (-1 where not known; never None)."""
        assert self.corner is not None  # filled by __post_init__
        return self.corner

    def track_labels(self) -> NDArray[np.int64]:
        """``track`` as ``__post_init__`` left it (-1 where not known; never None)."""
        assert self.track is not None  # filled by __post_init__
        return self.track

    def variances_m2(self) -> FloatArray:
        """``variance_m2`` as ``__post_init__`` left it (never None)."""
        assert self.variance_m2 is not None  # filled by __post_init__
        return self.variance_m2

    @classmethod
    def empty(cls) -> EdgePoints:
        """No edge points (a scan without edges near the path)."""
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.points_m)

    def subset(self, keep: NDArray[np.bool_]) -> EdgePoints:
        """The points where ``keep`` is True."""
        return EdgePoints(
            points_m=self.points_m[keep],
            directions=self.directions[keep],
            residual_m=self.residual_m[keep],
            n_points=self.n_points[keep],
            track=None if self.track is None else self.track[keep],
            variance_m2=None if self.variance_m2 is None else self.variance_m2[keep],
            corner=None if self.corner is None else self.corner[keep],
        )

    @classmethod
    def concatenate(cls, parts: list[EdgePoints]) -> EdgePoints:
        if not parts:
            return cls.empty()
        return cls(
            **{
                name: np.concatenate([getattr(p, name) for p in parts])
                for name in (
                    "points_m",
                    "directions",
                    "residual_m",
                    "n_points",
                    "track",
                    "variance_m2",
                    "corner",
                )
            }
        )


def edges_from_profiles(
    profiles: Profiles,
    features: ScanFeatures | None = None,
    trees: tuple[cKDTree, cKDTree] | None = None,
    *,
    fit_radius_m: float = 0.016,
) -> EdgePoints:
    """The corners of every slice as edge points, linked into tracks, each with the direction
    of its track there; every :data:`REFINE_EVERY` th corner of a track refined by a fit of its
    two faces in 3-D (when ``features`` are given).

    A slice holds tens of points per face, and the corner is where two lines extrapolated from
    them meet: a few tenths of a millimetre off at a depth camera's noise. The slice has told
    which two faces meet there; fitted over a ball of ``fit_radius_m`` (hundreds of points each,
    curving along the edge), the same two faces place the edge several times more precisely
    (:func:`recon.edge_lines.fit_edge_lines` started from the slice's lines).

    Parameters
    ----------
    profiles : Profiles
    features : ScanFeatures, optional
        The scan near the path, for the refinement.
    trees : (cKDTree, cKDTree), optional
        Over the voxel and dense clouds.
    fit_radius_m : float
        Ball of the refining fits.

    Returns
    -------
    EdgePoints
        Possibly empty.
    """
    station, pair = np.nonzero(profiles.corner_ok)
    if len(station) == 0:
        return EdgePoints.empty()
    corners = profiles.corners_world_m[station, pair]
    along = profiles.along[station]
    i, j = profiles.pairs[pair, 0], profiles.pairs[pair, 1]
    count = np.minimum(profiles.count[station, i], profiles.count[station, j])
    residual = np.maximum(profiles.rms_m[station, i], profiles.rms_m[station, j])
    variance = profiles.corner_variance_m2[station, pair]
    track = _tracks(corners, along, station)
    direction = _track_directions(corners, along, track)
    parts = []
    covered = np.zeros(len(corners), dtype=bool)
    if features is not None and len(features.dense_points_m):
        refined, covered = _refined(
            profiles, station, pair, corners, direction, track, features, trees, fit_radius_m
        )
        parts.append(refined)
    # A slice's corner unrefined is kept only where its own lines place it well (at a depth
    # camera's noise of a millimetre, most slices' lines cannot).
    keep = ~covered & (variance <= MAX_SLICE_CORNER_SIGMA_M**2)
    offsets = np.asarray(SAMPLE_OFFSETS_M)
    samples = corners[keep, None, :] + offsets[None, :, None] * direction[keep, None, :]
    repeat = len(offsets)
    parts.append(
        EdgePoints(
            points_m=samples.reshape(-1, 3),
            directions=np.repeat(direction[keep], repeat, axis=0),
            residual_m=np.repeat(residual[keep], repeat),
            n_points=np.repeat(count[keep].astype(np.int64), repeat),
            track=np.repeat(track[keep], repeat),
            variance_m2=np.repeat(variance[keep], repeat),
            corner=np.repeat(np.flatnonzero(keep), repeat),
        )
    )
    return EdgePoints.concatenate(parts)


#: A slice's corner that no 3-D fit refined is used only when its own uncertainty (1 sigma, both
#: directions together) is below this.
MAX_SLICE_CORNER_SIGMA_M = 0.0004
#: Every this many corners of a track (slices 2 mm apart) is refined in 3-D, and stands for its
#: neighbours either side.
REFINE_EVERY = 1
#: A refined corner must stay within this of its slice's corner ...
REFINE_MAX_MOVE_M = 0.0015
#: ... and within three of the slice corner's standard deviations of it, give or take this ...
REFINE_SLACK_M = 0.0002
#: ... run within this angle of its track ...
REFINE_MAX_TURN_DEG = 30.0
#: ... scatter no more than this many times the slice's lines ...
REFINE_MAX_SCATTER = 1.3
#: ... and keep its faces within this angle of the slice's lines (else it found other faces).
REFINE_MAX_FACE_TURN_DEG = 15.0


def _refined(
    profiles: Profiles,
    station: NDArray[np.intp],
    pair: NDArray[np.intp],
    corners: FloatArray,
    direction: FloatArray,
    track: NDArray[np.int64],
    features: ScanFeatures,
    trees: tuple[cKDTree, cKDTree] | None,
    radius_m: float,
) -> tuple[EdgePoints, NDArray[np.bool_]]:
    """Every :data:`REFINE_EVERY` th corner of each track refined in 3-D (see
    :func:`edges_from_profiles`): the refined edge points, and which slice corners they stand
    for."""
    order = np.lexsort((station, track))
    rank = np.empty(len(order), np.int64)
    # Position of each corner within its track, in station order.
    starts = np.r_[0, np.flatnonzero(np.diff(track[order])) + 1]
    position = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    rank[order] = position
    chosen = np.flatnonzero(rank % REFINE_EVERY == REFINE_EVERY // 2)
    if len(chosen) == 0:
        return EdgePoints.empty(), np.zeros(len(corners), bool)
    b, p = station[chosen], pair[chosen]
    i, j = profiles.pairs[p, 0], profiles.pairs[p, 1]
    axes = profiles.axes[b]

    def normal3(line: NDArray[np.int64]) -> FloatArray:
        n2 = profiles.normal[b, line]
        return n2[:, :1] * axes[:, 0] + n2[:, 1:] * axes[:, 1]

    query = corners[chosen]
    fit = fit_edge_lines(
        query,
        features,
        radius_m=radius_m,
        trees=trees,
        seed_planes=(normal3(i), query, normal3(j), query),
    )
    moved = np.linalg.norm(fit.points_m - query, axis=1)
    turn = np.abs(np.einsum("ni,ni->n", fit.directions, direction[chosen]))
    # Within what the slice's corner is known to: a ball too large for a tight bend, or a face
    # that curves across it, pulls the fit off the corner the slice saw.
    slice_sigma = np.sqrt(profiles.corner_variance_m2[b, p])
    agrees = moved <= np.minimum(REFINE_MAX_MOVE_M, 3.0 * slice_sigma + REFINE_SLACK_M)
    ok = fit.ok & agrees & (turn >= np.cos(np.radians(REFINE_MAX_TURN_DEG)))
    ok &= _faces_kept(fit, normal3(i), normal3(j))
    # The ball's faces must be as flat as the slice's lines: a third face taken in (a small
    # part's next feature, a shallow crease's neighbour) shows as a larger scatter.
    slice_rms = np.maximum(profiles.rms_m[b, i], profiles.rms_m[b, j])
    ok &= fit.residual_m <= REFINE_MAX_SCATTER * slice_rms
    good = chosen[ok]
    covered = np.zeros(len(corners), dtype=bool)
    if len(good) == 0:
        return EdgePoints.empty(), covered
    # Each refined corner stands for the slices either side of it on its track.
    by_rank = {(int(track[c]), int(rank[c])): c for c in range(len(corners))}
    for c in good:
        for step in range(-(REFINE_EVERY // 2), REFINE_EVERY // 2 + 1):
            other = by_rank.get((int(track[c]), int(rank[c]) + step))
            if other is not None:
                covered[other] = True
    lines = fit.directions[ok]
    flip = np.einsum("ni,ni->n", lines, direction[good]) < 0
    lines[flip] *= -1
    half = 0.5 * REFINE_EVERY * STATION_SPACING_M
    offsets = np.arange(-half, half + 1e-9, 0.001)
    samples = fit.points_m[ok][:, None, :] + offsets[None, :, None] * lines[:, None, :]
    repeat = len(offsets)
    residual = fit.residual_m[ok]
    count = fit.n_points[ok]
    return (
        EdgePoints(
            points_m=samples.reshape(-1, 3),
            directions=np.repeat(lines, repeat, axis=0),
            residual_m=np.repeat(residual, repeat),
            n_points=np.repeat(count, repeat),
            track=np.repeat(track[good], repeat),
            variance_m2=np.repeat(
                EDGE_VARIANCE_FACTOR * residual**2 / np.maximum(count, 1), repeat
            ),
            # A refined corner is its own corner, numbered after the slices' ones.
            corner=np.repeat(len(corners) + good, repeat),
        ),
        covered,
    )


def _faces_kept(fit: EdgeLineFit, normal_a: FloatArray, normal_b: FloatArray) -> NDArray[np.bool_]:
    """Whether a refined fit's faces are still the slice's two (either way round)."""
    cos = np.cos(np.radians(REFINE_MAX_FACE_TURN_DEG))
    # The fit's face normals are not kept; its direction and bisector are: both slice normals
    # must be perpendicular to the fitted edge direction, near enough.
    along = fit.directions
    kept: NDArray[np.bool_] = (
        np.abs(np.einsum("ni,ni->n", along, normal_a)) <= np.sqrt(1 - cos**2)
    ) & (np.abs(np.einsum("ni,ni->n", along, normal_b)) <= np.sqrt(1 - cos**2))
    return kept


def _tracks(corners: FloatArray, along: FloatArray, station: np.ndarray) -> NDArray[np.int64]:
    """Connected groups of corners: two corners of different slices are linked when they lie
    within :data:`TRACK_LINK_M` of each other and within :data:`TRACK_OFFSET_M` across the
    path."""
    n = len(corners)
    pairs = cKDTree(corners).query_pairs(TRACK_LINK_M, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(n, dtype=np.int64)
    a, b = pairs[:, 0], pairs[:, 1]
    gap = corners[b] - corners[a]
    t = along[a] + along[b]
    t /= np.maximum(np.linalg.norm(t, axis=1), 1e-300)[:, None]
    across = gap - np.einsum("pi,pi->p", gap, t)[:, None] * t
    linked = (station[a] != station[b]) & (np.linalg.norm(across, axis=1) <= TRACK_OFFSET_M)
    graph = coo_matrix((np.ones(np.count_nonzero(linked)), (a[linked], b[linked])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    tracks: NDArray[np.int64] = labels.astype(np.int64)
    return tracks


def _track_directions(corners: FloatArray, along: FloatArray, track: np.ndarray) -> FloatArray:
    """Each corner's edge direction: the main axis of its track's corners within
    :data:`DIRECTION_REACH_M` (the slice's normal where the track is too short there)."""
    k = min(16, len(corners))
    dist, idx = cKDTree(corners).query(corners, k=k, distance_upper_bound=DIRECTION_REACH_M)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    same = np.isfinite(dist) & (gather(track, idx, fill_index=len(track)) == track[:, None])
    points = gather(corners, idx, fill_index=len(corners))
    pca = weighted_pca(points, same.astype(np.float64))
    direction = pca.axes[:, :, 0]
    enough = np.count_nonzero(same, axis=1) >= 3
    spread = pca.variances[:, 0] > 4.0 * np.maximum(pca.variances[:, 1], 1e-18)
    direction = np.where((enough & spread)[:, None], direction, along)
    flip = np.einsum("ni,ni->n", direction, along) < 0
    direction[flip] *= -1
    unit: FloatArray = direction / np.linalg.norm(direction, axis=1)[:, None]
    return unit


#: Slices are cut along the path every this far ...
STATION_SPACING_M = 0.002
#: ... and on past both of its ends this far: an edge usually runs on past where an operator
#: starts and stops, and the points near an end then have the edge on both sides of them.
BEYOND_ENDS_M = 0.012


def stations_along(path_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Where to cut slices along an ordered path, and the path's direction there.

    Returns
    -------
    stations : ndarray of shape (B, 3)
        Every :data:`STATION_SPACING_M` of arc length, and on past both ends by up to
        :data:`BEYOND_ENDS_M` along the end directions.
    along : ndarray of shape (B, 3)
        Unit directions: the path's over 6 mm, its end directions past its ends.
    """
    path_m = np.asarray(path_m, dtype=np.float64)
    if len(path_m) < 2:
        return np.zeros((0, 3)), np.zeros((0, 3))
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(path_m, axis=0), axis=1))))
    if arc[-1] <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3))

    def at(s: FloatArray) -> FloatArray:
        return np.column_stack([np.interp(s, arc, path_m[:, k]) for k in range(3)])

    length = arc[-1]
    inner_arc = np.append(np.arange(0.0, length, STATION_SPACING_M), length)
    stations = [at(inner_arc)]
    along = [at(inner_arc + 0.003) - at(inner_arc - 0.003)]
    steps = np.arange(STATION_SPACING_M, BEYOND_ENDS_M + 1e-12, STATION_SPACING_M)
    reach = min(0.006, length)
    for end, direction in (
        (path_m[0], path_m[0] - at(np.array([reach]))[0]),
        (path_m[-1], path_m[-1] - at(np.array([length - reach]))[0]),
    ):
        norm = np.linalg.norm(direction)
        if norm > 1e-9:
            direction = direction / norm
            stations.append(end + np.outer(steps, direction))
            along.append(np.tile(direction, (len(steps), 1)))
    stations_m, along_m = np.concatenate(stations), np.concatenate(along)
    norm = np.linalg.norm(along_m, axis=1)
    keep = norm > 1e-9
    return stations_m[keep], along_m[keep] / norm[keep][:, None]


def thin_edges(
    profiles: Profiles,
    features: ScanFeatures | None = None,
    trees: tuple[cKDTree, cKDTree] | None = None,
    *,
    fit_radius_m: float = 0.016,
) -> EdgePoints:
    """The thinned edge along a path from its slices (see :func:`edges_from_profiles`)."""
    return edges_from_profiles(profiles, features, trees, fit_radius_m=fit_radius_m)
