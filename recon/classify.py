"""Classification of path segments: does a segment follow an edge, a surface, or nothing?

:class:`SegmentKind` is a string enum, so a :class:`recon.types.Segment` written to JSON (the
service stores ``dataclasses.asdict(segment)``) reads ``"edge"``, ``"surface"`` or ``"path"``,
and compares equal to those strings.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from recon.fitting import gather
from recon.types import FloatArray, ReconParams

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
    fell_back : bool
        The scan was near but the path disagreed with it (:func:`check_consistency`): path only.
    tracks : tuple of int, or None
        The edge an EDGE segment follows: the tracks of :class:`recon.edges.EdgePoints` that
        make it up (one edge found in pieces is several tracks).
    rms_to_edge_m : float
        Typical (median) distance of the segment to that edge, where the edge is there.
    next_edge_m : float
        How far the next candidate edge lies from the segment (median; inf when none): how
        clearly the trace picked its edge.
    """

    kind: SegmentKind
    edge_fraction: float
    fell_back: bool = False
    tracks: tuple[int, ...] | None = None
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
    each edge of the scan near it (a track of :class:`recon.edges.EdgePoints`) is weighed as a
    whole: along how much of the segment it runs (its coverage) and how far from the segment
    (median). The segment follows the edge with the largest coverage among those that run within
    :data:`EDGE_FOLLOW_DISTANCE_M` of it, if that coverage is at least ``params.edge_fraction``:
    one edge for the whole segment, never a hop from edge to edge point by point. Otherwise it
    follows a surface.

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
                    tracks=choice.tracks,
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
    tracks: tuple[int, ...]
    coverage: float
    rms_m: float
    next_m: float


def _edge_candidates(points_m: FloatArray, model: ScanModel):
    """Per point and track: the distance to the track's nearest edge point within
    :data:`EDGE_CANDIDATE_REACH_M` (a dict of track -> (N,) distances, inf where absent)."""
    if model.edge_tree is None:
        return {}
    k = min(48, len(model.edges))
    dist, idx = model.edge_tree.query(
        points_m, k=k, distance_upper_bound=EDGE_CANDIDATE_REACH_M, workers=-1
    )
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    tracks = gather(model.edges.track, idx, fill_index=len(model.edges))
    present = np.isfinite(dist)
    out = {}
    for track in np.unique(tracks[present]):
        out[int(track)] = np.where(present & (tracks == track), dist, np.inf).min(axis=1)
    return out


def _choose_edge(candidates, seg: slice, length: int) -> _EdgeChoice | None:
    """The edge a segment follows (see :func:`classify_segments`), or None.

    The track that runs along most of the segment within :data:`EDGE_FOLLOW_DISTANCE_M` of it
    is the edge; other such tracks join it where they continue it (where both are there, they
    lie within :data:`SAME_EDGE_M` of each other as seen from the segment): one edge the scan
    showed in pieces.
    """
    scored = []
    for track, distance in candidates.items():
        here = distance[seg]
        covered = np.isfinite(here)
        if not np.any(covered):
            continue
        # The median: a few stray corners linked into a track do not make the trace leave it.
        typical = float(np.median(here[covered]))
        scored.append((track, covered, typical, here))
    following = [c for c in scored if c[2] <= EDGE_FOLLOW_DISTANCE_M]
    if not following:
        return None
    first = max(following, key=lambda c: (round(float(np.mean(c[1])), 2), -c[2]))
    tracks = [first[0]]
    covered = first[1].copy()
    for track, mine, typical, here in sorted(following, key=lambda c: -np.count_nonzero(c[1])):
        if track == first[0]:
            continue
        both = mine & first[1]
        if np.any(both) and np.median(np.abs(here[both] - first[3][both])) > SAME_EDGE_M:
            continue  # a parallel edge, not this one in another piece
        if typical > max(SAME_EDGE_SLACK * first[2], SAME_EDGE_M):
            continue  # where the edge is not, another one farther from the trace than it
        tracks.append(track)
        covered |= mine
    distances = np.min([c[3] for c in scored if c[0] in tracks], axis=0)
    rms = float(np.median(distances[covered])) if np.any(covered) else float("inf")
    others = [
        c[2] for c in scored if c[0] not in tracks and np.count_nonzero(c[1]) >= 0.25 * length
    ]
    return _EdgeChoice(
        tuple(tracks), float(np.mean(covered)), rms, min(others) if others else float("inf")
    )


#: Two tracks seen from a segment within this of each other (median, where both are there) are
#: one edge ...
SAME_EDGE_M = 0.0012
#: ... and a track where the first is not joins it only if the segment runs no farther from it
#: than this many times (or :data:`SAME_EDGE_M`) from the first.
SAME_EDGE_SLACK = 1.5


#: Once registered, a path that follows an edge runs within a hand's error of it: a segment whose
#: median distance from the thinned edge (or from the surface, along its normal) is above this
#: is not where the scan says its feature is (a wrong registration, another edge), and leaning it
#: onto the scan could make it worse than it came in. A hand's error reaches 2-5 mm at most
#: (paper, Sec. VI); a sloppy trace on a calibrated scanner was measured at 1.6 mm on median.
CONSISTENT_DISTANCE_M = 0.003


def check_consistency(
    points_m: FloatArray,
    bounds: list[tuple[int, int]],
    classes: list[SegmentClass],
    model: ScanModel,
) -> tuple[list[SegmentClass], list[str]]:
    """Segments whose registered path does not agree with the scan fall back to the path alone.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3)
        The registered path, scan frame.
    bounds : list of (start, stop)
    classes : list of SegmentClass
        From :func:`classify_segments`.
    model : ScanModel

    Returns
    -------
    classes : list of SegmentClass
        Path-only (``fell_back``) for every segment that failed the check.
    notes : list of str
        One per fallback, saying why and what to check.
    """
    out, notes = [], []
    for index, ((start, stop), segment_class) in enumerate(zip(bounds, classes, strict=True)):
        here = points_m[start:stop]
        distance = None
        if segment_class.kind == SegmentKind.EDGE and model.edge_tree is not None:
            distance, _ = model.edge_tree.query(here, workers=-1)
            feature = "edge"
        elif segment_class.kind == SegmentKind.SURFACE:
            _, nearest = model.coarse_tree.query(here, workers=-1)
            normals = model.features.normals[nearest]
            offset = here - model.features.points_m[nearest]
            distance = np.abs(np.einsum("ij,ij->i", offset, normals))
            feature = "surface"
        if distance is None or np.median(distance) <= CONSISTENT_DISTANCE_M:
            out.append(segment_class)
            continue
        out.append(SegmentClass(SegmentKind.PATH, segment_class.edge_fraction, fell_back=True))
        notes.append(
            f"segment {index} runs {np.median(distance) * 1e3:.1f} mm from the scan's {feature} "
            f"on median once registered (a hand stays within "
            f"{CONSISTENT_DISTANCE_M * 1e3:.1f} mm): the scan was not used there, the path was "
            "smoothed on its own; check the registration or the calibration"
        )
    return out, notes
