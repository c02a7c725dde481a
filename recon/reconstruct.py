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

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from recon.classify import PATH_ONLY, SegmentKind, classify_segments
from recon.errors import DegenerateInputError, UnitsMismatchError
from recon.methods.anchored import anchored_segment
from recon.methods.common import SegmentResult
from recon.methods.paper import paper_segment
from recon.registration import register_to_model
from recon.resample import ResampledPath, resample_equidistant
from recon.scan_model import ScanModel, build_scan_model
from recon.segment import find_corners, split_at
from recon.transforms import apply_transform, check_rigid, invert_transform
from recon.types import (
    FloatArray,
    Method,
    ReconParams,
    Reconstruction,
    Recording,
    Registration,
    Scan,
    Segment,
)

#: One segment's reconstruction: (points, kind, scan model or None, params, N_P half-width).
SegmentMethod = Callable[
    [FloatArray, SegmentKind, ScanModel | None, ReconParams, int], SegmentResult
]
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
    """The resampled path, its segments (``[start, stop)``, sharing corners, never spanning two
    pieces of the trace), N_P's half-width in points, and the piece of each resampled point."""

    resampled: ResampledPath
    bounds: list[tuple[int, int]]
    half_width: int
    piece: NDArray[np.int64]


def plan_segments(recording: Recording, params: ReconParams) -> SegmentPlan:
    """Algorithm 1's path part: resample equidistantly and split at corners, piece by piece
    (the stretch between two pieces was not traced: nothing is resampled across it).

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
    bounds: list[tuple[int, int]] = []
    offset = 0
    for part in parts:
        corners = find_corners(
            part.points_m,
            spacing_m=part.spacing_m,
            angle_deg=params.corner_angle_deg,
            scale_m=params.corner_scale_m,
        )
        bounds += [(offset + a, offset + b) for a, b in split_at(len(part.points_m), corners)]
        offset += len(part.points_m)
    resampled = parts[0] if len(parts) == 1 else _joined(parts)
    return SegmentPlan(
        resampled=resampled,
        bounds=bounds,
        half_width=max(1, int(round(params.radius_m / resampled.spacing_m))),
        piece=np.repeat(np.arange(len(parts)), [len(p.points_m) for p in parts]),
    )


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

    def stacked(name: str):
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
    path: Recording | FloatArray,
    scan: Scan | None = None,
    *,
    params: ReconParams | None = None,
    T_scan_tracker_init: FloatArray | None = None,
) -> Reconstruction:
    """Reconstruct a traced path, using the scan's structure where there is one.

    Parameters
    ----------
    path : Recording or ndarray of shape (N, 3), metres
        The trace, tracker frame. A recording in pieces (``Recording.piece``) is resampled and
        fitted piece by piece (no segment spans two), with one registration for all of them.
    scan : Scan, optional
        The workpiece, scan frame. Without it (or with ``alpha=1``) only the path is used, as in
        the paper's Fig. 8.
    params : ReconParams, optional
    T_scan_tracker_init : ndarray of shape (4, 4), optional
        Known or approximate transform from tracker to scan frame (a stored calibration);
        identity if not given. Registration refines it unless ``params.register`` is False.

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
    """
    params = params or ReconParams()
    recording = path if isinstance(path, Recording) else Recording(points_m=path)
    check_scales(recording.points_m, None if scan is None else scan.points_m)
    plan = plan_segments(recording, params)
    resampled, bounds, half_width = plan.resampled, plan.bounds, plan.half_width
    points = resampled.points_m

    notes: list[str] = []
    registration: Registration | None = None
    model: ScanModel | None = None
    T_scan_tracker: FloatArray | None = None
    if scan is not None and params.uses_scan:
        prepared = prepare_scan_model(
            points, scan, bounds, params, T_scan_tracker_init=T_scan_tracker_init
        )
        model, T_scan_tracker = prepared.model, prepared.T_scan_tracker
        registration = prepared.registration
        work_points = apply_transform(T_scan_tracker, points)
        classes = classify_segments(work_points, bounds, model, params)
    else:
        work_points = points
        classes = [PATH_ONLY] * len(bounds)

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
        results.append(method(seg_points, kind, model, params, half_width))
        if kind == SegmentKind.PATH and model is not None:
            notes.append(f"segment {len(segments) - 1} has no scan near it: path only")
    if T_scan_tracker is not None:
        T_tracker_scan = invert_transform(T_scan_tracker)
        for result in results:
            result.points = apply_transform(T_tracker_scan, result.points)

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
    )


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
) -> Reconstruction:
    """Concatenate segment results; a corner point shared by two segments takes the later one."""
    n = len(resampled.points_m)
    points = np.empty((n, 3))
    mode = np.empty(n, np.int8)
    segment = np.empty(n, np.int64)
    n_path = np.empty(n, np.int64)
    n_surface = np.empty(n, np.int64)
    residual_path = np.empty(n)
    residual_surface = np.empty(n)
    alpha = np.empty(n)
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
    )
