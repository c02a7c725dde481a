"""The anchored method (ours): the path smoothed in 3-D, pulled towards the registered scan.

Once the scan is registered, its absolute position is known, and that is what removes the
slow drift off the feature that no window-sized smoother can see. The path is smoothed by a
3-D polynomial (all three components kept); the scan supplies a target point: on the edge
(a 3-D polynomial through the thinned edge points near it) or on the surface (the point's
projection onto a local quadric along the surface normal, which is all a surface defines).
The result is ``p + beta (alpha s + (1 - alpha) t - p)`` for smoothed point s and target t.

``alpha="auto"`` chooses the balance per point by inverse-variance weighting,
``alpha = var_scan / (var_scan + var_path)``: var_scan is the variance of the target from its fit
(thinned edge points are correlated over a face-fit ball, so their count is discounted
accordingly). var_path must include the drift, which the path's own residuals cannot show; it is
estimated by the method of moments from the path-to-target discrepancy averaged over a long
stretch (ten radii), ``E|s - t|^2 - var_scan``, and is never below the smoothed path's own
variance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter1d

from recon.arrays import FloatArray
from recon.classify import SegmentKind
from recon.faces import fit_faces
from recon.fitting import (
    fit_linear_robust,
    gather,
    poly_design,
    weighted_pca,
    window_indices,
)
from recon.methods.common import (
    SegmentResult,
    adaptive_smoothing,
    edge_neighbourhoods,
    edge_query,
    for_each_chunk,
    path_fit,
    prior_variance,
)
from recon.recon_params import ReconParams
from recon.results import PointMode, PointReason
from recon.scan_model import ScanModel

#: The drift estimate averages the path-to-scan discrepancy over this many radii.
DRIFT_WINDOW_RADII = 10.0
#: Nearest scan neighbours per point for the surface fits: a depth camera's error is correlated
#: over centimetres, and a quadric over a disc of about 18 mm (at a point per mm^2) follows less
#: of it (the lift-off plate's height: 0.43 mm at median with 128 neighbours within 12 mm, 0.29
#: with these).
SURFACE_NEIGHBOURS = 1024
#: N_S on an edge reaches this many radii from the smoothed point.
EDGE_SCAN_RADII = 1.5
#: Edge samples gathered for the narrowest N_S (more for the wider ones, in proportion).
EDGE_NEIGHBOURS = 64
#: ... and at least this many samples (about ten millimetres of edge).
MIN_EDGE_SAMPLES = 10
#: How far a scan's feature may be off where it looks precise: what the scatter of its points does
#: not show (the views merged a little off, the depth quantised), 1 sigma, counted in each
#: point's uncertainty (measured on the real-parts benchmark: edges fitted from hundreds of
#: points were still 0.1-0.2 mm off).
SCAN_ACCURACY_M = 0.15e-3
#: Edge samples per independent one: 3 samples per slice's corner, slices 6 mm thick every 2 mm.
EDGE_SAMPLES_PER_INDEPENDENT = 9.0
#: N_S on a surface reaches this many radii from the smoothed point.
SURFACE_SCAN_RADII = 4


def anchored_segment(
    points: FloatArray,
    kind: SegmentKind,
    model: ScanModel | None,
    params: ReconParams,
    half_width: int,
    *,
    prior_variance_m2: FloatArray | None = None,
    placement_variance_m2: FloatArray | None = None,
    corners: tuple[int, ...] | None = None,
) -> SegmentResult:
    """The anchored method for every point of one segment (see the module docstring).

    Parameters
    ----------
    points : ndarray of shape (n, 3), metres
        The segment, scan frame (tracker frame without a scan).
    kind : SegmentKind
        What the segment follows: the target is on the thinned edge for an edge, on a local
        quadric of the dense cloud for a surface.
    model : ScanModel or None
        None only for ``kind`` PATH.
    params : ReconParams
    half_width : int
        N_P's half-width, in points.
    prior_variance_m2 : ndarray of shape (n,), optional
        How far off the trace is known to be, across the path (both directions together): the
        fused variance of several demonstrations. :data:`HAND_ERROR_PRIOR_M` when not given.
        It is the uncertainty of what only the path decides (a point without a scan, the
        in-plane position on a surface).
    placement_variance_m2 : ndarray of shape (n,), optional
        How far off the scan is placed under each point (the registration's uncertainty there,
        registered by touches: independent of the hand's error). With ``prior_variance_m2``,
        what a point's move onto the scan's evidence may be explained by.
    corners : tuple of int, optional
        The corners an EDGE segment follows (their points alone form N_S).

    Returns
    -------
    SegmentResult
    """
    n = len(points)
    prior = prior_variance(prior_variance_m2, n)
    # The trace is off the scan's evidence by the hand's error and by the scan's placement.
    explained_variance = prior if placement_variance_m2 is None else prior + placement_variance_m2
    windows = window_indices(n, half_width)
    degree = min(params.degree, windows.shape[1] - 2)
    scale = params.radius_m
    use_scan = kind != SegmentKind.PATH and params.alpha != 1.0
    if use_scan and model is None:
        raise ValueError(f"a {kind.name.lower()} segment follows the scan: give its model")
    out = SegmentResult.unchanged(points)
    smoothed = np.empty_like(points)
    var_path_fit = np.zeros(n)
    evidence = Evidence.empty(points)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    end_distance = np.minimum(arc, arc[-1] - arc)
    if kind != SegmentKind.EDGE:
        # Where the path alone decides across it (no scan; the plane of a surface), the widest
        # window that does not bend it (see adaptive_smoothing).
        adaptive = adaptive_smoothing(points, half_width, degree=params.degree, scale=scale)

    def fit_chunk(rows: slice) -> None:
        # A 3-D curve: both transverse components as polynomials of the first.
        fitted = path_fit(points, windows[rows], rows, degree=degree, scale=scale, outputs=2)
        frame, x_i, design_at, fit_p = fitted.frame, fitted.x_i, fitted.design_at, fitted.fit
        if kind == SegmentKind.EDGE:
            on_curve = np.column_stack([x_i, fit_p.predict(design_at)])
            smoothed[rows] = frame.to_world(on_curve)
            var_path_fit[rows] = fit_p.rms**2 * fit_p.leverage(design_at)
            out.n_path[rows] = windows.shape[1]
            out.residual_path[rows] = fit_p.rms
        else:
            smoothed[rows] = adaptive.points_m[rows]
            var_path_fit[rows] = adaptive.variance_m2[rows]
            out.n_path[rows] = 2 * adaptive.half_width[rows] + 1
            out.residual_path[rows] = adaptive.rms_m[rows]
        if use_scan:
            assert model is not None  # refused above otherwise
            evidence.fill(
                rows,
                weigh_evidence(
                    smoothed[rows],
                    frame.axes[:, :, 0],
                    kind,
                    model,
                    params,
                    degree,
                    max_move_m=params.evidence_sigmas * np.sqrt(explained_variance[rows]),
                    end_distance_m=end_distance[rows],
                    corners=corners,
                ),
            )

    if use_scan:
        assert model is not None  # refused above otherwise
        # The trees are built on first use: build them here, not once per thread.
        _ = model.edge_tree if kind == SegmentKind.EDGE else model.dense_tree
        _ = model.fine_normals
    for_each_chunk(fit_chunk, n)

    # Across the path, what only the path decides is as uncertain as the trace (the prior); the
    # smoothing's own noise adds to it.
    path_only_var = prior + 2.0 * var_path_fit
    if use_scan:
        supported = evidence.mode != PointMode.PATH
        target = np.where(supported[:, None], evidence.target, smoothed)
        var_target = np.where(supported, evidence.variance, np.inf)
        var_path = _path_variance(smoothed, target, var_target, var_path_fit, supported, half_width)
        if params.alpha == "auto":
            alpha = _auto_alpha(var_target, var_path, supported)
        else:
            alpha = np.full(n, float(params.alpha))
        # Where the evidence starts and stops, the scan's pull fades in and out over N_P rather
        # than jumping.
        weight = ramp(supported, half_width)
        alpha = 1.0 - weight * (1.0 - np.where(supported, alpha, 1.0))
        out.mode[:] = evidence.mode
        out.reason[:] = evidence.reason
        out.n_surface[:] = np.where(supported, evidence.count, 0)
        out.residual_surface[:] = np.where(supported, evidence.residual, np.nan)
        # The components the scan defines: two across an edge, the height on a face; on a face
        # the third (in the plane, across the path) is the path's alone.
        components = np.where(evidence.mode == PointMode.EDGE, 2, 1)
        per_component = np.where(supported, var_path, 0.0) / components
        # The scan's own accuracy beyond its scatter (SCAN_ACCURACY_M) is no reason to trust it
        # less than another scan (alpha weighs what the data show), but it is part of how far
        # the result may be off.
        target_var = np.where(supported, var_target, 0.0) + SCAN_ACCURACY_M**2
        blend_var = components * (alpha**2 * per_component + (1.0 - alpha) ** 2 * target_var)
        blend_var = blend_var + np.where(components == 1, 0.5 * path_only_var, 0.0)
        variance = np.where(
            supported, weight * blend_var + (1 - weight) * path_only_var, path_only_var
        )
    else:
        target = smoothed
        alpha = np.ones(n)
        out.mode[:] = PointMode.PATH
        variance = path_only_var
    blended = alpha[:, None] * smoothed + (1.0 - alpha[:, None]) * target
    beta = params.beta
    out.points[:] = points + beta * (blended - points)
    out.alpha[:] = alpha
    out.variance_m2[:] = beta**2 * variance + (1.0 - beta) ** 2 * prior
    return out


@dataclass
class Evidence:
    """What the scan says at each point of a segment, once weighed (one row per point).

    Attributes
    ----------
    target : ndarray of shape (n, 3)
        Where the scan's feature puts the point (the smoothed point where it says nothing).
    variance : ndarray of shape (n,)
        Of the target across the path (inf where the scan is not used).
    mode : ndarray of shape (n,), int8
        :class:`PointMode`: EDGE, SURFACE (one face), or PATH where the evidence failed.
    reason : ndarray of shape (n,), int8
        :class:`PointReason`.
    count : ndarray of shape (n,), int
        Scan points (or edge samples) behind the target.
    residual : ndarray of shape (n,)
        RMS residual of the scan's fit.
    """

    target: FloatArray
    variance: FloatArray
    mode: np.ndarray
    reason: np.ndarray
    count: np.ndarray
    residual: FloatArray

    @classmethod
    def empty(cls, points: FloatArray) -> Evidence:
        n = len(points)
        return cls(
            target=points.copy(),
            variance=np.full(n, np.inf),
            mode=np.full(n, PointMode.PATH, np.int8),
            reason=np.full(n, PointReason.NONE, np.int8),
            count=np.zeros(n, np.int64),
            residual=np.full(n, np.nan),
        )

    def fill(self, rows: slice, other: Evidence) -> None:
        for name in ("target", "variance", "mode", "reason", "count", "residual"):
            getattr(self, name)[rows] = getattr(other, name)


def weigh_evidence(
    centres: FloatArray,
    direction: FloatArray,
    kind: SegmentKind,
    model: ScanModel,
    params: ReconParams,
    degree: int,
    *,
    max_move_m: FloatArray,
    end_distance_m: FloatArray | None = None,
    corners: tuple[int, ...] | None = None,
) -> Evidence:
    """The scan's target for each smoothed point, accepted only where the evidence holds.

    A target is accepted where (a) the scan defines the feature there (an edge fitted from edge
    samples on both sides with scan points near it; a face with points near the target) and (b)
    the point moves no farther than the trace's error explains (``max_move_m``). On an edge
    segment, a point whose edge fails falls back to the one face under it (its height), then to
    the path alone; on a surface segment, to the path alone.

    Parameters
    ----------
    centres : ndarray of shape (B, 3)
        Smoothed path points, scan frame.
    direction : ndarray of shape (B, 3)
        The path's direction there.
    kind : SegmentKind
        EDGE or SURFACE.
    model : ScanModel
    params : ReconParams
    degree : int
        Of the edge's local polynomial.
    max_move_m : ndarray of shape (B,)
        The farthest a point may move across the path.
    end_distance_m : ndarray of shape (B,), optional
        How far each point lies from its segment's nearer end, along it: only there may an edge
        be continued past the end of its samples (inside a segment a gap in them is bridged by
        the samples beyond it, not by a straight line). Everywhere when not given.
    corners : tuple of int, optional
        The corners the segment follows.

    Returns
    -------
    Evidence
    """
    out = Evidence.empty(centres)
    todo = np.ones(len(centres), dtype=bool)
    first_failure = np.full(len(centres), PointReason.NO_FEATURE, np.int8)
    if kind == SegmentKind.EDGE:
        t, var_t, count, resid, past = _edge_targets(
            centres,
            direction,
            model,
            params,
            degree,
            corners=corners,
            end_distance_m=end_distance_m,
        )
        found = np.isfinite(var_t)
        gap, _ = model.dense_tree.query(t, workers=-1)
        # A continued edge's line runs on past the scan's points: the support is looked for
        # where the edge's samples end.
        on_evidence = found & ((gap <= EDGE_SUPPORT_M) | (past > 0))
        near = _explained(centres, t, max_move_m, model, on_evidence)
        accept = on_evidence & near
        # Past the end of the edge's samples near the segment's end: the trace ran on past the
        # feature. Elsewhere, no samples near is no feature.
        near_end = (
            np.ones(len(centres), dtype=bool)
            if end_distance_m is None
            else np.asarray(end_distance_m) <= CONTINUE_PAST_END_M + SPAN_SLACK_M
        )
        ended = ~found & np.isfinite(past) & (past > CONTINUE_PAST_END_M) & near_end
        first_failure = np.where(
            ended,
            PointReason.PAST_END,
            np.where(
                ~found,
                PointReason.NO_FEATURE,
                np.where(~on_evidence, PointReason.OFF_EVIDENCE, PointReason.FAR_FROM_TRACE),
            ),
        ).astype(np.int8)
        reason = np.where(past > CONTINUED_NOTE_M, PointReason.CONTINUED, PointReason.NONE)
        _take(out, accept, t, var_t, PointMode.EDGE, reason.astype(np.int8), count, resid)
        todo &= ~accept
    if np.any(todo):
        rows = np.flatnonzero(todo)
        face = fit_faces(
            centres[rows],
            model,
            radius_m=SURFACE_SCAN_RADII * params.radius_m,
            neighbours=SURFACE_NEIGHBOURS,
            scale_m=params.radius_m,
        )
        face_target = centres.copy()
        face_target[rows] = face.target_m
        face_ok = np.zeros(len(centres), dtype=bool)
        face_ok[rows] = face.ok
        face_normal = np.zeros_like(centres)
        face_normal[rows] = face.normal
        accept = _explained(centres, face_target, max_move_m, model, face_ok, face_normal) & todo
        face_reason = PointReason.ONE_FACE if kind == SegmentKind.EDGE else PointReason.NONE
        t = np.zeros_like(centres)
        t[rows] = face.target_m
        var_t = np.full(len(centres), np.inf)
        var_t[rows] = face.variance_m2
        count = np.zeros(len(centres), np.int64)
        count[rows] = face.count
        resid = np.full(len(centres), np.nan)
        resid[rows] = face.rms_m
        _take(out, accept, t, var_t, PointMode.SURFACE, face_reason, count, resid)
        if kind == SegmentKind.SURFACE:
            face_failure = np.where(face.ok, PointReason.FAR_FROM_TRACE, PointReason.NO_FEATURE)
            first_failure[rows] = face_failure
        todo &= ~accept
    out.reason[todo] = first_failure[todo]
    return out


def _explained(
    centres: FloatArray,
    targets: FloatArray,
    max_move_m: FloatArray,
    model: ScanModel,
    candidate: NDArray[np.bool_],
    normals: FloatArray | None = None,
) -> NDArray[np.bool_]:
    """Whether moving each point (consecutive points of a segment) to its target is what the
    trace's error explains: a move within the hand's error (``max_move_m``), or, onto a face
    (``normals`` given), a lift-off.

    A lift-off is the pen off a face for a moment: up to :data:`MAX_LIFT_OFF_M` above it, with
    nothing of the scan between the pen and the face (it hung in the air above it), and the
    trace on that very face within the hand's error right before and after (a run of at most
    :data:`MAX_LIFT_OFF_LENGTH_M`; a trace that runs off a face all along it is on another one,
    or on a face the scan does not show), the scan running from there to the lifted target
    without a step. Only points where ``candidate`` (the target is on the scan's evidence) count.
    """
    move = np.linalg.norm(targets - centres, axis=1)
    near: NDArray[np.bool_] = candidate & (move <= max_move_m)
    if normals is None:
        return near
    lifted: NDArray[np.bool_] = candidate & ~near & (move <= MAX_LIFT_OFF_M)
    n = len(centres)
    if np.any(lifted) and n > 1:
        spacing = float(np.median(np.linalg.norm(np.diff(centres, axis=0), axis=1)))
        longest = max(1, int(round(MAX_LIFT_OFF_LENGTH_M / max(spacing, 1e-9))))
        edges = np.flatnonzero(np.diff(np.r_[0, lifted.astype(np.int8), 0]))
        for start, stop in zip(edges[::2], edges[1::2], strict=True):
            # A run of lifted points, flanked by the trace on the face (a run that reaches an
            # end of the segment needs its other side only).
            flanks = [k for k in (start - 1, stop) if 0 <= k < n]
            if stop - start > longest or not flanks or not all(near[k] for k in flanks):
                lifted[start:stop] = False
                continue
            rows = np.arange(start, stop)
            ok = np.ones(len(rows), dtype=bool)
            for k in flanks:
                ok &= _scan_along(np.repeat(targets[k][None], len(rows), 0), targets[rows], model)
            lifted[rows] = ok
    if np.any(lifted):
        rows = np.flatnonzero(lifted)
        lifted[rows] = _in_free_air(centres[rows], targets[rows], model)
    return near | lifted


def _scan_along(starts: FloatArray, ends: FloatArray, model: ScanModel) -> np.ndarray:
    """Whether the scan runs along the straight way from each start to its end (both on one
    face, with no step between): a point within :data:`LIFT_OFF_SAME_FACE_M` of every
    millimetre of it but for gaps of at most :data:`LIFT_OFF_SCAN_GAP_M`.

    Each way is probed every :data:`LIFT_OFF_PROBE_M` along its own length (whatever the others
    batched with it measure), and at its end.
    """
    lengths = np.linalg.norm(ends - starts, axis=1)
    count = np.ceil(lengths / LIFT_OFF_PROBE_M).astype(np.int64) + 1  # probes per way
    steps = np.arange(int(count.max(initial=1)))
    # Probe k of a way at k millimetres, the last at its end; past it (shorter ways) none.
    along = np.minimum(steps[None, :] * LIFT_OFF_PROBE_M, lengths[:, None])
    own = steps[None, :] < count[:, None]
    unit = (ends - starts) / np.maximum(lengths, 1e-12)[:, None]
    probes = starts[:, None, :] + along[..., None] * unit[:, None, :]
    gap, _ = model.dense_tree.query(
        probes.reshape(-1, 3), distance_upper_bound=LIFT_OFF_SAME_FACE_M, workers=-1
    )
    covered = np.isfinite(gap).reshape(probes.shape[:2]) | ~own
    allowed = int(round(LIFT_OFF_SCAN_GAP_M / LIFT_OFF_PROBE_M))
    return _longest_false_run(covered) <= allowed


def _longest_false_run(flags: np.ndarray) -> np.ndarray:
    """Per row of ``flags`` (R, S), bool: the length of its longest run of False, (R,), int."""
    longest = np.zeros(len(flags), dtype=np.int64)
    run = np.zeros(len(flags), dtype=np.int64)
    for column in (~flags).T:
        run = np.where(column, run + 1, 0)
        longest = np.maximum(longest, run)
    return longest


def _in_free_air(starts: FloatArray, targets: FloatArray, model: ScanModel) -> NDArray[np.bool_]:
    """Whether the straight way from each start to its target (all but its last
    :data:`LIFT_OFF_LANDING_M`) passes no scan point closer than :data:`LINE_OF_SIGHT_M`."""
    way = targets - starts
    length = np.linalg.norm(way, axis=1)
    reach = np.maximum(length - LIFT_OFF_LANDING_M, 0.0)
    steps = np.arange(0.0, MAX_LIFT_OFF_M, 0.5 * LINE_OF_SIGHT_M)
    unit = way / np.maximum(length, 1e-12)[:, None]
    probes = (
        starts[:, None, :] + np.minimum(steps[None, :], reach[:, None])[..., None] * unit[:, None]
    )
    gap, _ = model.dense_tree.query(
        probes.reshape(-1, 3), distance_upper_bound=LINE_OF_SIGHT_M, workers=-1
    )
    blocked = np.isfinite(gap).reshape(len(starts), len(steps))
    clear: NDArray[np.bool_] = ~blocked.any(axis=1)
    return clear


#: A pen lifted off the workpiece is farther from it than the hand's error explains: a point may
#: move this far down onto its feature when nothing of the scan lies between (paper, Fig. 7: a
#: lift-off of several millimetres).
MAX_LIFT_OFF_M = 0.012
#: A lift-off lasts at most this long along the path, flanked by the trace on the face. Longer
#: (0.1 m was tried) accepts a trace 2-5 mm off a face along 80-100 mm as lifted and moves it
#: down (a misplaced scan on the casting: 138 points moved 2-4.4 mm off the truth, unflagged);
#: the price is that demonstrations fused after lifting at different places (one lift of 80 mm)
#: fall back to the path there, flagged (one seed of 20 of the lift-off plate, 6.8 mm) ...
MAX_LIFT_OFF_LENGTH_M = 0.06
#: ... the face there the same: the scan within this of the straight way from there to the
#: lifted point's target (a step of a few millimetres leaves a gap; the scan's own gaps between
#: points, about a millimetre, do not).
LIFT_OFF_SAME_FACE_M = 0.0018
#: ... a random scan of about a point per square millimetre leaves such a gap now and then (on
#: the lift-off plate: one or two probes of the thousands along the ways), a step of a few
#: millimetres a gap several millimetres long.
LIFT_OFF_SCAN_GAP_M = 0.002
#: The ways are probed this far apart.
LIFT_OFF_PROBE_M = 0.001
#: The way down is clear when no scan point lies within this of it ...
LINE_OF_SIGHT_M = 0.0008
#: ... but for its last stretch, where it reaches the feature and the scan's scatter about it (a
#: depth camera's surface scatters by a millimetre or more) would block a clear way.
LIFT_OFF_LANDING_M = 0.0025


def _take(
    out: Evidence,
    accept: NDArray[np.bool_],
    target: FloatArray,
    variance: FloatArray,
    mode: PointMode,
    reason: NDArray[np.int8] | PointReason,
    count: np.ndarray,
    residual: FloatArray,
) -> None:
    out.target[accept] = target[accept]
    out.variance[accept] = variance[accept]
    out.mode[accept] = mode
    out.reason[accept] = (
        reason[accept] if isinstance(reason, np.ndarray) and reason.ndim else reason
    )
    out.count[accept] = count[accept]
    out.residual[accept] = residual[accept]


#: An edge target needs a scan point this close to it: the crest (or the faces right next to it)
#: is in the scan, the two faces were not extrapolated over a gap.
EDGE_SUPPORT_M = 0.002


def ramp(supported: np.ndarray, half_width: int) -> FloatArray:
    """A weight that is 1 deep inside runs of supported points and falls to 0 over ``half_width``
    points towards their ends (0 at unsupported points): how much of the scan's pull a point
    gets, so that it fades in and out instead of jumping.

    Parameters
    ----------
    supported : ndarray of shape (n,), bool
    half_width : int

    Returns
    -------
    ndarray of shape (n,), in [0, 1]
    """
    n = len(supported)
    if n == 0 or half_width <= 0:
        return supported.astype(np.float64)
    # Distance (in points) to the nearest unsupported point, either way; segment ends do not
    # count (a segment's end is not where evidence stops).
    index = np.arange(n)
    gaps = np.flatnonzero(~supported)
    if len(gaps) == 0:
        return np.ones(n)
    position = np.searchsorted(gaps, index)
    before = np.where(position > 0, index - gaps[np.maximum(position - 1, 0)], n)
    after = np.where(position < len(gaps), gaps[np.minimum(position, len(gaps) - 1)] - index, n)
    distance = np.minimum(before, after).astype(np.float64)
    weight: FloatArray = np.clip(distance / half_width, 0.0, 1.0) * supported
    return weight


def _edge_targets(
    centres: FloatArray,
    direction: FloatArray,
    model: ScanModel,
    params: ReconParams,
    degree: int,
    *,
    corners: tuple[int, ...] | None = None,
    end_distance_m: FloatArray | None = None,
) -> tuple[NDArray[Any], ...]:
    """Nearest point of the local edge curve to each smoothed path point, over the widest stretch
    of edge that does not bend it.

    The edge is fitted over :data:`EDGE_WINDOW_FACTORS` times the N_S reach (see
    :func:`_edge_targets_within`); at each point the widest fit that agrees with every narrower
    one (within :data:`EDGE_ICI_GAMMA` of their summed standard deviations: the intersection of
    confidence intervals, as for the path in :func:`recon.methods.common.adaptive_smoothing`) is
    kept. A straight edge is then averaged over several centimetres of scan, a tight bend over
    the narrowest stretch.

    Returns
    -------
    target : (B, 3); var : (B,) (inf where unfit); count : (B,); residual : (B,); past : (B,)
        How far past the end of the edge's samples the point lies (0 within them).
    """
    if model.edge_tree is None:
        b = len(centres)
        return (
            centres,
            np.full(b, np.inf),
            np.zeros(b, np.int64),
            np.full(b, np.nan),
            np.zeros(b),
        )
    near_end = (
        np.ones(len(centres), dtype=bool)
        if end_distance_m is None
        else np.asarray(end_distance_m) <= CONTINUE_PAST_END_M + SPAN_SLACK_M
    )
    # One query of the widest window: each narrower one's neighbours are its first columns.
    widest = max(EDGE_WINDOW_FACTORS)
    wider = edge_query(
        model,
        centres,
        k=EDGE_NEIGHBOURS * widest,
        radius_m=EDGE_SCAN_RADII * params.radius_m * widest,
    )
    fits = [
        _edge_targets_within(
            centres, direction, model, params, degree, corners, factor, near_end, wider
        )
        for factor in EDGE_WINDOW_FACTORS
    ]
    rows = np.arange(len(centres))
    valid = np.stack([np.isfinite(f[1]) for f in fits])  # (F, B)
    # Start from the narrowest window that fits (a gap in the edge's samples narrower than the
    # wider windows is bridged by them), widen while every narrower valid one agrees.
    start = np.where(valid.any(axis=0), np.argmax(valid, axis=0), 0)
    chosen = start.copy()
    growing = valid[start, rows]
    for j in range(1, len(fits)):
        t_j, var_j = fits[j][0], fits[j][1]
        widen = growing & (j > start) & valid[j]
        for i in range(j):
            t_i, var_i = fits[i][0], fits[i][1]
            gap = np.linalg.norm(t_j - t_i, axis=1)
            with np.errstate(invalid="ignore"):
                bound = EDGE_ICI_GAMMA * (np.sqrt(var_i) + np.sqrt(var_j))
            counts = (i >= start) & valid[i]
            widen &= ~counts | (gap <= bound)
        growing &= widen | (j <= start)
        chosen = np.where(widen, j, chosen)
    return tuple(np.stack([f[k] for f in fits])[chosen, rows] for k in range(5))


#: The edge's N_S reaches these multiples of its narrowest reach; the widest that does not bend
#: the edge is kept (see :func:`_edge_targets`).
EDGE_WINDOW_FACTORS = (1, 2, 4)
#: The intersection-of-confidence-intervals constant of the edge's window choice.
EDGE_ICI_GAMMA = 1.5


def _edge_targets_within(
    centres: FloatArray,
    direction: FloatArray,
    model: ScanModel,
    params: ReconParams,
    degree: int,
    corners: tuple[int, ...] | None,
    factor: int,
    near_end: NDArray[np.bool_],
    wider: tuple[FloatArray, NDArray[np.int64]],
) -> tuple[FloatArray, FloatArray, NDArray[np.intp], FloatArray, FloatArray]:
    """:func:`_edge_targets` with N_S reaching ``factor`` times :data:`EDGE_SCAN_RADII` radii
    (its neighbours read from ``wider``, the edge query of the widest window).

    A 3-D polynomial (both transverse components of the edge points' principal frame as
    functions of the first) is fitted robustly to the thinned edge points near the point.
    """
    ns, ws, idx_s = edge_neighbourhoods(
        centres,
        direction,
        model,
        EDGE_SCAN_RADII * params.radius_m * factor,
        corners=corners,
        max_points=EDGE_NEIGHBOURS * factor,
        wider=wider,
    )
    frame = weighted_pca(ns, ws)
    axes = frame.axes.copy()
    flip = np.einsum("bi,bi->b", axes[:, :, 0], direction) < 0
    axes[flip, :, 0] *= -1
    local = np.einsum("bij,bki->bkj", axes, ns - frame.mean[:, None])
    scale = params.radius_m * factor
    fit, ws = fit_linear_robust(
        poly_design(local[..., 0], degree=degree, scale=scale), local[..., 1:], ws, floor=1e-5
    )
    x_at = np.einsum("bi,bi->b", axes[:, :, 0], centres - frame.mean)
    # Past the end of the edge's samples, the edge's line is continued (straight, from where
    # its samples end) rather than its polynomial extrapolated.
    has = np.any(ws > 0, axis=1)
    lo = np.where(has, np.where(ws > 0, local[..., 0], np.inf).min(axis=1), x_at)
    hi = np.where(has, np.where(ws > 0, local[..., 0], -np.inf).max(axis=1), x_at)
    x_end = np.clip(x_at, lo, hi)
    past = np.where(has, np.abs(x_at - x_end), np.inf)
    design_at = poly_design(x_end, degree=degree, scale=scale)
    slope = np.einsum("bp,bpm->bm", _poly_slope(x_end, degree=degree, scale=scale), fit.coef)
    across = fit.predict(design_at) + slope * (x_at - x_end)[:, None]
    target = frame.mean + np.einsum("bij,bj->bi", axes, np.column_stack([x_at, across]))
    target = np.where((has & np.all(np.isfinite(target), axis=1))[:, None], target, centres)
    var_from_scatter = fit.rms**2 * np.minimum(
        fit.leverage(design_at) * edge_dependence(model), 1.0
    )
    # The scatter about the local curve hides what neighbouring corners share (their slices
    # overlap), so the corners' own precision bounds the target's variance from below.
    line_variance = gather(model.edges.variances_m2(), idx_s, fill_index=len(model.edges))
    var_from_fits = (ws * line_variance).sum(axis=1) / np.maximum(ws.sum(axis=1), 1e-300)
    var = np.maximum(var_from_scatter, var_from_fits / factor)
    # Within the samples' span, or continued at most CONTINUE_PAST_END_M past its end; the
    # continued line's uncertainty grows with the distance (its slope's).
    count = count_of(ws)
    span_ok = (past <= SPAN_SLACK_M) | (near_end & (past <= CONTINUE_PAST_END_M))
    # The line's direction is known to about rms / sqrt(count) over the window's length.
    slope_sigma = np.maximum(fit.rms, 1e-5) / np.sqrt(np.maximum(count, 1)) / scale
    var = var + (np.where(has, past, 0.0) * slope_sigma) ** 2
    # A handful of samples left by the direction filter on a tight bend: a curve through them is
    # an extrapolation, not the edge (measured on a 15 mm bend: 7 samples, 1.2 mm off).
    ok = (fit.dof >= 2) & span_ok & (count >= MIN_EDGE_SAMPLES)
    return target, np.where(ok, var, np.inf), count, fit.rms, past


def edge_dependence(model: ScanModel) -> float:
    """How many edge samples carry one sample's worth of independent information.

    Each slice's corner is sampled three times along the edge, and neighbouring slices share
    points (they are thicker than they are apart): count one independent sample per slice
    thickness, not one per sample.
    """
    return EDGE_SAMPLES_PER_INDEPENDENT


def _surface_targets(
    centres: FloatArray, model: ScanModel, params: ReconParams
) -> tuple[NDArray[Any], ...]:
    """Each smoothed path point moved along the local surface normal onto a fitted quadric.

    Returns
    -------
    target : (B, 3); var : (B,) (inf where unfit); count : (B,); residual : (B,)
    """
    # Up to a thousand neighbours per point: fit_faces takes a few hundred points at a time.
    face = fit_faces(
        centres,
        model,
        radius_m=SURFACE_SCAN_RADII * params.radius_m,
        neighbours=SURFACE_NEIGHBOURS,
        scale_m=params.radius_m,
    )
    return face.target_m, face.variance_m2, face.count, face.rms_m


def count_of(weights: FloatArray) -> NDArray[np.intp]:
    """Points with a weight, per row."""
    counts: NDArray[np.intp] = np.count_nonzero(weights, axis=1)
    return counts


def _poly_slope(x: FloatArray, *, degree: int, scale: float) -> FloatArray:
    """d/dx of :func:`recon.fitting.poly_design`'s basis at ``x``: shape (B, degree + 1)."""
    u = np.asarray(x) / scale
    powers = np.arange(degree + 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        values = powers * np.where(powers > 0, u[:, None] ** np.maximum(powers - 1, 0), 0.0)
    return values / scale


#: Past the end of an edge's samples (a trace that runs on past where the feature ends), the
#: edge's line is continued this far; farther, the point keeps the trace (said per point).
CONTINUE_PAST_END_M = 0.005
#: A point this far past its edge's samples is still among them (they are a millimetre apart).
SPAN_SLACK_M = 0.0005
#: A point continued more than this past its edge's samples is said to be (reason CONTINUED).
CONTINUED_NOTE_M = 0.0015


def _path_variance(
    smoothed: FloatArray,
    target: FloatArray,
    var_target: FloatArray,
    var_path_fit: FloatArray,
    supported: NDArray[np.bool_],
    half_width: int,
) -> FloatArray:
    """The smoothed path's variance against the scan's target, drift included (see the module
    docstring): the mean path-to-target discrepancy over a long stretch less the target's own
    variance, and never below the smoothing's own.

    Returns
    -------
    ndarray of shape (n,)
        Summed over the components the target defines.
    """
    discrepancy = np.where(supported, np.sum((smoothed - target) ** 2, axis=1), 0.0)
    size = int(2 * DRIFT_WINDOW_RADII * half_width + 1)
    weight = uniform_filter1d(supported.astype(np.float64), size, mode="nearest")
    mean_discrepancy = uniform_filter1d(discrepancy, size, mode="nearest") / np.maximum(
        weight, 1e-12
    )
    var_t = np.where(supported, var_target, 0.0)
    variance: FloatArray = np.maximum(mean_discrepancy - var_t, var_path_fit)
    return variance


def _auto_alpha(
    var_target: FloatArray, var_path: FloatArray, supported: NDArray[np.bool_]
) -> FloatArray:
    """Inverse-variance weight of the path (see the module docstring)."""
    var_t = np.where(supported, var_target, 0.0)
    return var_t / np.maximum(var_t + var_path, 1e-300)
