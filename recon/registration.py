"""Registration of a path to a scan model: the edge or the surface as target, then the
degeneracy-aware ICP (:func:`recon.icp.register_icp`).

A path that follows edges is registered point-to-line to the thinned edge (the edge itself, not
the curvature band, whose centroid lies inside the corner); any other path point-to-plane to the
voxel cloud. Which one is decided *after* trying: a misplaced scanner (a few millimetres, a
degree) can put an edge-following trace farther from the edge than any fixed threshold at the
initial guess, and a path registered to the surface when it follows an edge slides along the
faces and ends up worse than it came in. So when the scan has an edge along the path, both
registrations are run, and the edge wins when the path follows the edge once registered to it;
the result says which was chosen, why, and how the other fared.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from recon.arrays import FloatArray
from recon.classify import EDGE_FOLLOW_DISTANCE_M, SegmentKind, classify_segments
from recon.errors import RegistrationError
from recon.icp import MAX_SOURCE_POINTS, RigidMotion, _across, register_icp
from recon.recon_params import ReconParams
from recon.results import Registration
from recon.scan_model import ScanModel
from recon.transforms import apply_transform

#: The edge is tried as the target when the thinned edge lies within the ICP's pairing distance
#: of at least this fraction of the path ...
EDGE_TARGET_FRACTION = 0.5
#: ... and has at least this many points.
EDGE_TARGET_MIN_POINTS = 10
#: The target not chosen is registered with at most this many path points: its figures are
#: reported, not used, and a thinner path costs proportionally less.
ALTERNATIVE_SOURCE_POINTS = 1000
#: ... and at most this many ICP iterations per stage. The surface of an edge scene leaves the
#: path free to creep along the edge: the surface ICP then ran all 60 + 60 iterations of both
#: stages (0.3 s of a 1.2 s command) for figures that are only reported.
ALTERNATIVE_ITERATIONS = 15
#: At most this many rounds of "register the segments that follow the edge, then look again".
EDGE_PASSES = 3


def register_to_model(
    points_tracker_m: FloatArray,
    model: ScanModel,
    bounds: list[tuple[int, int]],
    params: ReconParams,
    *,
    T_scan_tracker_init: FloatArray,
) -> Registration:
    """Register a path (tracker frame) to a scan model (scan frame), to its edge or its surface.

    The edge is tried when the thinned edge runs near most of the path (within the ICP's pairing
    distance at the initial guess): the path's points on segments that follow an edge at the
    initial guess (all of them if none does yet) are registered point-to-line. It is kept when,
    registered so, at least half of the path's points lie on segments that follow the edge
    (:func:`recon.classify.classify_segments`). Otherwise the whole path is registered
    point-to-plane to the surface.

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
        With ``reason`` (why this target) and the other target's figures when it was tried.

    Raises
    ------
    RegistrationError
        Neither target could be registered to (see :func:`recon.icp.register_icp`).
    """
    points = np.asarray(points_tracker_m, dtype=np.float64)
    edge = _try_edge(points, model, bounds, params, T_scan_tracker_init)
    if edge is not None and edge.following >= EDGE_TARGET_FRACTION:
        # Only for the summary's "how the other fared": a thinner path is plenty for that.
        surface = _try(
            lambda: _register_surface(
                points,
                model,
                params,
                T_scan_tracker_init,
                max_source_points=ALTERNATIVE_SOURCE_POINTS,
                max_iterations=ALTERNATIVE_ITERATIONS,
            )
        )
        return replace(
            edge.registration,
            reason=f"{edge.following * 100:.0f} % of the path follows the scan's edge once "
            "registered to it",
            alternative=_alternative(surface, points, model, bounds, params),
        )
    try:
        surface = _register_surface(points, model, params, T_scan_tracker_init)
    except RegistrationError as error:
        if edge is None:
            raise
        # The surface could not be registered to but the edge could: better than nothing, and
        # said so (the path does not follow the edge well).
        return replace(
            edge.registration,
            reason=f"the surface could not be registered to ({error}); only "
            f"{edge.following * 100:.0f} % of the path follows the edge",
        )
    if edge is None:
        reason = (
            "the scan has no edge along the path"
            if len(model.edges) < EDGE_TARGET_MIN_POINTS
            else "the scan's edge is not near most of the path"
        )
    else:
        reason = (
            f"registered to the edge, only {edge.following * 100:.0f} % of the path would follow it"
        )
    return replace(
        surface,
        reason=reason,
        alternative=None if edge is None else _summary_of(edge.registration, edge.following),
    )


class _EdgeTry:
    def __init__(self, registration: Registration, following: float):
        self.registration = registration
        self.following = following


def _try(make: Callable[..., Registration]) -> Registration | None:
    try:
        return make()
    except RegistrationError:
        return None


def _try_edge(
    points: FloatArray,
    model: ScanModel,
    bounds: list[tuple[int, int]],
    params: ReconParams,
    T_init: FloatArray,
) -> _EdgeTry | None:
    """The edge registration and the fraction of the path that then follows the edge; None
    when the edge is not near enough of the path to try, or its registration fails."""
    edges = model.edges
    if len(edges) < EDGE_TARGET_MIN_POINTS or model.edge_tree is None:
        return None
    start = apply_transform(T_init, points)
    dist, _ = model.edge_tree.query(start, distance_upper_bound=params.icp_max_distance_m)
    if np.mean(np.isfinite(dist)) < EDGE_TARGET_FRACTION:
        return None
    on_edge = _following(start, model, bounds, params)
    registration = None
    # Which segments follow the edge is judged where the path is: a misplaced scanner can hide
    # one leg of a corner at the initial guess, and registering the other leg alone leaves the
    # motion along it free. So register, judge again, and repeat while the set grows.
    for _ in range(EDGE_PASSES):
        use = on_edge if np.count_nonzero(on_edge) >= EDGE_TARGET_MIN_POINTS else None
        source = points if use is None else points[use]
        attempt = _try(
            lambda source=source: register_icp(
                source,
                edges.points_m,
                init_T_target_source=T_init,
                max_distance_m=params.icp_max_distance_m,
                target_directions=edges.directions,
                target_label=SegmentKind.EDGE.value,
                target_tree=model.edge_tree,
            )
        )
        if attempt is None:
            break
        registration = attempt
        moved = apply_transform(registration.T_scan_tracker, points)
        now_on_edge = _following(moved, model, bounds, params)
        grew = np.count_nonzero(now_on_edge & ~on_edge) > 0
        on_edge = now_on_edge
        if use is None or not grew:
            break
    if registration is None:
        return None
    return _EdgeTry(registration, float(np.mean(on_edge)))


def _following(
    points_scan_m: FloatArray,
    model: ScanModel,
    bounds: list[tuple[int, int]],
    params: ReconParams,
) -> np.ndarray:
    """Per point: on a segment that follows the scan's edge (scan frame): its points lie within
    :data:`EDGE_FOLLOW_DISTANCE_M` of the thinned edge, on median, along at least
    ``params.edge_fraction`` of it. (A quick look for choosing the registration's target; which
    corners a segment follows is decided once registered, by :func:`classify_segments`.)"""
    on_edge = np.zeros(len(points_scan_m), dtype=bool)
    if model.edge_tree is None:
        return on_edge
    dist, _ = model.edge_tree.query(
        points_scan_m, distance_upper_bound=EDGE_FOLLOW_DISTANCE_M, workers=-1
    )
    near = np.isfinite(dist)
    for start, stop in bounds:
        if np.mean(near[start:stop]) >= max(params.edge_fraction, 0.5):
            on_edge[start:stop] = True
    return on_edge


def _register_surface(
    points: FloatArray,
    model: ScanModel,
    params: ReconParams,
    T_init: FloatArray,
    *,
    max_source_points: int = MAX_SOURCE_POINTS,
    max_iterations: int = 60,
) -> Registration:
    features = model.features
    return register_icp(
        points,
        features.points_m,
        init_T_target_source=T_init,
        max_distance_m=params.icp_max_distance_m,
        target_normals=features.normals,
        target_label=SegmentKind.SURFACE.value,
        target_tree=model.coarse_tree,
        max_source_points=max_source_points,
        max_iterations=max_iterations,
    )


def _alternative(
    surface: Registration | None,
    points: FloatArray,
    model: ScanModel,
    bounds: list[tuple[int, int]],
    params: ReconParams,
) -> dict[str, Any] | None:
    if surface is None:
        return None
    moved = apply_transform(surface.T_scan_tracker, points)
    return _summary_of(surface, float(np.mean(_following(moved, model, bounds, params))))


def _summary_of(registration: Registration, following: float) -> dict[str, Any]:
    """The figures of a registration that was tried and not chosen."""
    return {
        "target": registration.target,
        "rmse_m": registration.rmse_m,
        "fitness": registration.fitness,
        "constrained_dof": registration.constrained_dof,
        "following_edge": following,
        "path_moved_mean_m": registration.path_moved_mean_m,
    }


def feature_information(
    points_tracker_m: FloatArray,
    model: ScanModel,
    bounds: list[tuple[int, int]],
    params: ReconParams,
    *,
    T_scan_tracker: FloatArray,
    motion: RigidMotion,
) -> FloatArray:
    """What registering a path to the features it follows would learn about each rigid motion.

    The motions with information are the ones that move the path against its features: across
    the edge where a segment follows an edge, along the normal where it follows a surface. Those
    are the motions a calibration must fix for the path to land on its features.

    Parameters
    ----------
    points_tracker_m : ndarray of shape (N, 3)
        The resampled path, tracker frame.
    model : ScanModel
    bounds : list of (start, stop)
    params : ReconParams
    T_scan_tracker : ndarray of shape (4, 4)
        Where the path is relative to the scan.
    motion : RigidMotion
        Twists in the tracker frame that the result is expressed for.

    Returns
    -------
    ndarray of shape (6, 6)
        ``J^T J`` over the path's points, unit weights.
    """
    points = np.asarray(points_tracker_m, dtype=np.float64)
    in_scan = apply_transform(T_scan_tracker, points)
    classes = classify_segments(in_scan, bounds, model, params)
    R = np.asarray(T_scan_tracker, dtype=np.float64)[:3, :3]
    info = np.zeros((6, 6))
    for (start, stop), segment_class in zip(bounds, classes, strict=True):
        here = in_scan[start:stop]
        if segment_class.kind == SegmentKind.EDGE and model.edge_tree is not None:
            _, index = model.edge_tree.query(here, workers=-1)
            axes = _across(model.edges.directions[index])
        elif segment_class.kind == SegmentKind.SURFACE:
            _, index = model.coarse_tree.query(here, workers=-1)
            axes = model.features.normals[index][:, None, :]
        else:
            continue
        # Directions back into the tracker frame, where the twists act.
        jacobian = motion.jacobian(points[start:stop], axes @ R)
        info += np.einsum("pai,paj->ij", jacobian, jacobian)
    return info


__all__ = ["EDGE_FOLLOW_DISTANCE_M", "feature_information", "register_to_model"]
