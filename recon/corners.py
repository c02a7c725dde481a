"""Corners of a path: where the trace turns sharply, kept only where the workpiece turns too.

Each segment between corners is reconstructed on its own, so a polynomial never bends around a
corner. But a split costs something: two new segment ends, each fitted from one side only. So a
candidate from the trace (:func:`find_candidates`) becomes a corner only with evidence:

* with a scan, the scan's support (:func:`confirm_with_scan`): edge lines on both sides that turn
  by about as much as the trace and meet near it. Their intersection is the corner, where both
  segments then end, so the robot turns where the workpiece turns;
* without one (or where the scan has no edge), sharpness: the trace turns by the same angle
  whether measured over short or long chords, where a rounded bend of radius R turns by about
  chord / R (:data:`SHARPNESS`), so a bend well above the tremor's scale is never split.

Every candidate's fate is reported (:class:`Corner`), with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from recon.arrays import FloatArray
from recon.fitting import weighted_pca

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

#: Candidates are looked for down to this share of the corner threshold: the trace rounds a
#: corner off (a 60 degree turn can measure 45 over short chords), and the scan's edges, where
#: there is a scan, decide. Without a scan a corner must reach the threshold itself.
CANDIDATE_SHARE = 0.6
#: A corner turns by at most this much more over chords twice as long (a bend of radius R turns
#: by twice as much: 2.0; a sharp corner by the same angle: 1.0; tremor on short chords makes a
#: sharp corner look a little rounder).
SHARPNESS = 1.35
#: The scan's edge lines are fitted to the thinned edge along this stretch of the path on each
#: side of a candidate (from the inner to the outer bound, in metres of arc): within about
#: half an edge-fit ball of the corner the fits reach the other leg (measured on 24 corners:
#: the corner 0.49 mm off at median from 4 mm in, 0.26 mm from 10 mm in).
LINE_STRETCH_M = (0.010, 0.034)
#: Fewest edge samples for each side's line.
MIN_LINE_SAMPLES = 8
#: The two edge lines must pass within this distance of each other (they meet at the corner) ...
MAX_LINE_GAP_M = 0.002
#: ... their corner within this distance of the trace's candidate ...
MAX_CORNER_OFFSET_M = 0.008
#: ... and they must turn by at least this share of the corner threshold (the trace's own turn
#: at a corner is noisy: a hand that hesitates draws a small loop, 170 degrees over short chords).
MIN_TURN_SHARE = 1.0
#: Edge samples within this distance of the path stretch belong to its side's edge line (the
#: path is registered: it is within a millimetre or two of its edge) ...
LINE_REACH_M = 0.004
#: ... if they run within this angle of the stretch's direction (not the other leg's samples).
LINE_DIRECTION_TOLERANCE_DEG = 30.0


def turning_angle_deg(points_m: FloatArray, *, half_window: int) -> FloatArray:
    """Turning angle at every point, measured between chords ``half_window`` points long.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3), metres
        Equidistant path points.
    half_window : int
        Chord length in points. Chords longer than the hand tremor's wavelength keep tremor
        from looking like corners.

    Returns
    -------
    ndarray of shape (N,), degrees
        0 for a straight path, 90 at a right-angle corner; 0 within ``half_window`` of the ends,
        where no chord fits on one side.
    """
    points = np.asarray(points_m, dtype=np.float64)
    n = len(points)
    k = int(half_window)
    if k < 1:
        raise ValueError(f"half_window must be >= 1, got {half_window}")
    angle = np.zeros(n)
    if n <= 2 * k:
        return angle
    incoming = points[k:-k] - points[: -2 * k]
    outgoing = points[2 * k :] - points[k:-k]
    cos = np.einsum("ij,ij->i", incoming, outgoing) / np.maximum(
        np.linalg.norm(incoming, axis=1) * np.linalg.norm(outgoing, axis=1), 1e-300
    )
    angle[k:-k] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return angle


def local_peaks(values: FloatArray, *, height: float, distance: int) -> np.ndarray:
    """Indices of local maxima of at least ``height``, no two closer than ``distance`` (the
    higher one wins), in increasing order. (What ``scipy.signal.find_peaks`` does with these two
    arguments, without importing all of ``scipy.signal`` for it.)

    Parameters
    ----------
    values : ndarray of shape (N,)
    height : float
    distance : int
        At least 1.

    Returns
    -------
    ndarray of int
    """
    v = np.asarray(values, dtype=np.float64)
    if len(v) < 3:
        return np.zeros(0, dtype=np.int64)
    # A plateau counts once, at its middle.
    inner = np.arange(1, len(v) - 1)
    left = v[inner] > v[inner - 1]
    rising = np.flatnonzero(left)
    candidates = []
    for i in inner[rising]:
        j = i
        while j + 1 < len(v) and v[j + 1] == v[i]:
            j += 1
        if j + 1 < len(v) and v[j + 1] < v[i] and v[i] >= height:
            candidates.append((i + j) // 2)
    kept: list[int] = []
    for i in sorted(candidates, key=lambda c: -v[c]):
        if all(abs(i - k) >= distance for k in kept):
            kept.append(i)
    return np.array(sorted(kept), dtype=np.int64)


@dataclass(frozen=True)
class Candidate:
    """A place where the trace turns sharply enough to be a corner.

    Attributes
    ----------
    index : int
        The resampled point where the turn peaks.
    angle_deg : float
        The turn over chords of the corner scale.
    long_angle_deg : float
        The turn over chords twice as long.
    """

    index: int
    angle_deg: float
    long_angle_deg: float

    @property
    def sharp(self) -> bool:
        """Turning no more over longer chords: a corner rather than a rounded bend."""
        return self.long_angle_deg <= SHARPNESS * self.angle_deg


def find_candidates(
    points_m: FloatArray, *, spacing_m: float, angle_deg: float, scale_m: float
) -> list[Candidate]:
    """Where the trace turns by more than :data:`CANDIDATE_SHARE` of ``angle_deg`` over chords of
    ``scale_m``.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3), metres
        Equidistant path points.
    spacing_m : float
        Their spacing.
    angle_deg : float
        The corner threshold on the turning angle.
    scale_m : float
        Chord length for the turning angle; also the smallest distance between two candidates.

    Returns
    -------
    list of Candidate
        In path order.
    """
    k = max(1, int(round(scale_m / spacing_m)))
    angle = turning_angle_deg(points_m, half_window=k)
    long_angle = turning_angle_deg(points_m, half_window=2 * k)
    peaks = local_peaks(angle, height=CANDIDATE_SHARE * angle_deg, distance=2 * k)
    out = []
    for i in peaks:
        # The longer chords' turn, at its own peak near this one (a bend's peak is broad).
        lo, hi = max(0, i - k), min(len(angle), i + k + 1)
        out.append(Candidate(int(i), float(angle[i]), float(long_angle[lo:hi].max())))
    return out


@dataclass(frozen=True)
class EdgeLine:
    """A straight stretch of the scan's edge: a point on it and its unit direction (scan frame).

    Attributes
    ----------
    point_m : ndarray of shape (3,)
    direction : ndarray of shape (3,)
        Pointing away from the corner.
    rms_m : float
        Of the edge samples about the line.
    n_samples : int
    """

    point_m: FloatArray
    direction: FloatArray
    rms_m: float
    n_samples: int


@dataclass(frozen=True)
class Corner:
    """A candidate's fate.

    Attributes
    ----------
    index : int
        Resampled point of the trace's turn.
    angle_deg : float
        The trace's turn.
    split : bool
        Whether the path is split here.
    reason : str
        Why (or why not), in words.
    point_m : ndarray of shape (3,) or None
        Where the scan's edge lines meet (scan frame), when the scan supports the corner.
    lines : tuple of EdgeLine
        The two edge lines (before, after), when the scan supports the corner.
    """

    index: int
    angle_deg: float
    split: bool
    reason: str
    point_m: FloatArray | None = None
    lines: tuple[EdgeLine, ...] = ()


def judge_without_scan(candidate: Candidate, *, angle_deg: float) -> Corner:
    """A candidate where the scan has no say: split only if it turns by ``angle_deg`` or more,
    sharply."""
    if candidate.angle_deg < angle_deg:
        return Corner(
            candidate.index,
            candidate.angle_deg,
            False,
            f"the trace turns {candidate.angle_deg:.0f} deg, less than the corner threshold of "
            f"{angle_deg:.0f} deg, and no scan edge turns there: not split",
        )
    if candidate.sharp:
        return Corner(
            candidate.index,
            candidate.angle_deg,
            True,
            f"the trace turns {candidate.angle_deg:.0f} deg sharply (as much over "
            f"{2:d}x longer chords: {candidate.long_angle_deg:.0f} deg) and no scan edge says "
            "otherwise",
        )
    return Corner(
        candidate.index,
        candidate.angle_deg,
        False,
        f"the trace turns {candidate.angle_deg:.0f} deg but keeps turning over longer chords "
        f"({candidate.long_angle_deg:.0f} deg): a rounded bend, not split",
    )


def confirm_with_scan(
    points_scan_m: FloatArray,
    arc_m: FloatArray,
    candidate: Candidate,
    edge_points_m: FloatArray,
    edge_tree: cKDTree | None,
    *,
    edge_directions: FloatArray,
    angle_deg: float,
    max_offset_m: float = MAX_CORNER_OFFSET_M,
) -> Corner | None:
    """Whether the scan's edges turn where the trace does; None when the scan has no edge line
    on one side of the candidate or both (the scan has no say there).

    Parameters
    ----------
    points_scan_m : ndarray of shape (N, 3)
        The resampled trace, scan frame (registered).
    arc_m : ndarray of shape (N,)
        Its arc length.
    candidate : Candidate
    edge_points_m : ndarray of shape (E, 3)
        The thinned edge, scan frame.
    edge_tree : scipy.spatial.cKDTree or None
        Over ``edge_points_m``.
    edge_directions : ndarray of shape (E, 3)
        The thinned edge's unit directions.
    angle_deg : float
        The corner threshold: the scan's edges must turn at least this much.
    max_offset_m : float
        The scan's corner must lie within this of the trace near the turn (the farthest the
        hand's error explains); farther, it is another corner than the one traced.

    Returns
    -------
    Corner or None
        None when the scan cannot say: no edge line on one side or both.
    """
    if edge_tree is None or len(edge_points_m) == 0:
        return None
    c = candidate.index
    lines = []
    for sign in (-1, 1):
        offset = sign * (arc_m - arc_m[c])
        stretch = (offset >= LINE_STRETCH_M[0]) & (offset <= LINE_STRETCH_M[1])
        lines.append(_edge_line(points_scan_m[stretch], edge_points_m, edge_directions, edge_tree))
    if lines[0] is None and lines[1] is None:
        return None
    first, second = lines
    if first is None or second is None:
        # The path leaves an edge (onto a face, into the air) or the candidate is too near an
        # end for a line: the scan cannot say, the trace's sharpness does.
        return None
    # Each line's direction turned to point away from the corner (towards its samples' centre).
    before, after = (
        EdgeLine(
            line.point_m,
            line.direction * np.sign(np.dot(line.direction, line.point_m - points_scan_m[c])),
            line.rms_m,
            line.n_samples,
        )
        for line in (first, second)
    )
    # The edge's turn: 180 deg less the angle between the two directions pointing away.
    cos_between = float(np.clip(np.dot(before.direction, after.direction), -1.0, 1.0))
    turn = 180.0 - float(np.degrees(np.arccos(cos_between)))
    point, gap = closest_approach(before, after)
    # Across the trace, not along it: where along the path the hand turned is itself uncertain
    # by a few millimetres (a hand rounds a corner).
    near_turn = np.abs(arc_m - arc_m[c]) <= LINE_STRETCH_M[0]
    offset = float(np.min(np.linalg.norm(points_scan_m[near_turn] - point, axis=1)))
    problems = []
    if turn < MIN_TURN_SHARE * angle_deg:
        problems.append(f"the scan's edge turns only {turn:.0f} deg there")
    if gap > MAX_LINE_GAP_M:
        problems.append(f"its two edge lines pass {gap * 1e3:.1f} mm apart")
    if offset > max_offset_m:
        problems.append(f"they meet {offset * 1e3:.1f} mm from the trace's turn")
    if problems:
        return Corner(
            c,
            candidate.angle_deg,
            False,
            f"the trace turns {candidate.angle_deg:.0f} deg but {', and '.join(problems)}: "
            "not split",
        )
    return Corner(
        c,
        candidate.angle_deg,
        True,
        f"the scan's edges turn {turn:.0f} deg and meet {offset * 1e3:.1f} mm from the trace's "
        f"turn of {candidate.angle_deg:.0f} deg: both segments end where they meet",
        point_m=point,
        lines=(before, after),
    )


def _edge_line(
    path_stretch_m: FloatArray,
    edge_points_m: FloatArray,
    edge_directions: FloatArray,
    edge_tree: cKDTree,
) -> EdgeLine | None:
    """A line fitted to the thinned edge along a stretch of the path (samples near it that run
    its way); None with too few samples."""
    if len(path_stretch_m) < 2:
        return None
    near = edge_tree.query_ball_point(path_stretch_m, r=LINE_REACH_M)
    index = np.unique(np.concatenate([np.asarray(i, dtype=np.int64) for i in near]))
    way = path_stretch_m[-1] - path_stretch_m[0]
    way /= max(float(np.linalg.norm(way)), 1e-12)
    along = np.abs(edge_directions[index] @ way)
    index = index[along >= np.cos(np.radians(LINE_DIRECTION_TOLERANCE_DEG))]
    if len(index) < MIN_LINE_SAMPLES:
        return None
    samples = edge_points_m[index]
    keep = np.ones(len(samples), dtype=bool)
    for _ in range(2):  # robust: refit without samples beyond three sigma of the line
        pca = weighted_pca(samples[None], keep[None].astype(np.float64))
        centre, direction = pca.mean[0], pca.axes[0, :, 0]
        rel = samples - centre
        off = rel - np.outer(rel @ direction, direction)
        distance = np.linalg.norm(off, axis=1)
        rms = float(np.sqrt(np.mean(distance[keep] ** 2)))
        keep = distance <= 3.0 * max(rms, 1e-5)
    if np.count_nonzero(keep) < MIN_LINE_SAMPLES:
        return None
    return EdgeLine(centre, direction, rms, int(np.count_nonzero(keep)))


def closest_approach(a: EdgeLine, b: EdgeLine) -> tuple[FloatArray, float]:
    """Midpoint of the closest approach of two lines, and their distance there (inf for
    parallel lines)."""
    w = a.point_m - b.point_m
    da, db = a.direction, b.direction
    aa, ab, bb = da @ da, da @ db, db @ db
    det = aa * bb - ab * ab
    if det < 1e-9:  # parallel: no corner
        return 0.5 * (a.point_m + b.point_m), float("inf")
    s = (ab * (db @ w) - bb * (da @ w)) / det
    t = (aa * (db @ w) - ab * (da @ w)) / det
    pa, pb = a.point_m + s * da, b.point_m + t * db
    return 0.5 * (pa + pb), float(np.linalg.norm(pa - pb))


def lines_to_edge_samples(
    corner: Corner, *, reach_m: float, spacing_m: float
) -> tuple[FloatArray, FloatArray]:
    """Samples of a confirmed corner's two edge lines, from the corner out to ``reach_m``:
    the stretch where the scan's own edge fits span three faces and are missing.

    Returns
    -------
    points, directions : ndarrays of shape (S, 3)
    """
    if corner.point_m is None:
        return np.zeros((0, 3)), np.zeros((0, 3))
    steps = np.arange(0.0, reach_m + 1e-12, spacing_m)
    points, directions = [], []
    for line in corner.lines:
        # Start on the line itself, at the foot of the corner point.
        foot = line.point_m + ((corner.point_m - line.point_m) @ line.direction) * line.direction
        points.append(foot + np.outer(steps, line.direction))
        directions.append(np.tile(line.direction, (len(steps), 1)))
    return np.concatenate(points), np.concatenate(directions)
