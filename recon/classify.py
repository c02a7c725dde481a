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

#: A segment whose points lie this close (median) to the thinned edge follows it: 2.5 times
#: the operator's typical error (paper, Sec. VI: std 0.5-1 mm).
EDGE_FOLLOW_DISTANCE_M = 0.0025


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
    """

    kind: SegmentKind
    edge_fraction: float
    fell_back: bool = False


#: The class of every segment when no scan is used.
PATH_ONLY = SegmentClass(SegmentKind.PATH, 0.0)


def classify_segments(
    points_m: FloatArray,
    bounds: list[tuple[int, int]],
    model: ScanModel,
    params: ReconParams,
) -> list[SegmentClass]:
    """Per segment: follows an edge, a surface, or nothing of the scan.

    The paper's rule: a segment follows an edge when a large fraction (``edge_fraction``) of the
    scan points nearest to it are edge points. Curvature flags thin out as scan noise grows
    (at 1.5 mm the fraction on a traced right-angle ridge fell to 0.48), so a segment also
    follows an edge when the thinned edge (the fitted intersection of two faces) runs within
    :data:`EDGE_FOLLOW_DISTANCE_M` of it on median. Either way it must have thinned edge points
    along at least half of it. A segment with scan points near less than half of its points has
    nothing to follow.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3), metres
        The path, scan frame.
    bounds : list of (start, stop)
        The segments, ``[start, stop)`` into ``points_m``.
    model : ScanModel
    params : ReconParams
        ``icp_max_distance_m`` is the reach for scan support, ``radius_m`` for thinned-edge
        support, ``edge_fraction`` the paper's threshold.

    Returns
    -------
    list of SegmentClass
        One per segment, in order.
    """
    reach = params.icp_max_distance_m
    dist, idx = model.coarse_tree.query(points_m, k=5, distance_upper_bound=reach, workers=-1)
    near = np.isfinite(dist)
    n_coarse = model.coarse_tree.n
    is_edge = gather(model.features.is_edge.astype(np.float64), idx, n_coarse) > 0.5
    supported = near.any(axis=1)
    point_fraction = (is_edge & near).sum(axis=1) / np.maximum(near.sum(axis=1), 1)
    if model.edge_tree is not None:
        edge_dist, _ = model.edge_tree.query(points_m, distance_upper_bound=params.radius_m)
    else:
        edge_dist = np.full(len(points_m), np.inf)
    edge_near = np.isfinite(edge_dist)
    classes = []
    for start, stop in bounds:
        seg = slice(start, stop)
        if supported[seg].mean() < 0.5:
            classes.append(PATH_ONLY)
            continue
        fraction = float(point_fraction[seg][supported[seg]].mean())
        on_thinned_edge = np.median(edge_dist[seg]) <= EDGE_FOLLOW_DISTANCE_M
        if (fraction >= params.edge_fraction or on_thinned_edge) and edge_near[seg].mean() >= 0.5:
            classes.append(SegmentClass(SegmentKind.EDGE, fraction))
        else:
            classes.append(SegmentClass(SegmentKind.SURFACE, fraction))
    return classes


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
