"""The reconstruction pipeline (the paper's Algorithms 1 and 2): it wires the stages together.

resample (:mod:`recon.resample`) -> split at corners (:mod:`recon.segment`) -> scan model near
the trace (:mod:`recon.scan_model`) -> registration (:mod:`recon.registration`) -> what each
segment follows (:mod:`recon.classify`) -> the method per segment (:mod:`recon.methods.paper`,
Eq. 4 of the paper, or :mod:`recon.methods.anchored`, ours) -> one :class:`Reconstruction`.

With a scan, the work is done in the scan frame (every fit is rigid-equivariant) and only the
result is mapped back to the tracker frame: cheaper than moving the scan and rebuilding its trees.
The result carries the transform and the scan model it used, so that planning reuses them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from recon.arrays import FloatArray
from recon.classify import PATH_ONLY, SegmentClass, SegmentKind, classify_segments
from recon.corners import (
    Candidate,
    Corner,
    EdgeLine,
    closest_approach,
    confirm_with_scan,
    find_candidates,
    judge_without_scan,
    lines_to_edge_samples,
)
from recon.errors import DegenerateInputError, UnitsMismatchError
from recon.fusion import FusedTrace, fuse_traces
from recon.icp import RigidMotion
from recon.inputs import Recording, Scan
from recon.methods.anchored import CONTINUE_PAST_END_M, anchored_segment
from recon.methods.common import HAND_ERROR_PRIOR_M, SegmentResult
from recon.methods.paper import paper_segment
from recon.recon_params import Method, ReconParams
from recon.registration import register_to_model
from recon.resample import ResampledPath, resample_equidistant
from recon.results import (
    CornerReport,
    DemonstrationReport,
    PointReason,
    Reconstruction,
    Registration,
    Segment,
)
from recon.scan_model import ScanModel, build_scan_model
from recon.segment import split_at
from recon.touches import (
    INITIAL_GUESS_SIGMA_M,
    ROUGH_GUESS_SIGMA_M,
    TouchRegistration,
    judge_at_path,
    register_touches,
)
from recon.touches import touch_advice as motion_advice
from recon.transforms import apply_transform, check_rigid, invert_transform

#: One segment's reconstruction: ``method(points, kind, model or None, params, N_P half-width, *,
#: prior_variance_m2, placement_variance_m2, corners)`` -> SegmentResult (see
#: :func:`recon.methods.anchored.anchored_segment`).
SegmentMethod = Callable[..., SegmentResult]
#: The methods by ``ReconParams.method``.
METHODS: dict[Method, SegmentMethod] = {"paper": paper_segment, "anchored": anchored_segment}


def check_scales(path_m: FloatArray, scan_m: FloatArray | None) -> None:
    """Refuse sizes that look like a unit mix-up (metres read as millimetres or the reverse).

    Raises
    ------
    UnitsMismatchError
        A path longer than 50 m across (a millimetre file read as metres), or path and scan
        sizes a factor of 200 or more apart.
    """
    extent = float(np.linalg.norm(np.ptp(path_m, axis=0)))
    if extent > 50.0:
        raise UnitsMismatchError(
            f"the path spans {extent:.0f} m, far more than a robot reaches: it is probably in "
            "millimetres; pass units='mm' (--units mm)"
        )
    if scan_m is None or len(scan_m) == 0:
        return
    scan_extent = float(np.linalg.norm(np.ptp(scan_m, axis=0)))
    if extent > 0 and scan_extent > 0:
        ratio = scan_extent / extent
        if ratio > 200 or ratio < 1 / 200:
            raise UnitsMismatchError(
                f"the scan spans {scan_extent:.4g} and the path {extent:.4g} (same units assumed), "
                f"a factor of {max(ratio, 1 / ratio):.0f} apart: one of them is probably in "
                "millimetres and the other in metres; convert one before reconstructing"
            )


@dataclass(frozen=True)
class SegmentPlan:
    """The resampled path, where it may turn a corner, and its segments.

    Attributes
    ----------
    resampled : ResampledPath
    bounds : list of (start, stop)
        Segments split at every corner candidate (``[start, stop)``, sharing corners, never
        spanning two pieces of the trace): what registration classifies before the corners are
        judged.
    half_width : int
        N_P's half-width in points.
    piece : ndarray of shape (N,), int
        The piece of each resampled point.
    piece_bounds : list of (start, stop)
        Each piece's points.
    candidates : list of Candidate
        Where the trace turns sharply (indices into ``resampled``).
    """

    resampled: ResampledPath
    bounds: list[tuple[int, int]]
    half_width: int
    piece: NDArray[np.int64]
    piece_bounds: list[tuple[int, int]]
    candidates: list[Candidate]

    def split(self, corners: list[int]) -> list[tuple[int, int]]:
        """The pieces split at the given corner indices."""
        bounds = []
        for start, stop in self.piece_bounds:
            inside = np.array([c - start for c in corners if start < c < stop - 1], np.int64)
            bounds += [(start + a, start + b) for a, b in split_at(stop - start, inside)]
        return bounds


def plan_segments(recording: Recording, params: ReconParams) -> SegmentPlan:
    """Algorithm 1's path part: resample equidistantly and find where the trace turns sharply,
    piece by piece (the stretch between two pieces was not traced: nothing is resampled across
    it).

    Raises
    ------
    DegenerateInputError
        Too few points after resampling for a fit of ``params.degree``.
    """
    pieces = recording.pieces()
    parts = [
        _resample(piece, params, "the path" if len(pieces) == 1 else f"piece {k} of the path")
        for k, piece in enumerate(pieces)
    ]
    candidates: list[Candidate] = []
    piece_bounds: list[tuple[int, int]] = []
    offset = 0
    for part in parts:
        found = find_candidates(
            part.points_m,
            spacing_m=part.spacing_m,
            angle_deg=params.corner_angle_deg,
            scale_m=params.corner_scale_m,
        )
        candidates += [replace(c, index=c.index + offset) for c in found]
        piece_bounds.append((offset, offset + len(part.points_m)))
        offset += len(part.points_m)
    resampled = parts[0] if len(parts) == 1 else _joined(parts)
    plan = SegmentPlan(
        resampled=resampled,
        bounds=[],
        half_width=max(1, int(round(params.radius_m / resampled.spacing_m))),
        piece=np.repeat(np.arange(len(parts)), [len(p.points_m) for p in parts]),
        piece_bounds=piece_bounds,
        candidates=candidates,
    )
    return replace(plan, bounds=plan.split([c.index for c in candidates]))


def _resample(recording: Recording, params: ReconParams, label: str) -> ResampledPath:
    resampled = resample_equidistant(
        recording.points_m,
        spacing_m=params.spacing_m,
        t_s=recording.t_s,
        orientations_xyzw=recording.orientations_xyzw,
    )
    n = len(resampled.points_m)
    if n < params.degree + 2:
        raise DegenerateInputError(
            f"{label} has only {n} points after resampling at "
            f"{params.spacing_m * 1000:.2f} mm; a degree-{params.degree} fit needs at least "
            f"{params.degree + 2}: record a longer trace or lower the spacing"
        )
    return resampled


def _joined(parts: list[ResampledPath]) -> ResampledPath:
    """Resampled pieces end to end; arc length runs on across the untraced gaps (it measures the
    traced path only)."""

    def stacked(name: str) -> NDArray[Any] | None:
        values = [getattr(p, name) for p in parts]
        return None if any(v is None for v in values) else np.concatenate(values)

    lengths = np.cumsum([0.0] + [p.arc_length_m[-1] for p in parts[:-1]])
    return ResampledPath(
        points_m=np.concatenate([p.points_m for p in parts]),
        arc_length_m=np.concatenate(
            [p.arc_length_m + s for p, s in zip(parts, lengths, strict=True)]
        ),
        spacing_m=min(p.spacing_m for p in parts),
        t_s=stacked("t_s"),
        n_duplicates=sum(p.n_duplicates for p in parts),
        orientations_xyzw=stacked("orientations_xyzw"),
    )


def reconstruct(
    path: Recording | FloatArray | Sequence[Recording],
    scan: Scan | None = None,
    *,
    params: ReconParams | None = None,
    T_scan_tracker_init: FloatArray | None = None,
    touches: TouchRegistration | None = None,
) -> Reconstruction:
    """Reconstruct a traced path, using the scan's structure where there is one.

    Parameters
    ----------
    path : Recording, ndarray of shape (N, 3), metres, or sequence of Recording
        The trace, tracker frame. A recording in pieces (``Recording.piece``) is resampled and
        fitted piece by piece (no segment spans two), with one registration for all of them.
        Several recordings are demonstrations of one path: they are fused first
        (:func:`recon.fusion.fuse_traces`; an outlier is left out and named) and the fused
        trace, with its known variance, is reconstructed.
    scan : Scan, optional
        The workpiece, scan frame. Without it (or with ``alpha=1``) only the path is used, as in
        the paper's Fig. 8.
    params : ReconParams, optional
    T_scan_tracker_init : ndarray of shape (4, 4), optional
        Known or approximate transform from tracker to scan frame (a stored calibration);
        identity if not given. Registration refines it unless ``params.register`` is False.
    touches : TouchRegistration, optional
        The scanner registered by touching the workpiece (:mod:`recon.touches`): its transform
        is used as it is (the trace is not registered, so its drift stays out of the transform),
        after checking that the touches fix every motion the traced features need.

    Returns
    -------
    Reconstruction
        In the tracker frame, one point per resampled input point, with the ``T_scan_tracker``
        and the ``scan_model`` (scan frame) that were used.

    Raises
    ------
    ValueError
        Malformed arguments.
    DegenerateInputError, NoOverlapError, UnitsMismatchError, RegistrationError
        See :mod:`recon.errors`.
    TouchesInsufficientError
        The touches leave the scan's placement uncertain by more than
        ``params.uncertainty_tolerance_m`` (1 sigma) at the path, across its features.
    """
    params = params or ReconParams()
    notes: list[str] = []
    fused = None
    if isinstance(path, Sequence) and not isinstance(path, np.ndarray):
        recordings = list(path)
        if not recordings or not all(isinstance(r, Recording) for r in recordings):
            raise ValueError("path must be a recording, an (N, 3) array or a list of recordings")
        for r in recordings:
            check_scales(r.points_m, None if scan is None else scan.points_m)
        if len(recordings) > 1:
            fused = fuse_traces(recordings, spacing_m=params.spacing_m)
            notes += fused.notes
            if any(r.orientations_xyzw is not None for r in recordings):
                notes.append(
                    "the fused trace keeps no pen orientations (demonstrations at different "
                    "speeds share no clock): take the tool axis from the scan or a fixed one"
                )
            path = fused.recording
        else:
            path = recordings[0]
    recording = path if isinstance(path, Recording) else Recording(points_m=path)
    check_scales(recording.points_m, None if scan is None else scan.points_m)
    plan = plan_segments(recording, params)
    resampled, bounds, half_width = plan.resampled, plan.bounds, plan.half_width
    points = resampled.points_m
    # What the trace alone is known to be off by, across the path: the fused demonstrations'
    # variance (two of its three axes) where there are several, else the hand-error prior.
    prior = None if fused is None else _prior_from_fusion(fused, resampled)

    registration: Registration | None = None
    model: ScanModel | None = None
    T_scan_tracker: FloatArray | None = None
    if scan is not None and params.uses_scan and touches is not None:
        model = build_scan_model(scan, apply_transform(touches.T_scan_tracker, points), params)
        registration = touch_registration(
            points, touches, model, bounds, params, T_scan_tracker_init=T_scan_tracker_init
        )
        T_scan_tracker = registration.T_scan_tracker
    elif scan is not None and params.uses_scan:
        prepared = prepare_scan_model(
            points, scan, bounds, params, T_scan_tracker_init=T_scan_tracker_init
        )
        model, T_scan_tracker = prepared.model, prepared.T_scan_tracker
        registration = prepared.registration
    work_points = points if T_scan_tracker is None else apply_transform(T_scan_tracker, points)

    corners = judge_corners(plan, work_points, model, params)
    bounds = plan.split([c.index for c in corners if c.split])
    if model is not None:
        model = with_corner_edges(model, corners)
        classes = classify_segments(work_points, bounds, model, params)
    else:
        classes = [PATH_ONLY] * len(bounds)

    # How far off the scan is placed under each point, apart from the hand's error (a registration
    # to the trace took the hand's rigid drift into the transform: what is left is in the prior).
    placement_variance = transform_sigma_m(registration, points) ** 2
    results = []
    segments = []
    method = METHODS[params.method]
    for (start, stop), segment_class in zip(bounds, classes, strict=True):
        kind = segment_class.kind
        seg_points = work_points[start:stop]
        segments.append(
            Segment(start=start, stop=stop, kind=kind, edge_fraction=segment_class.edge_fraction)
        )
        if len(seg_points) < 3:
            results.append(SegmentResult.unchanged(seg_points))
            notes.append(f"segment {len(segments) - 1} has {len(seg_points)} points: left as is")
            continue
        results.append(
            method(
                seg_points,
                kind,
                model,
                params,
                half_width,
                prior_variance_m2=None if prior is None else prior[start:stop],
                placement_variance_m2=placement_variance[start:stop],
                corners=segment_class.corners,
            )
        )
        if kind == SegmentKind.PATH and model is not None:
            notes.append(f"segment {len(segments) - 1} has no scan near it: path only")
        segments[-1] = _with_evidence(segments[-1], segment_class, results[-1])
    if model is not None:
        notes += evidence_notes(segments, results, resampled.arc_length_m)
    join_at_corners(
        bounds,
        results,
        corners,
        [c.kind for c in classes],
        work_points,
        spacing_m=resampled.spacing_m,
        beta=params.beta,
    )
    if T_scan_tracker is not None:
        T_tracker_scan = invert_transform(T_scan_tracker)
        for result in results:
            result.points = apply_transform(T_tracker_scan, result.points)
        corners = [
            c
            if c.point_m is None
            else replace(c, point_m=apply_transform(T_tracker_scan, c.point_m[None])[0])
            for c in corners
        ]

    return _assemble(
        resampled,
        bounds,
        segments,
        results,
        registration,
        params,
        notes,
        T_scan_tracker=T_scan_tracker,
        scan_model=model,
        piece=plan.piece,
        corners=corners,
        demonstrations=() if fused is None else fused.traces,
        prior=prior,
    )


def _with_evidence(segment: Segment, segment_class: SegmentClass, result: SegmentResult) -> Segment:
    """The segment with its edge's evidence and the share of its points that fell back."""
    fell = np.isin(result.reason, [int(r) for r in PointReason if r.fallen_back])
    distance = segment_class.rms_to_edge_m
    next_edge = segment_class.next_edge_m
    return replace(
        segment,
        edge_distance_m=float(distance) if np.isfinite(distance) else None,
        next_edge_m=float(next_edge) if np.isfinite(next_edge) else None,
        fallen_back=float(np.mean(fell)) if len(fell) else 0.0,
    )


def evidence_notes(
    segments: list[Segment], results: list[SegmentResult], arc_m: FloatArray
) -> list[str]:
    """What the summary says of where the scan's evidence failed and of the ends.

    Parameters
    ----------
    segments : list of Segment
        With their evidence (see :func:`_with_evidence`).
    results : list of SegmentResult
        One per segment.
    arc_m : ndarray of shape (N,)
        Arc length of the resampled points.

    Returns
    -------
    list of str
        A line per segment whose points fell back more than :data:`recon.results.DISTRUST_SHARE`
        ("scan not trusted here", with where and why), and a line per end that was continued
        past the end of the scan's edge or left to the trace there.
    """
    notes = []
    mm = 1e3
    for index, (segment, result) in enumerate(zip(segments, results, strict=True)):
        if not segment.scan_trusted:
            counts = np.bincount(result.reason.astype(np.int64), minlength=len(PointReason))
            why = ", ".join(
                f"{count} {PointReason(code).label.replace('_', ' ')}"
                for code, count in enumerate(counts)
                if count and PointReason(code).fallen_back
            )
            notes.append(
                f"segment {index} (points {segment.start}-{segment.stop - 1}, "
                f"{arc_m[segment.start] * mm:.0f}-{arc_m[segment.stop - 1] * mm:.0f} mm along "
                f"the path): scan not trusted here, {segment.fallen_back * 100:.0f} % of its "
                f"points kept the trace ({why}); the scan does not show its feature clearly "
                "there (look at the scan, or trace it again)"
            )
    for label, which, reasons in (
        ("start", "first", results[0].reason),
        ("end", "last", results[-1].reason[::-1]),
    ):
        # The run of points past the edge's end, from the path's end inward.
        beyond = (reasons == PointReason.CONTINUED) | (reasons == PointReason.PAST_END)
        run = len(beyond) if beyond.all() else int(np.argmin(beyond))
        if not run:
            continue
        continued = int(np.count_nonzero(reasons[:run] == PointReason.CONTINUED))
        left = run - continued
        done = []
        if continued:
            done.append(f"{continued} continued along the scan's edge line")
        if left:
            done.append(
                f"{left} left to the trace (beyond the "
                f"{CONTINUE_PAST_END_M * mm:.0f} mm it is continued)"
            )
        notes.append(
            f"the trace runs on past the scan's edge at its {label}: of its {which} {run} "
            f"point{'s' if run > 1 else ''}, {' and '.join(done)}"
        )
    return notes


def _prior_from_fusion(fused: FusedTrace, resampled: ResampledPath) -> FloatArray:
    """The fused variance at the resampled points (by arc length), across the path."""
    fused_points = fused.recording.points_m
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(fused_points, axis=0), axis=1))))
    variance = np.interp(resampled.arc_length_m, arc, fused.variance_m2)
    prior: FloatArray = variance * (2.0 / 3.0)
    return prior


def transform_sigma_m(
    registration: Registration | None, points_tracker_m: FloatArray
) -> FloatArray:
    """1-sigma error the registration's covariance alone gives each point (zero when unknown).

    Parameters
    ----------
    registration : Registration or None
    points_tracker_m : ndarray of shape (N, 3)

    Returns
    -------
    ndarray of shape (N,), metres
    """
    points = np.asarray(points_tracker_m, dtype=np.float64)
    if (
        registration is None
        or registration.covariance is None
        or registration.motion_centre_m is None
        or registration.motion_length_m is None
    ):
        return np.zeros(len(points))
    motion = RigidMotion(registration.motion_centre_m, registration.motion_length_m)
    in_scan = apply_transform(registration.T_scan_tracker, points)
    return motion.point_sigma(registration.covariance, in_scan)


def registration_sigma_m(
    registration: Registration | None,
    points_tracker_m: FloatArray,
    *,
    hand_variance_m2: FloatArray | None = None,
) -> FloatArray:
    """1-sigma error the registration's uncertainty gives each point (zero when unknown).

    Parameters
    ----------
    registration : Registration or None
    points_tracker_m : ndarray of shape (N, 3)
    hand_variance_m2 : ndarray of shape (N,), optional
        What the trace is known to be off by across the path (the fused demonstrations'
        variance); :data:`HAND_ERROR_PRIOR_M` squared when not given. A registration to the
        trace is at least this uncertain.

    Returns
    -------
    ndarray of shape (N,), metres
    """
    points = np.asarray(points_tracker_m, dtype=np.float64)
    sigma = transform_sigma_m(registration, points)
    if registration is not None and registration.target != "touches":
        # Registered to the trace itself: the rigid part of the hand's slow drift went into the
        # transform, and the residuals cannot show it (measured: the transform's error at the
        # path was 2-4 times what the residuals' covariance gives). It is as large as the
        # hand's error (the fused demonstrations' where there are several).
        hand = (
            HAND_ERROR_PRIOR_M
            if hand_variance_m2 is None
            else np.sqrt(np.asarray(hand_variance_m2, dtype=np.float64))
        )
        sigma = np.maximum(sigma, hand)
    return sigma


def judge_corners(
    plan: SegmentPlan, points_m: FloatArray, model: ScanModel | None, params: ReconParams
) -> list[Corner]:
    """Each corner candidate judged: by the scan's edges where it has some there, else by its
    sharpness (see :mod:`recon.corners`).

    Parameters
    ----------
    plan : SegmentPlan
    points_m : ndarray of shape (N, 3)
        The resampled trace, in the scan frame when there is a model.
    model : ScanModel or None
    params : ReconParams

    Returns
    -------
    list of Corner
        One per candidate, in path order.
    """
    arc = plan.resampled.arc_length_m
    out = []
    for candidate in plan.candidates:
        judged = None
        if model is not None:
            judged = confirm_with_scan(
                points_m,
                arc,
                candidate,
                model.edges.points_m,
                model.edge_tree,
                edge_directions=model.edges.directions,
                angle_deg=params.corner_angle_deg,
                max_offset_m=params.evidence_sigmas * HAND_ERROR_PRIOR_M,
            )
        if judged is None:
            judged = judge_without_scan(candidate, angle_deg=params.corner_angle_deg)
        out.append(judged)
    return out


def with_corner_edges(model: ScanModel, corners: list[Corner]) -> ScanModel:
    """The model with the scan's confirmed corners' edge lines sampled up to the corners.

    Near a corner the edge fits span three faces and are left out of the thinned edge, which
    would leave each segment's last stretch to extrapolate; the two edge lines that met there
    fill it, so both segments follow their edge to where the edges meet.
    """
    confirmed = [c for c in corners if c.split and c.point_m is not None]
    located = [c.point_m for c in confirmed if c.point_m is not None]  # the same, for the types
    if not confirmed:
        return model
    extra = [
        lines_to_edge_samples(
            c, reach_m=model.edge_fit_radius_m, spacing_m=model.edge_sample_spacing_m
        )
        for c in confirmed
    ]
    # The scan's own samples near a corner come from balls that reach both legs; the lines,
    # fitted farther out, are the better account of the edge there.
    near_corner = np.zeros(len(model.edges), dtype=bool)
    if len(model.edges):
        for corner_m in located:
            near_corner |= (
                np.linalg.norm(model.edges.points_m - corner_m, axis=1)
                < CORNER_CLEAR_FRACTION * model.edge_fit_radius_m
            )
    return model.with_extra_edges(
        np.concatenate([p for p, _ in extra]),
        np.concatenate([d for _, d in extra]),
        drop=near_corner,
    )


#: The scan's own edge samples this close to a confirmed corner (as a share of the edge-fit
#: ball's radius) give way to the corner's edge lines.
CORNER_CLEAR_FRACTION = 0.75


#: Without a scan, a corner is where the lines fitted to this much of each segment's end meet.
CORNER_LINE_M = 0.008


def join_at_corners(
    bounds: list[tuple[int, int]],
    results: list[SegmentResult],
    corners: list[Corner],
    kinds: list[SegmentKind],
    input_points_m: FloatArray,
    *,
    spacing_m: float,
    beta: float,
) -> None:
    """Make neighbouring segments end on one point at each corner (in place).

    Where the scan confirmed the corner and both segments follow its edges, both end where the
    scan's edge lines meet, or ``beta`` of the way there from the trace (as every other point
    moves by ``beta``). Elsewhere both end where lines fitted to their results' last
    :data:`CORNER_LINE_M` (less on a shorter segment) meet, or at the mean of their two ends if
    those lines do not come within a millimetre of each other.

    Parameters
    ----------
    bounds : list of (start, stop)
    results : list of SegmentResult
        One per segment, ``points`` in the frame of ``input_points_m``.
    corners : list of Corner
    kinds : list of SegmentKind
        What each segment follows, once checked (a segment that fell back to the path alone
        does not end on the scan's corner).
    input_points_m : ndarray of shape (N, 3)
        The resampled trace.
    spacing_m : float
    beta : float
    """
    by_index = {c.index: c for c in corners if c.split}
    k = max(2, int(round(CORNER_LINE_M / spacing_m)))
    pairs = zip(results[:-1], results[1:], bounds[:-1], kinds[:-1], kinds[1:], strict=True)
    for left, right, (_, stop), left_kind, right_kind in pairs:
        corner = by_index.get(stop - 1)
        if corner is None:
            continue  # two pieces of the trace, not a corner: nothing to join
        on_edges = left_kind == SegmentKind.EDGE and right_kind == SegmentKind.EDGE
        if corner.point_m is not None and on_edges:
            trace_point = input_points_m[stop - 1]
            point = trace_point + beta * (corner.point_m - trace_point)
        else:
            run = min(k, len(left.points), len(right.points))
            point = 0.5 * (left.points[-1] + right.points[0])
            if run >= 2:
                point = meeting_point(left.points[-run:], right.points[:run], fallback=point)
        left.points[-1] = point
        right.points[0] = point


def meeting_point(before: FloatArray, after: FloatArray, *, fallback: FloatArray) -> FloatArray:
    """Where lines through two runs of points meet (``fallback`` if they pass more than a
    millimetre apart, or meet more than 5 mm from it).

    Parameters
    ----------
    before, after : ndarrays of shape (K, 3), K >= 2
    fallback : ndarray of shape (3,)
    """
    lines = []
    for run in (before, after):
        centre = run.mean(axis=0)
        _, _, vt = np.linalg.svd(run - centre)
        lines.append(EdgeLine(centre, vt[0], 0.0, len(run)))
    point, gap = closest_approach(*lines)
    if gap > 1e-3 or np.linalg.norm(point - fallback) > 5e-3:
        return fallback
    return point


def touch_registration(
    points_tracker_m: FloatArray,
    touches: TouchRegistration,
    model: ScanModel,
    bounds: list[tuple[int, int]],
    params: ReconParams,
    *,
    T_scan_tracker_init: FloatArray | None = None,
) -> Registration:
    """The touches' transform as the reconstruction's registration, once it is checked to place
    this path within ``params.uncertainty_tolerance_m`` (1 sigma, across its features; the rule of
    :func:`recon.touches.touch_uncertainty`, the same as a calibration's).

    Parameters
    ----------
    points_tracker_m : ndarray of shape (N, 3)
        The resampled trace, tracker frame.
    touches : TouchRegistration
    model : ScanModel
        Built around the trace placed by the touches.
    bounds : list of (start, stop)
    params : ReconParams
    T_scan_tracker_init : ndarray of shape (4, 4), optional
        Where the path was before (identity if not given), to say how far the touches moved it.

    Returns
    -------
    Registration
        Target ``"touches"``; ``rmse_m`` and ``n_pairs`` of the touches used; its covariance is
        the touches' (of the motions they solve for), so the reconstruction's uncertainty carries
        what they leave at the path.

    Raises
    ------
    TouchesInsufficientError
        The touches leave more than the tolerance at the path; the message names each poorly
        pinned motion with the millimetres it leaves and what to touch.
    """
    judged = judge_at_path(touches, points_tracker_m, model, bounds, params)
    # The reconstruction's own tolerance: its summary names every stretch of the path whose
    # uncertainty exceeds it, and touches that alone exceed it would put the path there.
    judged.check(params.uncertainty_tolerance_m, remedy=WITHOUT_TOUCHES)
    T = touches.T_scan_tracker
    init = np.eye(4) if T_scan_tracker_init is None else check_rigid(T_scan_tracker_init)
    moved = np.linalg.norm(
        apply_transform(T, points_tracker_m) - apply_transform(init, points_tracker_m), axis=1
    )
    residual = touches.residual_m[touches.used]
    n_used = len(residual)
    covariance, scan_motion = touches.covariance_in_scan_frame()
    return Registration(
        T_scan_tracker=T,
        rmse_m=float(np.sqrt(np.mean(residual**2))),
        fitness=float(np.mean(touches.used)),
        n_pairs=n_used,
        target="touches",
        constrained_dof=touches.fixed_motions,
        path_moved_mean_m=float(moved.mean()),
        path_moved_max_m=float(moved.max()),
        covariance=covariance,
        motion_centre_m=scan_motion.centre_m,
        motion_length_m=scan_motion.length_m,
        reason=f"{n_used} touches of the workpiece place this path to {judged.summary()}, "
        f"within the {params.uncertainty_tolerance_m * 1e3:.2f} mm tolerance"
        # No touch left over: the fit passes through every touch, so a residual of 0 checks
        # nothing and a touch that slipped would go unnoticed.
        + (
            "; no more touches than motions, so their residual checks nothing: touch one or two "
            "more points to have a check"
            if n_used <= touches.fixed_motions
            else ""
        )
        + (f" ({'; '.join(touches.notes)})" if touches.notes else ""),
    )


#: What else can be done with touches that leave too much at the path.
WITHOUT_TOUCHES = "or do without the touches (the scan is then registered to the trace)"


def touches_for_trace(
    trace: Recording,
    touches_tracker_m: FloatArray,
    scan: Scan,
    *,
    params: ReconParams | None = None,
    T_scan_tracker_init: FloatArray | None = None,
    touch_sigma_m: FloatArray | None = None,
    check: bool = True,
) -> TouchRegistration:
    """The scanner registered by touches, started from a stored calibration or, without one,
    from registering the trace to the scan as a reconstruction does; checked (unless ``check``
    is False) to place the trace within ``params.uncertainty_tolerance_m``, by the rule a
    reconstruction applies (:func:`touch_registration`).

    Parameters
    ----------
    trace : Recording
        The traced path, tracker frame.
    touches_tracker_m : ndarray of shape (T, 3)
        The touches (the dwells' mean tip positions), tracker frame.
    scan : Scan
    params : ReconParams, optional
    T_scan_tracker_init : ndarray of shape (4, 4), optional
    touch_sigma_m : ndarray of shape (T,), optional
        See :func:`recon.touches.register_touches`.
    check : bool

    Returns
    -------
    TouchRegistration
        With its ``judgement`` at the trace when checked.

    Raises
    ------
    RegistrationError
        The touches could not be registered, or (``TouchesInsufficientError``) they leave more
        than the tolerance at the trace.
    """
    params = params or ReconParams()
    plan = plan_segments(trace, params)
    points = plan.resampled.points_m
    start, guess_sigma_m = T_scan_tracker_init, INITIAL_GUESS_SIGMA_M
    if start is None:
        start = prepare_scan_model(points, scan, plan.bounds, params).T_scan_tracker
        guess_sigma_m = ROUGH_GUESS_SIGMA_M  # it keeps the rigid part of the hand's drift
    touches = register_touches(
        touches_tracker_m,
        scan.points_m,
        T_scan_tracker_init=start,
        touch_sigma_m=touch_sigma_m,
        initial_sigma_m=guess_sigma_m,
    )
    if check:
        model = build_scan_model(scan, apply_transform(touches.T_scan_tracker, points), params)
        judged = judge_at_path(touches, points, model, plan.bounds, params)
        judged.check(params.uncertainty_tolerance_m, remedy=WITHOUT_TOUCHES)
        touches = replace(touches, judgement=judged)
    return touches


def touch_advice(missing: list[str]) -> str:
    """What to touch to pin motions the touches do not pin at all (in words, as
    :meth:`recon.icp.RigidMotion.describe` gives them); see :func:`recon.touches.touch_advice`."""
    return "; ".join(motion_advice(motion) for motion in missing)


def uncertainty_notes(
    uncertainty_m: FloatArray, arc_m: FloatArray, *, tolerance_m: float
) -> list[str]:
    """A note per stretch of the path whose uncertainty exceeds ``tolerance_m``.

    Parameters
    ----------
    uncertainty_m : ndarray of shape (N,)
    arc_m : ndarray of shape (N,)
        Arc length of the points.
    tolerance_m : float

    Returns
    -------
    list of str
        E.g. "points 0-14 (0-14 mm along the path): uncertainty up to 0.83 mm, above the
        0.50 mm tolerance".
    """
    above = np.asarray(uncertainty_m) > tolerance_m
    edges = np.flatnonzero(np.diff(np.r_[0, above.astype(np.int8), 0]))
    stretches: list[list[int]] = []
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        # Stretches a few points apart are one stretch to an operator.
        if stretches and start - stretches[-1][1] <= MERGE_GAP_POINTS:
            stretches[-1][1] = stop
        else:
            stretches.append([start, stop])
    notes = []
    for start, stop in stretches[:MAX_UNCERTAINTY_NOTES]:
        worst = float(np.max(uncertainty_m[start:stop]))
        notes.append(
            f"points {start}-{stop - 1} ({arc_m[start] * 1e3:.0f}-{arc_m[stop - 1] * 1e3:.0f} mm "
            f"along the path): uncertainty up to {worst * 1e3:.2f} mm, above the "
            f"{tolerance_m * 1e3:.2f} mm tolerance"
        )
    if len(stretches) > MAX_UNCERTAINTY_NOTES:
        notes.append(
            f"and {len(stretches) - MAX_UNCERTAINTY_NOTES} more stretches above the tolerance "
            "(the CSV's uncertainty_m has every point)"
        )
    return notes


#: Stretches above the uncertainty tolerance this many points apart or fewer are named as one.
MERGE_GAP_POINTS = 10
#: At most this many stretches are named; the rest are counted.
MAX_UNCERTAINTY_NOTES = 5


@dataclass(frozen=True)
class PreparedScan:
    """The scan model near a path and the transform to use it with.

    Attributes
    ----------
    model : ScanModel
        Scan frame.
    T_scan_tracker : ndarray of shape (4, 4)
        The registration's transform, else the initial one.
    registration : Registration or None
        None when registration was switched off.
    """

    model: ScanModel
    T_scan_tracker: FloatArray
    registration: Registration | None


def prepare_scan_model(
    points_tracker_m: FloatArray,
    scan: Scan,
    bounds: list[tuple[int, int]],
    params: ReconParams,
    *,
    T_scan_tracker_init: FloatArray | None = None,
) -> PreparedScan:
    """The scan model near a path (scan frame) and the transform to use it with.

    The model is built around the path mapped by the initial transform (the crop margin covers
    the misalignment left); registration, unless ``params.register`` is False, then refines the
    transform against it. The model does not depend on the registration's result.

    Parameters
    ----------
    points_tracker_m : ndarray of shape (N, 3), metres
        The resampled trace, tracker frame.
    scan : Scan
    bounds : list of (start, stop)
        The trace's segments (registration picks its target from their classification).
    params : ReconParams
    T_scan_tracker_init : ndarray of shape (4, 4), optional
        Identity if not given.

    Returns
    -------
    PreparedScan

    Raises
    ------
    ValueError
        A ``T_scan_tracker_init`` that is not a rigid transform.
    NoOverlapError, RegistrationError
        See :mod:`recon.errors`.
    """
    if T_scan_tracker_init is None:
        T_scan_tracker = np.eye(4)
    else:
        T_scan_tracker = check_rigid(T_scan_tracker_init, name="T_scan_tracker_init").copy()
    model = build_scan_model(scan, apply_transform(T_scan_tracker, points_tracker_m), params)
    registration = None
    if params.register:
        registration = register_to_model(
            points_tracker_m, model, bounds, params, T_scan_tracker_init=T_scan_tracker
        )
        T_scan_tracker = registration.T_scan_tracker
    return PreparedScan(model=model, T_scan_tracker=T_scan_tracker, registration=registration)


def _assemble(
    resampled: ResampledPath,
    bounds: list[tuple[int, int]],
    segments: list[Segment],
    results: list[SegmentResult],
    registration: Registration | None,
    params: ReconParams,
    notes: list[str],
    *,
    T_scan_tracker: FloatArray | None,
    scan_model: ScanModel | None,
    piece: NDArray[np.int64],
    corners: list[Corner],
    demonstrations: tuple[DemonstrationReport, ...] = (),
    prior: FloatArray | None = None,
) -> Reconstruction:
    """Concatenate segment results; a corner point shared by two segments takes the later one
    (both hold the same point there, see :func:`join_at_corners`)."""
    n = len(resampled.points_m)
    points = np.empty((n, 3))
    mode = np.empty(n, np.int8)
    segment = np.empty(n, np.int64)
    n_path = np.empty(n, np.int64)
    n_surface = np.empty(n, np.int64)
    residual_path = np.empty(n)
    residual_surface = np.empty(n)
    alpha = np.empty(n)
    variance = np.empty(n)
    reason = np.empty(n, np.int8)
    for index, ((start, stop), result) in enumerate(zip(bounds, results, strict=True)):
        sl = slice(start, stop)
        points[sl] = result.points
        mode[sl] = result.mode
        segment[sl] = index
        n_path[sl] = result.n_path
        n_surface[sl] = result.n_surface
        residual_path[sl] = result.residual_path
        residual_surface[sl] = result.residual_surface
        alpha[sl] = result.alpha
        variance[sl] = result.variance_m2
        reason[sl] = result.reason
    from_registration = registration_sigma_m(registration, points, hand_variance_m2=prior)
    uncertainty = np.sqrt(variance + from_registration**2)
    notes = list(notes) + uncertainty_notes(
        uncertainty, resampled.arc_length_m, tolerance_m=params.uncertainty_tolerance_m
    )
    return Reconstruction(
        points_m=points,
        input_points_m=resampled.points_m,
        t_s=resampled.t_s,
        orientations_xyzw=resampled.orientations_xyzw,
        displacement_m=np.linalg.norm(points - resampled.points_m, axis=1),
        mode=mode,
        segment=segment,
        n_path=n_path,
        n_surface=n_surface,
        residual_path_m=residual_path,
        residual_surface_m=residual_surface,
        alpha=alpha,
        segments=tuple(segments),
        registration=registration,
        params=params,
        notes=tuple(notes),
        T_scan_tracker=T_scan_tracker,
        scan_model=scan_model,
        piece=piece,
        uncertainty_m=uncertainty,
        demonstrations=tuple(demonstrations),
        reason=reason,
        corners=tuple(
            CornerReport(
                index=c.index,
                angle_deg=c.angle_deg,
                split=c.split,
                reason=c.reason,
                point_m=None
                if c.point_m is None
                else (float(c.point_m[0]), float(c.point_m[1]), float(c.point_m[2])),
            )
            for c in corners
        ),
    )
