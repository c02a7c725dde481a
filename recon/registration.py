"""Registration of a path to a scan model: edge or surface target, then the degeneracy-aware ICP.

A path that mostly follows edges is registered point-to-line to the thinned edge (the edge itself,
not the curvature band, whose centroid lies inside the corner); any other path point-to-plane to
the voxel cloud. The ICP is :func:`recon.icp.register_icp`.
"""

from __future__ import annotations

import numpy as np

from recon.classify import SegmentKind, classify_segments
from recon.icp import register_icp
from recon.scan_model import ScanModel
from recon.transforms import apply_transform
from recon.types import FloatArray, ReconParams, Registration

#: A path is registered to the edge when at least this fraction of its points lie on segments
#: that follow an edge ...
EDGE_TARGET_FRACTION = 0.5
#: ... and the thinned edge has at least this many points.
EDGE_TARGET_MIN_POINTS = 10


def register_to_model(
    points_tracker_m: FloatArray,
    model: ScanModel,
    bounds: list[tuple[int, int]],
    params: ReconParams,
    *,
    T_scan_tracker_init: FloatArray,
) -> Registration:
    """Register a path (tracker frame) to a scan model (scan frame).

    The segments are classified at the initial transform (:func:`recon.classify
    .classify_segments`); the path's edge-following points are registered to the thinned edge
    when they are most of the path and the edge has points enough, else the whole path to the
    surface.

    Parameters
    ----------
    points_tracker_m : ndarray of shape (N, 3), metres
        The resampled trace, tracker frame.
    model : ScanModel
        Built around the trace mapped by ``T_scan_tracker_init``.
    bounds : list of (start, stop)
        The path's segments.
    params : ReconParams
        ``icp_max_distance_m`` is the pairing distance of the ICP's first stage.
    T_scan_tracker_init : ndarray of shape (4, 4)
        Initial guess.

    Returns
    -------
    Registration

    Raises
    ------
    RegistrationError
        See :func:`recon.icp.register_icp`.
    """
    points = np.asarray(points_tracker_m, dtype=np.float64)
    path_in_scan = apply_transform(T_scan_tracker_init, points)
    classes = classify_segments(path_in_scan, bounds, model, params)
    on_edge = np.zeros(len(points), dtype=bool)
    for (start, stop), segment_class in zip(bounds, classes, strict=True):
        on_edge[start:stop] |= segment_class.kind == SegmentKind.EDGE
    edges, features = model.edges, model.features
    if (
        np.count_nonzero(on_edge) >= EDGE_TARGET_FRACTION * len(points)
        and len(edges) >= EDGE_TARGET_MIN_POINTS
    ):
        return register_icp(
            points[on_edge],
            edges.points_m,
            init_T_target_source=T_scan_tracker_init,
            max_distance_m=params.icp_max_distance_m,
            target_directions=edges.directions,
            target_label=SegmentKind.EDGE.value,
        )
    return register_icp(
        points,
        features.points_m,
        init_T_target_source=T_scan_tracker_init,
        max_distance_m=params.icp_max_distance_m,
        target_normals=features.normals,
        target_label=SegmentKind.SURFACE.value,
    )
