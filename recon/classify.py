"""Classification of path segments: does a segment follow an edge, a surface, or nothing?

:class:`SegmentKind` is a string enum, so a :class:`recon.results.Segment` written to JSON (the
service stores ``dataclasses.asdict(segment)``) reads ``"edge"``, ``"surface"`` or ``"path"``,
and compares equal to those strings.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from recon.arrays import FloatArray
from recon.fitting import gather
from recon.recon_params import ReconParams

if TYPE_CHECKING:
    # For the annotation only: Segment imports this module for SegmentKind, which should not
    # pull in the scan model's Open3D and SciPy.
    from recon.scan_model import ScanModel

#: A segment follows an edge when it runs within this of it, median over the stretch the edge
#: is there: about 2.5 times a hand's error across the path (paper, Sec. VI: std 0.5-1 mm). A trace
#: alongside an edge (on a face next to a wall, a few millimetres off it) runs farther.
EDGE_FOLLOW_DISTANCE_M = 0.0025
#: Edge points within this distance of a segment's points are its candidate edges.
EDGE_CANDIDATE_REACH_M = 0.006


class SegmentKind(enum.StrEnum):
    """What a segment of the path follows in the scan."""

    EDGE = "edge"  #: an edge of the scan (N_S: the thinned edge)
    SURFACE = "surface"  #: a surface of the scan (N_S: nearby scan points)
    PATH = "path"  #: nothing of the scan: reconstructed from the path alone


@dataclass(frozen=True)
class SegmentClass:
    """The classification of one segment.

    Attributes
    ----------
    kind : SegmentKind
    edge_fraction : float
        Mean fraction of edge points among the scan points nearest to the segment's points
        (0 for a segment with no scan near it).
    corners : tuple of int, or None
        The edge an EDGE segment follows: the corners (:attr:`recon.edges.EdgePoints.corner`)
        chosen along it.
    rms_to_edge_m : float
        Typical (median) distance of the segment to that edge, where the edge is there.
    next_edge_m : float
        How far the next candidate corner lay from the chosen one (median where there was one;
        inf when never): how clearly the trace picked its edge.
    """

    kind: SegmentKind
    edge_fraction: float
    corners: tuple[int, ...] | None = None
    rms_to_edge_m: float = float("nan")
    next_edge_m: float = float("nan")


#: The class of every segment when no scan is used.
PATH_ONLY = SegmentClass(SegmentKind.PATH, 0.0)


def classify_segments(
    points_m: FloatArray,
    bounds: list[tuple[int, int]],
    model: ScanModel,
    params: ReconParams,
) -> list[SegmentClass]:
    """Per segment: which edge it follows, else a surface, else nothing of the scan.

    A segment with scan points near less than half of its points has nothing to follow. Else
    the corners of the scan near it (:class:`recon.edges.EdgePoints`) are chosen along it as one
    (:func:`_choose_edge`: near the trace, and without hopping from one edge to the next one
    over); the segment follows them if they run along at least ``params.edge_fraction`` of it,
    and a surface otherwise. Its points without a corner then take the height of the face
    under them.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3), metres
        The path, scan frame.
    bounds : list of (start, stop)
        The segments, ``[start, stop)`` into ``points_m``.
    model : ScanModel
    params : ReconParams
        ``icp_max_distance_m`` is the reach for scan support, ``edge_fraction`` the coverage an
        edge needs.

    Returns
    -------
    list of SegmentClass
        One per segment, in order.
    """
    reach = params.icp_max_distance_m
    dist, _ = model.coarse_tree.query(points_m, k=1, distance_upper_bound=reach, workers=-1)
    supported = np.isfinite(dist)
    candidates = _edge_candidates(points_m, model)
    classes = []
    for start, stop in bounds:
        seg = slice(start, stop)
        if supported[seg].mean() < 0.5:
            classes.append(PATH_ONLY)
            continue
        choice = _choose_edge(candidates, seg, stop - start)
        if choice is not None and choice.coverage >= params.edge_fraction:
            classes.append(
                SegmentClass(
                    SegmentKind.EDGE,
                    choice.coverage,
                    corners=choice.corners,
                    rms_to_edge_m=choice.rms_m,
                    next_edge_m=choice.next_m,
                )
            )
        else:
            coverage = 0.0 if choice is None else choice.coverage
            classes.append(SegmentClass(SegmentKind.SURFACE, coverage))
    return classes


@dataclass(frozen=True)
class _EdgeChoice:
    corners: tuple[int, ...]
    coverage: float
    rms_m: float
    next_m: float


#: Corners within this of a path point are its candidates (at most :data:`CANDIDATES`).
EDGE_CANDIDATE_REACH_M = 0.006
CANDIDATES = 6
#: The choice of corners along a segment (:func:`_choose_edge`) weighs a point's distance to its
#: corner by the hand's error across the path ...
FOLLOW_SIGMA_M = 0.0008
#: ... and the change of that offset from one point to the next by this (a slowly drifting hand
#: on one edge changes it by a few hundredths of a millimetre a step; the scan's corners scatter
#: by a few tenths; the next edge over is millimetres away) ...
OFFSET_STEP_SIGMA_M = 0.00035
#: ... a point with no corner costs what one this far from the trace would ...
NO_CORNER_COST_M = 0.0025
#: ... and leaving or joining the scan's edge costs as much as this many squared sigmas.
ENTER_COST = 4.0


def _edge_candidates(
    points_m: FloatArray, model: ScanModel
) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
    """Per point, the corners of the scan near it: up to :data:`CANDIDATES` distinct corners
    within :data:`EDGE_CANDIDATE_REACH_M`, nearest first.

    Returns
    -------
    ids : ndarray of shape (N, C), int
        :attr:`recon.edges.EdgePoints.corner` of each candidate (-2 where there is none).
    offsets : ndarray of shape (N, C, 3)
        From the point to the corner's nearest sample.
    distances : ndarray of shape (N, C)
        Their lengths (inf where there is none).
    """
    n = len(points_m)
    ids = np.full((n, CANDIDATES), -2, np.int64)
    offsets = np.zeros((n, CANDIDATES, 3))
    distances = np.full((n, CANDIDATES), np.inf)
    if model.edge_tree is None or n == 0:
        return ids, offsets, distances
    edges = model.edges
    k = min(32, len(edges))
    for start in range(0, n, 2048):
        rows = slice(start, min(start + 2048, n))
        dist, idx = model.edge_tree.query(
            points_m[rows], k=k, distance_upper_bound=EDGE_CANDIDATE_REACH_M, workers=-1
        )
        if k == 1:
            dist, idx = dist[:, None], idx[:, None]
        present = np.isfinite(dist)
        corner = np.where(present, gather(edges.corner_labels(), idx, fill_index=len(edges)), -3)
        # The first (nearest) sample of each corner in the row.
        seen_before = np.triu(corner[:, :, None] == corner[:, None, :], k=1).any(axis=1)
        first = present & ~seen_before
        order = np.argsort(~first, axis=1, kind="stable")[:, :CANDIDATES]
        take = np.take_along_axis(first, order, 1)
        chosen_idx = np.take_along_axis(idx, order, 1)
        ids[rows, : order.shape[1]] = np.where(take, np.take_along_axis(corner, order, 1), -2)
        d = np.take_along_axis(dist, order, 1)
        distances[rows, : order.shape[1]] = np.where(take, d, np.inf)
        sample = gather(edges.points_m, chosen_idx, fill_index=len(edges))
        offsets[rows, : order.shape[1]] = np.where(
            take[..., None], sample - points_m[rows][:, None, :], 0.0
        )
    return ids, offsets, distances


#: Steps of the Viterbi pass whose transition costs are computed together (bounds the memory:
#: about 1.3 kB a step).
VITERBI_BLOCK = 4096


def _transitions(offsets: FloatArray, c: int) -> FloatArray:
    """The cost of every move between the candidates (and "none", the last state) of
    consecutive points: offsets (S + 1, c, 3) -> (S, c + 1, c + 1), from x to."""
    step = offsets[1:, None, :, :] - offsets[:-1, :, None, :]  # (S, from, to, 3)
    transitions = np.full((len(step), c + 1, c + 1), ENTER_COST)
    transitions[:, :c, :c] = np.einsum("iabk,iabk->iab", step, step) / OFFSET_STEP_SIGMA_M**2
    transitions[:, c, c] = 0.0
    return transitions


def _choose_edge(
    candidates: tuple[NDArray[np.int64], FloatArray, FloatArray], seg: slice, length: int
) -> _EdgeChoice | None:
    """The corners a segment follows, chosen along it as one: the most likely sequence of
    corners (or none) point by point, where a point pays for its distance to its corner (the
    hand's error), for the change of that offset from the previous point (an edge does not hop
    to the next one over), and for having no corner; a Viterbi pass over the segment.

    Returns
    -------
    _EdgeChoice or None
        The corners chosen (their ids), the share of the segment that has one,
        the median distance to them, and the median distance from them to the next candidate
        corner where there was one (inf when never); None when no point has a corner.
    """
    ids, offsets, distances = candidates[0][seg], candidates[1][seg], candidates[2][seg]
    n = len(ids)
    if n == 0 or not np.isfinite(distances).any():
        return None
    c = ids.shape[1]
    none = c
    emit = np.concatenate(
        [
            np.where(np.isfinite(distances), (distances / FOLLOW_SIGMA_M) ** 2, np.inf),
            np.full((n, 1), (NO_CORNER_COST_M / FOLLOW_SIGMA_M) ** 2),
        ],
        axis=1,
    )
    cost = emit[0].copy()
    back = np.zeros((n, c + 1), np.int64)
    states = np.arange(c + 1)
    for i in range(1, n):
        if (i - 1) % VITERBI_BLOCK == 0:
            # The transition costs of a block of steps at once (the loop is then a few small
            # operations per point: it was a quarter of a second on a 10k-point edge).
            transitions = _transitions(offsets[i - 1 : i + VITERBI_BLOCK], c)
        total = cost[:, None] + transitions[(i - 1) % VITERBI_BLOCK]
        back[i] = np.argmin(total, axis=0)
        cost = total[back[i], states] + emit[i]
    state = np.empty(n, np.int64)
    state[-1] = int(np.argmin(cost))
    for i in range(n - 1, 0, -1):
        state[i - 1] = back[i, state[i]]
    on = state != none
    if not np.any(on):
        return None
    rows = np.flatnonzero(on)
    chosen = ids[rows, state[rows]]
    typical = float(np.median(distances[rows, state[rows]]))
    # How far the next candidate was, where there was one: how clearly the trace chose.
    slots = state[rows]
    gaps = np.linalg.norm(offsets[rows] - offsets[rows, slots][:, None, :], axis=2)  # (R, c)
    rest = np.isfinite(distances[rows]) & (np.arange(c)[None, :] != slots[:, None])
    has_rest = rest.any(axis=1)
    others = np.where(rest, gaps, np.inf).min(axis=1)[has_rest].tolist()
    return _EdgeChoice(
        tuple(sorted({int(x) for x in chosen})),
        float(np.count_nonzero(on)) / length,
        typical,
        float(np.median(others)) if others else float("inf"),
    )
