"""Cross-sections of the scan across a path: the faces as lines in each slice, and the edges as
the corners where two of those lines meet.

Looking along a feature, a workpiece is a profile: faces are lines in the slice (a wall, a floor, a
chamfer, both sides of a thin wall), edges are the corners where two lines meet, and a slot, a
step or a lip is a few lines a few millimetres apart. Fitting surfaces in a ball around a point
blends whatever the ball holds; finding the lines of the slice first keeps near-parallel features
apart down to the scan's noise.

At each station along the path, the dense scan points within :data:`SLAB_HALF_THICKNESS_M` of
the plane across the path (and :data:`PROFILE_RADIUS_M` of the station) are projected onto it.
Lines are found by a Hough transform (every point votes for the lines through it), strongest
first: each peak is refined by a total-least-squares fit to the points within a band of it, and
its points are then taken out before the next peak is sought. A corner is where two lines that
are at least :data:`MIN_CORNER_ANGLE_DEG` apart cross, and both lines' own points reach it.

Everything is vectorised over stations (no Python loop per station), chunk by chunk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter1d
from scipy.spatial import cKDTree

from recon.arrays import FloatArray
from recon.fitting import gather
from recon.kernels import PointGrid, compiled, hough_votes, nearest_within, thread_pool

#: Half the thickness of each slice (along the path): thick enough for tens of points per face
#: at a depth camera's density, thin enough that a curved feature stays straight within it.
SLAB_HALF_THICKNESS_M = 0.004
#: How far from the station the slice reaches.
PROFILE_RADIUS_M = 0.012
#: Dense points gathered per station before the slice is cut from them.
PROFILE_NEIGHBOURS = 768
#: The Hough transform's resolution: line directions ...
THETA_BINS = 30
#: ... and offsets.
RHO_BIN_M = 0.0005
#: At most this many lines per slice.
MAX_LINES = 4
#: A line needs this many points ...
MIN_LINE_POINTS = 10
#: ... spread over at least this length.
MIN_LINE_LENGTH_M = 0.002
#: A point belongs to a line within this many of the line's noise levels, and at least
#: :data:`MIN_BAND_M`.
BAND_SIGMAS = 2.5
MIN_BAND_M = 0.0008
#: Before a line's own noise is known: the band of its first refinement.
FIRST_BAND_M = 0.0015
#: Two lines closer than this to parallel make no corner.
MIN_CORNER_ANGLE_DEG = 25.0
#: A corner is supported when each line has a point within this of it (a depth camera loses the
#: pixels right at a silhouette) ...
CORNER_REACH_M = 0.0035
#: ... and extends at least this far from it.
MIN_ARM_M = 0.002
#: The peak of the Hough transform is sought over bands of this many offset bins (1.5 mm: about
#: the width of a face's points at a depth camera's noise).
PEAK_BAND_BINS = 3
#: A point belongs to a line only if its normal (its face's) is within this of the line's ...
NORMAL_TOLERANCE_DEG = 35.0
#: ... and votes only for lines in its own normal's direction bin and this many either side (the
#: peak needs no more: the refinement finds the line's direction; measured on the real-parts
#: benchmark, voting across the whole tolerance found the same corners at 3.5 times the cost).
VOTE_HALF_WINDOW = 1
#: A line whose points lean off it by more than this (median; a face's small-scale normals
#: scatter by a few degrees, a ramp bridging a low step leans 20-30) ...
RAMP_ANGLE_DEG = 15.0
#: ... in two runs with a gap of more than this between is a ramp, not a face.
RAMP_GAP_M = 0.0012
#: A point whose normal lies mostly along the path (its face is cut at a glancing angle) does not
#: vote: the in-slice part of its unit normal must be at least this long.
MIN_NORMAL_IN_SLICE = 0.6
#: A line nearly parallel to a stronger one (within this) and within three noise levels of it is
#: the same face's noisy tail.
DUPLICATE_ANGLE_DEG = 10.0
#: A line whose halves each run at more than this to it is two faces, not one.
BENT_ANGLE_DEG = 5.0
#: Supported corners of one slice this close are one corner (the strongest is kept).
CLOSE_CORNERS_M = 0.0025
#: Stations processed at once (bounds memory: a chunk's neighbours are stations x 768 x 3
#: floats, 5 MB at 256, a few such arrays per thread). Fewer cost more in numpy's per-call
#: overhead: 64 took a quarter longer on 10k stations, with the same output.
STATION_CHUNK = 256
#: How far a slice's points may lie from its station in 3-D: the profile radius across the
#: slab's half thickness (the slab is thin).
_REACH_M = float(np.hypot(PROFILE_RADIUS_M, SLAB_HALF_THICKNESS_M))
#: Chunks of stations whose neighbours are found in one query (1,024 stations).
QUERY_CHUNKS = 4


@dataclass(frozen=True)
class Profiles:
    """The lines and corners of the slices at B stations (L lines, P = L(L-1)/2 pairs each).

    Line ``i`` of station ``b`` is ``{p : normal[b, i] . p = offset_m[b, i]}`` in the slice's
    coordinates ``p = ((x - origin) . axes[b, 0], (x - origin) . axes[b, 1])``.

    Attributes
    ----------
    origin_m : ndarray of shape (B, 3)
        The stations (scan frame).
    along : ndarray of shape (B, 3)
        Unit normal of each slice: the path's direction there.
    axes : ndarray of shape (B, 2, 3)
        The slice's two in-plane unit axes.
    normal : ndarray of shape (B, L, 2)
        Unit normal of each line, slice coordinates.
    offset_m : ndarray of shape (B, L)
    count : ndarray of shape (B, L), int
        Points of each line.
    rms_m : ndarray of shape (B, L)
        RMS distance of a line's points to it.
    extent_m : ndarray of shape (B, L, 2)
        Smallest and largest position of a line's points along it (along ``(-n_y, n_x)``).
    line_ok : ndarray of shape (B, L), bool
    corner_m : ndarray of shape (B, P, 2)
        Where each pair of lines crosses, slice coordinates.
    corner_ok : ndarray of shape (B, P), bool
        A supported corner (see the module docstring).
    corner_angle_deg : ndarray of shape (B, P)
        Angle between the two lines (0 parallel, 90 square).
    corner_variance_m2 : ndarray of shape (B, P)
        Variance of the corner's position (both directions together) from the two lines' fits.
    pairs : ndarray of shape (P, 2), int
        The lines of each pair.
    """

    origin_m: FloatArray
    along: FloatArray
    axes: FloatArray
    normal: FloatArray
    offset_m: FloatArray
    count: NDArray[np.int64]
    rms_m: FloatArray
    extent_m: FloatArray
    line_ok: NDArray[np.bool_]
    corner_m: FloatArray
    corner_ok: NDArray[np.bool_]
    corner_angle_deg: FloatArray
    corner_variance_m2: FloatArray
    pairs: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.origin_m)

    def to_slice(self, points_m: FloatArray) -> FloatArray:
        """Points (one per station, shape (B, 3)) in their station's slice coordinates (B, 2)."""
        rel = points_m - self.origin_m
        local: FloatArray = np.einsum("bki,bi->bk", self.axes, rel)
        return local

    def to_world(self, slice_m: FloatArray) -> FloatArray:
        """Slice coordinates (B, 2) or (B, P, 2) back to the scan frame (B, 3) or (B, P, 3)."""
        if slice_m.ndim == 2:
            world: FloatArray = self.origin_m + np.einsum("bk,bki->bi", slice_m, self.axes)
        else:
            world = self.origin_m[:, None] + np.einsum("bpk,bki->bpi", slice_m, self.axes)
        return world

    @property
    def corners_world_m(self) -> FloatArray:
        """Every pair's crossing, scan frame (B, P, 3)."""
        return self.to_world(self.corner_m)


def slice_axes(along: FloatArray) -> FloatArray:
    """Two unit axes across each direction (B, 3) -> (B, 2, 3), right-handed with it."""
    helper = np.where(np.abs(along[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    a = np.cross(helper, along)
    a /= np.linalg.norm(a, axis=1)[:, None]
    b = np.cross(along, a)
    return np.stack([a, b], axis=1)


def find_profiles(
    stations_m: FloatArray,
    along: FloatArray,
    dense_points_m: FloatArray,
    dense_normals: FloatArray,
    dense_tree: cKDTree,
) -> Profiles:
    """The lines and corners of the slices across a path (see the module docstring).

    Parameters
    ----------
    stations_m : ndarray of shape (B, 3)
        Where to cut, scan frame.
    along : ndarray of shape (B, 3)
        The path's direction at each station (the slices' normals; unit or not).
    dense_points_m : ndarray of shape (D, 3)
        The scan near the path.
    dense_normals : ndarray of shape (D, 3)
        Their unit normals at a small scale (sign arbitrary): a point votes only for lines
        that run along its own face.
    dense_tree : scipy.spatial.cKDTree
        Over ``dense_points_m``: the reference's neighbour search, where the compiled kernels
        are off (:mod:`recon.kernels`).

    Returns
    -------
    Profiles
    """
    stations_m = np.asarray(stations_m, dtype=np.float64)
    along = np.asarray(along, dtype=np.float64)
    along = along / np.maximum(np.linalg.norm(along, axis=1), 1e-300)[:, None]
    # The compiled grid, built once, finds the same neighbours as the tree at the same
    # distances, in a third of the time (recon.kernels.nearest_within); the tree is the
    # reference.
    grid = (
        PointGrid(dense_points_m, _REACH_M)
        if compiled() is not None and len(stations_m) and len(dense_points_m)
        else None
    )
    k = min(PROFILE_NEIGHBOURS, len(dense_points_m))
    parts: list[Profiles] = []
    # Neighbours of many stations per query (the grid's threads share them), sliced per chunk.
    for start in range(0, len(stations_m), STATION_CHUNK * QUERY_CHUNKS):
        block = slice(start, start + STATION_CHUNK * QUERY_CHUNKS)
        dist, idx = nearest_within(
            dense_points_m, stations_m[block], k=k, radius_m=_REACH_M, grid=grid, tree=dense_tree
        )

        # numpy releases the GIL on the chunks' arrays: two threads take a fifth off the stage.
        def chunk(
            i: int, block: slice = block, dist: FloatArray = dist, idx: NDArray[np.int64] = idx
        ) -> Profiles:
            rows = slice(block.start + i, block.start + i + STATION_CHUNK)
            return _profiles_chunk(
                stations_m[rows],
                along[rows],
                dense_points_m,
                dense_normals,
                dist[i : i + STATION_CHUNK],
                idx[i : i + STATION_CHUNK],
            )

        parts.extend(thread_pool().map(chunk, range(0, len(dist), STATION_CHUNK)))
    if not parts:
        return _empty_profiles()
    pairs = parts[0].pairs
    fields = [f for f in Profiles.__dataclass_fields__ if f != "pairs"]
    return Profiles(
        **{f: np.concatenate([getattr(p, f) for p in parts]) for f in fields}, pairs=pairs
    )


def _empty_profiles() -> Profiles:
    pairs = _pairs()
    b, lines, p = 0, MAX_LINES, len(pairs)
    return Profiles(
        origin_m=np.zeros((b, 3)),
        along=np.zeros((b, 3)),
        axes=np.zeros((b, 2, 3)),
        normal=np.zeros((b, lines, 2)),
        offset_m=np.zeros((b, lines)),
        count=np.zeros((b, lines), np.int64),
        rms_m=np.zeros((b, lines)),
        extent_m=np.zeros((b, lines, 2)),
        line_ok=np.zeros((b, lines), bool),
        corner_m=np.zeros((b, p, 2)),
        corner_ok=np.zeros((b, p), bool),
        corner_angle_deg=np.zeros((b, p)),
        corner_variance_m2=np.zeros((b, p)),
        pairs=pairs,
    )


def _pairs() -> NDArray[np.int64]:
    i, j = np.triu_indices(MAX_LINES, k=1)
    return np.column_stack([i, j]).astype(np.int64)


def _profiles_chunk(
    stations: FloatArray,
    along: FloatArray,
    dense: FloatArray,
    normals: FloatArray,
    dist: FloatArray,
    idx: NDArray[np.int64],
) -> Profiles:
    """The profiles of ``B`` stations from their neighbours in the dense cloud (distances and
    indices (B, K) as a k-d tree's query returns them, ``len(dense)`` past the last)."""
    b = len(stations)
    axes = slice_axes(along)
    points = gather(dense, idx, fill_index=len(dense)) - stations[:, None, :]
    point_normals = gather(normals, idx, fill_index=len(dense))
    x = np.einsum("bki,bi->bk", points, axes[:, 0])
    y = np.einsum("bki,bi->bk", points, axes[:, 1])
    z = np.einsum("bki,bi->bk", points, along)
    nx = np.einsum("bki,bi->bk", point_normals, axes[:, 0])
    ny = np.einsum("bki,bi->bk", point_normals, axes[:, 1])
    free = np.isfinite(dist) & (np.abs(z) <= SLAB_HALF_THICKNESS_M)
    free &= x * x + y * y <= PROFILE_RADIUS_M**2
    # A point on a face that the slice cuts at a glancing angle (its normal along the path) says
    # nothing about the slice's lines.
    free &= nx * nx + ny * ny >= MIN_NORMAL_IN_SLICE**2
    # Only the slice's points from here on: moved to the front of each row and the rest cut off
    # (a quarter of the ball or less), which bounds the Hough votes.
    order = np.argsort(~free, axis=1, kind="stable")
    width = max(int(np.count_nonzero(free, axis=1).max(initial=0)), 1)
    order = order[:, :width]
    x, y = np.take_along_axis(x, order, 1), np.take_along_axis(y, order, 1)
    nx, ny = np.take_along_axis(nx, order, 1), np.take_along_axis(ny, order, 1)
    free = np.take_along_axis(free, order, 1)
    # The slice's own axes, from its points rather than the world's: the first along their main
    # normal direction, pointing away from their centre. A rigid motion (or a mirror image) of
    # the scan and the path then moves (mirrors) every result with it, bin for bin.
    x, y, nx, ny, axes = _intrinsic_axes(x, y, nx, ny, free, axes)
    # Each point's normal direction in the slice, as a line direction's normal angle in [0, pi).
    phi = np.mod(np.arctan2(ny, nx), np.pi)

    theta = (np.arange(THETA_BINS) + 0.5) * np.pi / THETA_BINS
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    n_rho = int(np.ceil(2 * PROFILE_RADIUS_M / RHO_BIN_M)) + 2
    lines = MAX_LINES
    normal = np.zeros((b, lines, 2))
    offset = np.zeros((b, lines))
    count = np.zeros((b, lines), np.int64)
    rms = np.zeros((b, lines))
    extent = np.zeros((b, lines, 2))
    line_ok = np.zeros((b, lines), bool)
    members = np.zeros((b, lines) + x.shape[1:], bool)
    accumulator = _votes(x, y, phi, free, n_rho)
    for line in range(lines):
        # Votes within a band of each offset, not in one bin: a line's points scatter over a few
        # bins.
        banded = uniform_filter1d(accumulator, size=PEAK_BAND_BINS, axis=2, mode="constant")
        peak = banded.reshape(b, -1).argmax(axis=1)
        t_bin, r_bin = np.divmod(peak, n_rho)
        n0 = np.column_stack([cos_t[t_bin], sin_t[t_bin]])
        rho0 = (r_bin + 0.5) * RHO_BIN_M - PROFILE_RADIUS_M - RHO_BIN_M
        band = np.full(b, FIRST_BAND_M)
        inside = free & (np.abs(x * n0[:, :1] + y * n0[:, 1:] - rho0[:, None]) <= band[:, None])
        inside &= _along_line(phi, n0)
        n0, rho0, sigma, inside = _refine(x, y, phi, free, inside, passes=2)
        # A line through two parallel faces a few millimetres apart (a step, a lip) slants
        # across both; each half of its points then runs along its own face, not along it.
        # Keep the half that is straighter, grown again as a line of its own.
        half, bent = _straighter_half(x, y, inside, n0)
        if np.any(bent):
            n1, rho1, sigma1, inside1 = _refine(x, y, phi, free, half, passes=2)
            n0 = np.where(bent[:, None], n1, n0)
            rho0 = np.where(bent, rho1, rho0)
            sigma = np.where(bent, sigma1, sigma)
            inside = np.where(bent[:, None], inside1, inside)
        # The line's points along it.
        s = x * -n0[:, 1:] + y * n0[:, :1]
        lo = np.where(inside, s, np.inf).min(axis=1)
        hi = np.where(inside, s, -np.inf).max(axis=1)
        n_in = np.count_nonzero(inside, axis=1)
        ok = (n_in >= MIN_LINE_POINTS) & (hi - lo >= MIN_LINE_LENGTH_M)
        ok &= _not_a_ramp(phi, n0, s, inside)
        normal[:, line] = n0
        offset[:, line] = rho0
        count[:, line] = n_in
        rms[:, line] = sigma
        extent[:, line] = np.column_stack([lo, hi])
        line_ok[:, line] = ok
        members[:, line] = inside & ok[:, None]
        # Its points vote no more.
        accumulator -= _votes(x, y, phi, inside, n_rho)
        free &= ~inside
        if not np.any(free):
            break

    line_ok, members = _without_duplicates(normal, offset, rms, line_ok, members)
    # Support is judged on every point a line took (a crest's points reach its corner); the
    # lines themselves are refitted without the points two lines share.
    support = members
    normal, offset, rms, count, members = _without_crests(
        x, y, members, normal, offset, rms, count, line_ok
    )
    pairs = _pairs()
    corner, corner_ok, angle, corner_var = _corners(
        x, y, members, support, normal, offset, rms, count, line_ok, pairs
    )
    corner_ok = _without_cut_off_corners(corner, corner_ok, pairs)
    corner_ok = _strongest_of_close_corners(corner, corner_ok, count, pairs)
    return Profiles(
        origin_m=stations,
        along=along,
        axes=axes,
        normal=normal,
        offset_m=offset,
        count=count,
        rms_m=rms,
        extent_m=extent,
        line_ok=line_ok,
        corner_m=corner,
        corner_ok=corner_ok,
        corner_angle_deg=angle,
        corner_variance_m2=corner_var,
        pairs=pairs,
    )


def _intrinsic_axes(
    x: FloatArray,
    y: FloatArray,
    nx: FloatArray,
    ny: FloatArray,
    free: NDArray[np.bool_],
    axes: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Turn each slice's axes onto its points' main normal direction (sign: away from their
    centroid) and express the points and normals in them."""
    w = free.astype(np.float64)
    # The doubled angle of the normals (sign-free), averaged: its half is the main direction.
    c2 = (w * (nx * nx - ny * ny)).sum(axis=1)
    s2 = (w * 2.0 * nx * ny).sum(axis=1)
    angle = 0.5 * np.arctan2(s2, c2)
    e = np.column_stack([np.cos(angle), np.sin(angle)])
    total = np.maximum(w.sum(axis=1), 1e-300)
    centroid = np.column_stack([(w * x).sum(1), (w * y).sum(1)]) / total[:, None]
    flip = np.einsum("bk,bk->b", centroid, e) > 0
    e[flip] *= -1
    perp = np.column_stack([-e[:, 1], e[:, 0]])

    def turned(u: FloatArray, v: FloatArray, basis: FloatArray) -> FloatArray:
        return u * basis[:, :1] + v * basis[:, 1:]

    new_axes = np.stack(
        [
            e[:, :1] * axes[:, 0] + e[:, 1:] * axes[:, 1],
            perp[:, :1] * axes[:, 0] + perp[:, 1:] * axes[:, 1],
        ],
        axis=1,
    )
    return (
        turned(x, y, e),
        turned(x, y, perp),
        turned(nx, ny, e),
        turned(nx, ny, perp),
        new_axes,
    )


def _votes(
    x: FloatArray, y: FloatArray, phi: FloatArray, weight: NDArray[np.bool_], n_rho: int
) -> FloatArray:
    """Hough accumulator (B, THETA_BINS, n_rho): each weighted point votes for the lines through
    it whose normals lie within :data:`VOTE_HALF_WINDOW` direction bins of its own normal
    (``phi``), each vote shared linearly between the two nearest offset bins
    (:func:`recon.kernels.hough_votes`)."""
    return hough_votes(
        x,
        y,
        phi,
        weight,
        n_theta=THETA_BINS,
        half_window=VOTE_HALF_WINDOW,
        radius_m=PROFILE_RADIUS_M,
        rho_bin_m=RHO_BIN_M,
        n_rho=n_rho,
    )


def _not_a_ramp(
    phi: FloatArray, normal: FloatArray, s: FloatArray, inside: NDArray[np.bool_]
) -> NDArray[np.bool_]:
    """Per station, False where the line is a ramp across a low step rather than a face: its
    points (``inside``, (B, K)) lean off it, the median angle between their normals (``phi``)
    and its ``normal`` (B, 2) above :data:`RAMP_ANGLE_DEG`, and they come in two runs along it
    (``s``, (B, K)) with a gap of more than :data:`RAMP_GAP_M` between (the step's riser, whose
    points face elsewhere). A narrow face (a thin wall's top) leans as much in small-scale
    normals blended over its edges, but its points run on without a gap."""
    line_phi = np.mod(np.arctan2(normal[:, 1], normal[:, 0]), np.pi)
    off = np.abs(phi - line_phi[:, None])
    off = np.minimum(off, np.pi - off)
    leaning = _masked_median(off, inside) > np.radians(RAMP_ANGLE_DEG)
    ordered = np.sort(np.where(inside, s, np.inf), axis=1)
    with np.errstate(invalid="ignore"):  # inf - inf past the last point: no step
        steps = np.diff(ordered, axis=1)
    gap = np.where(np.isfinite(steps), steps, 0.0).max(axis=1, initial=0.0)
    ramp: NDArray[np.bool_] = leaning & (gap > RAMP_GAP_M)
    return ~ramp


def _along_line(phi: FloatArray, normal: FloatArray) -> NDArray[np.bool_]:
    """Whether each point's normal (angle ``phi`` (B, K)) agrees with a line's normal (B, 2)
    within :data:`NORMAL_TOLERANCE_DEG`, sign ignored."""
    line_phi = np.mod(np.arctan2(normal[:, 1], normal[:, 0]), np.pi)[:, None]
    diff = np.abs(phi - line_phi)
    diff = np.minimum(diff, np.pi - diff)
    along: NDArray[np.bool_] = diff <= np.radians(NORMAL_TOLERANCE_DEG)
    return along


def _refine(
    x: FloatArray,
    y: FloatArray,
    phi: FloatArray,
    free: NDArray[np.bool_],
    inside: NDArray[np.bool_],
    *,
    passes: int,
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """Total least squares on a line's points, then its points again (within a band of its own
    noise, along its direction), ``passes`` times."""
    for _ in range(passes):
        normal, rho, sigma = _total_least_squares(x, y, inside)
        band = np.maximum(BAND_SIGMAS * sigma, MIN_BAND_M)
        distance = np.abs(x * normal[:, :1] + y * normal[:, 1:] - rho[:, None])
        inside = free & (distance <= band[:, None]) & _along_line(phi, normal)
    return normal, rho, sigma, inside


def _straighter_half(
    x: FloatArray, y: FloatArray, inside: NDArray[np.bool_], normal: FloatArray
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Where a line's two halves (split at its median point) run at more than
    :data:`BENT_ANGLE_DEG` to it, and by more than their noise explains (three standard
    deviations of the halves' directions): the points of the half with the smaller scatter,
    and which lines are bent."""
    s = x * -normal[:, 1:] + y * normal[:, :1]
    count = np.count_nonzero(inside, axis=1)
    median = _masked_median(s, inside)
    left = inside & (s <= median[:, None])
    right = inside & (s > median[:, None])
    halves = []
    for half in (left, right):
        n_h, _, sigma_h = _total_least_squares(x, y, half)
        cos = np.abs(np.einsum("bi,bi->b", n_h, normal))
        angle = np.radians(np.degrees(np.arccos(np.clip(cos, 0.0, 1.0))))
        points = np.count_nonzero(half, axis=1)
        spread = _masked_std(s, half)
        # A direction fitted to n points spread over the given standard deviation along it is
        # known to about sigma / (sqrt(n) spread).
        sigma_angle = sigma_h / np.maximum(np.sqrt(np.maximum(points, 1)) * spread, 1e-12)
        significant = (angle > np.radians(BENT_ANGLE_DEG)) & (angle > 3.0 * sigma_angle)
        halves.append((half, significant, sigma_h, points >= MIN_LINE_POINTS))
    (left, bent_l, sigma_l, ok_l), (right, bent_r, sigma_r, ok_r) = halves
    bent = (count >= 2 * MIN_LINE_POINTS) & ok_l & ok_r & (bent_l | bent_r)
    keep_left = sigma_l <= sigma_r
    return np.where(keep_left[:, None], left, right), bent


def _masked_std(values: FloatArray, mask: NDArray[np.bool_]) -> FloatArray:
    w = mask.astype(np.float64)
    total = np.maximum(w.sum(axis=1), 1e-300)
    mean = (w * values).sum(axis=1) / total
    std: FloatArray = np.sqrt((w * (values - mean[:, None]) ** 2).sum(axis=1) / total)
    return std


def _masked_median(values: FloatArray, mask: NDArray[np.bool_]) -> FloatArray:
    filled = np.where(mask, values, np.inf)
    ordered = np.sort(filled, axis=1)
    count = mask.sum(axis=1)
    rows = np.arange(len(values))
    lo = ordered[rows, np.maximum((count - 1) // 2, 0)]
    hi = ordered[rows, np.maximum(count // 2, 0)]
    return np.where(count > 0, 0.5 * (lo + hi), 0.0)


def _total_least_squares(
    x: FloatArray, y: FloatArray, weight: NDArray[np.bool_]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Each station's line through its weighted points: unit normal (B, 2), offset (B,) and the
    RMS distance of the points to it (B,)."""
    w = weight.astype(np.float64)
    total = np.maximum(w.sum(axis=1), 1e-300)
    mx, my = (w * x).sum(1) / total, (w * y).sum(1) / total
    dx, dy = x - mx[:, None], y - my[:, None]
    sxx, syy, sxy = (w * dx * dx).sum(1), (w * dy * dy).sum(1), (w * dx * dy).sum(1)
    # The normal is the eigenvector of the smaller eigenvalue of [[sxx, sxy], [sxy, syy]].
    angle = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # direction of the line
    normal = np.column_stack([-np.sin(angle), np.cos(angle)])
    rho = normal[:, 0] * mx + normal[:, 1] * my
    residual = (dx * normal[:, :1] + dy * normal[:, 1:]) ** 2
    dof = np.maximum(w.sum(axis=1) - 2, 1)
    sigma = np.sqrt((w * residual).sum(axis=1) / dof)
    return normal, rho, sigma


def _without_cut_off_corners(
    corner: FloatArray, corner_ok: NDArray[np.bool_], pairs: NDArray[np.int64]
) -> NDArray[np.bool_]:
    """Corners a third line cuts off dropped: where lines i and j would meet, but a line k
    crosses both near there, at supported corners at least :data:`CLOSE_CORNERS_M` apart, the
    part is chamfered (k is the chamfer's face) and the meeting of i and j lies in the air; the
    edges are k's two corners. (Closer together, k is a corner rounded by the slice's
    thickness, left to :func:`_strongest_of_close_corners`.)"""
    index = {tuple(pair): p for p, pair in enumerate(pairs.tolist())}
    lines = int(pairs.max()) + 1 if len(pairs) else 0
    ok = corner_ok.copy()
    for p, (i, j) in enumerate(pairs.tolist()):
        for k in range(lines):
            if k in (i, j):
                continue
            ik, jk = index[tuple(sorted((i, k)))], index[tuple(sorted((j, k)))]
            both = corner_ok[:, ik] & corner_ok[:, jk]
            span = np.linalg.norm(corner[:, ik] - corner[:, jk], axis=1)
            reach = np.maximum(
                np.linalg.norm(corner[:, ik] - corner[:, p], axis=1),
                np.linalg.norm(corner[:, jk] - corner[:, p], axis=1),
            )
            ok[:, p] &= ~(both & (span >= CLOSE_CORNERS_M) & (reach <= CORNER_REACH_M))
    return ok


def _strongest_of_close_corners(
    corner: FloatArray,
    corner_ok: NDArray[np.bool_],
    count: NDArray[np.int64],
    pairs: NDArray[np.int64],
) -> NDArray[np.bool_]:
    """Of supported corners within :data:`CLOSE_CORNERS_M` of each other in one slice (a corner
    rounded by the slice's thickness can grow a short third line across it), the one between
    the two best-populated lines only."""
    strength = np.minimum(count[:, pairs[:, 0]], count[:, pairs[:, 1]]).astype(np.float64)
    strength = np.where(corner_ok, strength, -1.0)
    ok = corner_ok.copy()
    for p in range(len(pairs)):
        for q in range(len(pairs)):
            if p == q:
                continue
            close = np.linalg.norm(corner[:, p] - corner[:, q], axis=1) <= CLOSE_CORNERS_M
            weaker = (strength[:, p] < strength[:, q]) | (
                (strength[:, p] == strength[:, q]) & (p > q)
            )
            ok[:, p] &= ~(close & corner_ok[:, q] & weaker)
    return ok


def _without_duplicates(
    normal: FloatArray,
    offset: FloatArray,
    rms: FloatArray,
    line_ok: NDArray[np.bool_],
    members: NDArray[np.bool_],
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Lines that repeat an earlier, stronger one (within :data:`DUPLICATE_ANGLE_DEG` of its
    direction and three noise levels of its offset: the noisy tail of the same face) dropped."""
    line_ok = line_ok.copy()
    members = members.copy()
    lines = normal.shape[1]
    for later in range(1, lines):
        for earlier in range(later):
            cos = np.abs(np.einsum("bi,bi->b", normal[:, later], normal[:, earlier]))
            parallel = cos >= np.cos(np.radians(DUPLICATE_ANGLE_DEG))
            sign = np.sign(np.einsum("bi,bi->b", normal[:, later], normal[:, earlier]))
            apart = np.abs(offset[:, later] - sign * offset[:, earlier])
            near = apart <= 3.0 * np.maximum(rms[:, later], rms[:, earlier])
            same = line_ok[:, later] & line_ok[:, earlier] & parallel & near
            line_ok[:, later] &= ~same
            members[:, later] &= ~same[:, None]
    return line_ok, members


def _without_crests(
    x: FloatArray,
    y: FloatArray,
    members: NDArray[np.bool_],
    normal: FloatArray,
    offset: FloatArray,
    rms: FloatArray,
    count: NDArray[np.int64],
    line_ok: NDArray[np.bool_],
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int64], NDArray[np.bool_]]:
    """Each line refitted without the points that also lie within another line's band: near a
    corner the crest's points sit close to both faces and would pull both lines into the
    corner."""
    band = np.maximum(BAND_SIGMAS * rms, MIN_BAND_M)  # (B, L)
    distance = np.abs(
        x[:, None] * normal[:, :, :1] + y[:, None] * normal[:, :, 1:] - offset[:, :, None]
    )  # (B, L, K)
    near = line_ok[:, :, None] & (distance <= band[:, :, None])
    others = near.sum(axis=1, keepdims=True) - near  # how many other lines claim each point
    clean = members & (others == 0)
    n_clean = np.count_nonzero(clean, axis=2)
    refit = line_ok & (n_clean >= MIN_LINE_POINTS) & (n_clean < count)
    if not np.any(refit):
        return normal, offset, rms, count, members
    normal, offset, rms = normal.copy(), offset.copy(), rms.copy()
    count, members = count.copy(), members.copy()
    for line in range(normal.shape[1]):
        rows = refit[:, line]
        if not np.any(rows):
            continue
        n_l, rho_l, sigma_l = _total_least_squares(x[rows], y[rows], clean[rows, line])
        normal[rows, line], offset[rows, line], rms[rows, line] = n_l, rho_l, sigma_l
        count[rows, line] = n_clean[rows, line]
        members[rows, line] = clean[rows, line]
    return normal, offset, rms, count, members


def _corners(
    x: FloatArray,
    y: FloatArray,
    members: NDArray[np.bool_],
    support: NDArray[np.bool_],
    normal: FloatArray,
    offset: FloatArray,
    rms: FloatArray,
    count: NDArray[np.int64],
    line_ok: NDArray[np.bool_],
    pairs: NDArray[np.int64],
) -> tuple[FloatArray, NDArray[np.bool_], FloatArray, FloatArray]:
    """Where each pair of lines crosses, and whether both lines' points reach it."""
    i, j = pairs[:, 0], pairs[:, 1]
    na, nb = normal[:, i], normal[:, j]  # (B, P, 2)
    det = na[..., 0] * nb[..., 1] - na[..., 1] * nb[..., 0]
    sin_angle = np.abs(det)
    angle = np.degrees(np.arcsin(np.clip(sin_angle, 0.0, 1.0)))
    safe = np.where(sin_angle > 1e-9, det, 1.0)
    ra, rb = offset[:, i], offset[:, j]
    cx = (ra * nb[..., 1] - rb * na[..., 1]) / safe
    cy = (na[..., 0] * rb - nb[..., 0] * ra) / safe
    corner = np.stack([cx, cy], axis=-1)
    ok = line_ok[:, i] & line_ok[:, j] & (angle >= MIN_CORNER_ANGLE_DEG)
    ok &= cx * cx + cy * cy <= PROFILE_RADIUS_M**2
    # Both lines' own points reach the corner and run on from it. (Squared distances: hypot
    # took two thirds of this function's time.)
    dx, dy = x[:, None] - cx[..., None], y[:, None] - cy[..., None]  # (B, P, K)
    d2 = dx * dx + dy * dy
    for line in (i, j):
        mine = support[:, line]  # (B, P, K)
        reach2 = np.where(mine, d2, np.inf).min(axis=2)
        arm2 = np.where(mine, d2, -np.inf).max(axis=2)
        ok &= (reach2 <= CORNER_REACH_M**2) & (arm2 >= MIN_ARM_M**2)
    # Each line is known at the corner to what its points tell there: the offset's variance
    # rms^2 / n, and the direction's, rms^2 / (n var(s)), times the lever from the points'
    # centre out to the corner; the corner moves by that over sin(angle), from each line.
    variances = []
    for line in (i, j):
        mine = members[:, line]
        n_line = normal[:, line]  # (B, P, 2)
        direction = np.stack([-n_line[..., 1], n_line[..., 0]], axis=-1)
        s_points = x[:, None] * direction[..., :1] + y[:, None] * direction[..., 1:]
        s_corner = cx * direction[..., 0] + cy * direction[..., 1]
        weight = mine.astype(np.float64)
        n = np.maximum(weight.sum(axis=2), 1.0)
        mean = (weight * s_points).sum(axis=2) / n
        spread = (weight * (s_points - mean[..., None]) ** 2).sum(axis=2) / n
        sigma2 = rms[:, line] ** 2
        lever = (s_corner - mean) ** 2
        variances.append(sigma2 / n + sigma2 * lever / (n * np.maximum(spread, 1e-12)))
    variance = (variances[0] + variances[1]) / np.maximum(sin_angle, 1e-3) ** 2
    return corner, ok, angle, np.where(ok, variance, np.inf)
