"""Reconstruction of a traced path with the structure of a scan (the paper's Algorithms 1 and 2).

Two methods, both vectorised over all path points (no Python loop per point):

``paper``
    Eq. (4): PCA of the path neighbourhood N_P and of the scan neighbourhood N_S separately,
    polynomials f_P and f_S fitted in their principal planes, and the point rebuilt from the
    path's frame as ``mu_P + C_P^x x + C_P^y beta (alpha f_P(x) + (1 - alpha) f_S(x))``. Only the
    *shape* of the scan enters, never its position, and the third component is dropped.

``anchored`` (ours)
    Once the scan is registered, its absolute position is known, and that is what removes the
    slow drift off the feature that no window-sized smoother can see. The path is smoothed by a
    3-D polynomial (all three components kept); the scan supplies a target point: on the edge
    (a 3-D polynomial through the thinned edge points near it) or on the surface (the point's
    projection onto a local quadric along the surface normal, which is all a surface defines).
    The result is ``p + beta (alpha s + (1 - alpha) t - p)`` for smoothed point s and target t.

``alpha="auto"`` chooses the balance per point by inverse-variance weighting,
``alpha = var_scan / (var_scan + var_path)``:

* ``paper``: the variances of the two fitted values f_P(x) and f_S(x), each the fit's residual
  variance times its leverage at x.
* ``anchored``: var_scan is the variance of the target from its fit (thinned edge points are
  correlated over a face-fit ball, so their count is discounted accordingly). var_path must include
  the drift, which the path's own residuals cannot show; it is estimated by the method of moments
  from the path-to-target discrepancy averaged over a long stretch (ten radii),
  ``E|s - t|^2 - var_scan``, and is never below the smoothed path's own variance.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter1d
from scipy.spatial import cKDTree

from recon.align import apply_transform, invert_transform, register_icp
from recon.errors import DegenerateInputError, UnitsMismatchError
from recon.features import EdgePoints, ScanFeatures, prepare_scan, thin_edges
from recon.fitting import (
    PCA,
    fit_linear,
    fit_linear_robust,
    gather,
    poly_design,
    quadric_design,
    weighted_pca,
    window_indices,
)
from recon.resample import ResampledPath, resample_equidistant
from recon.segment import find_corners, split_at
from recon.types import (
    FloatArray,
    PointMode,
    ReconParams,
    Reconstruction,
    Recording,
    Registration,
    Scan,
    Segment,
)

#: Rows processed at once; bounds memory (a chunk holds chunk x K neighbours).
CHUNK = 2048
#: The edge-line fits use balls this much larger than the curvature ball, to reach past the
#: crest's band of blended normals onto both faces with enough points on each.
EDGE_FIT_RADIUS_FACTOR = 2.0
#: Edge lines are fitted every this fraction of the fit radius along the path (4 mm for a 16 mm
#: ball): neighbouring fits share most of their points, so denser fits add cost, not information.
EDGE_QUERY_SPACING_FRACTION = 0.375
#: Spacing of the points sampled along each fitted edge line.
EDGE_SAMPLE_SPACING_M = 0.001
#: Edge points whose direction differs from the path's by more than this are another edge
#: (the other leg of a corner) and are left out of N_S.
EDGE_DIRECTION_TOLERANCE_DEG = 30.0
#: A segment whose points lie this close (median) to the thinned edge follows it: 2.5 times
#: the operator's typical error (paper, Sec. VI: std 0.5-1 mm).
EDGE_FOLLOW_DISTANCE_M = 0.0025
#: The anchored method's drift estimate averages the path-to-scan discrepancy over this many radii.
DRIFT_WINDOW_RADII = 10.0
#: Nearest scan neighbours per point for the surface fits of the anchored method.
SURFACE_NEIGHBOURS = 128
EDGE_SCAN_RADII = 1.5
SURFACE_SCAN_RADII = 1.5


class ScanContext:
    """The scan's structure near the path (scan frame), with search trees built on first use.

    ``edges`` is set once the edge band has been thinned (which needs the trees).
    """

    def __init__(
        self, features: ScanFeatures, *, edge_spacing_m: float, edge_fit_radius_m: float
    ) -> None:
        self.features = features
        self.edges = EdgePoints(
            np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
        )
        self.edge_spacing_m = edge_spacing_m  # distance between edge-line fits
        self.edge_fit_radius_m = edge_fit_radius_m

    @cached_property
    def coarse_tree(self) -> cKDTree:
        return cKDTree(self.features.points_m)

    @cached_property
    def dense_tree(self) -> cKDTree:
        return cKDTree(self.features.dense_points_m)

    @cached_property
    def edge_tree(self) -> cKDTree | None:
        return cKDTree(self.edges.points_m) if len(self.edges) else None


@dataclass
class _SegmentResult:
    points: FloatArray
    mode: NDArray[np.int8]
    n_path: NDArray[np.int64]
    n_surface: NDArray[np.int64]
    residual_path: FloatArray
    residual_surface: FloatArray
    alpha: FloatArray

    @classmethod
    def unchanged(cls, points: FloatArray) -> _SegmentResult:
        n = len(points)
        return cls(
            points=points.copy(),
            mode=np.full(n, PointMode.UNCHANGED, np.int8),
            n_path=np.zeros(n, np.int64),
            n_surface=np.zeros(n, np.int64),
            residual_path=np.full(n, np.nan),
            residual_surface=np.full(n, np.nan),
            alpha=np.ones(n),
        )


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
    """The resampled path, its segments (``[start, stop)``, sharing corners) and N_P's half-width
    in points."""

    resampled: ResampledPath
    bounds: list[tuple[int, int]]
    half_width: int


def plan_segments(recording: Recording, params: ReconParams) -> SegmentPlan:
    """Algorithm 1's path part: resample equidistantly and split at corners.

    Raises
    ------
    DegenerateInputError
        Too few points after resampling for a fit of ``params.degree``.
    """
    resampled = resample_equidistant(
        recording.points_m,
        spacing_m=params.spacing_m,
        t_s=recording.t_s,
        orientations_xyzw=recording.orientations_xyzw,
    )
    points = resampled.points_m
    if len(points) < params.degree + 2:
        raise DegenerateInputError(
            f"the path has only {len(points)} points after resampling at "
            f"{params.spacing_m * 1000:.2f} mm; a degree-{params.degree} fit needs at least "
            f"{params.degree + 2}: record a longer trace or lower the spacing"
        )
    corners = find_corners(
        points,
        spacing_m=resampled.spacing_m,
        angle_deg=params.corner_angle_deg,
        scale_m=params.corner_scale_m,
    )
    return SegmentPlan(
        resampled=resampled,
        bounds=split_at(len(points), corners),
        half_width=max(1, int(round(params.radius_m / resampled.spacing_m))),
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
        The trace, tracker frame.
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
        In the tracker frame, one point per resampled input point.

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
    context: ScanContext | None = None
    # With a scan, the work is done in the scan frame (every fit here is rigid-equivariant) and
    # only the result is mapped back: cheaper than moving the scan and rebuilding its trees.
    T_scan_tracker = np.eye(4)
    if scan is not None and params.uses_scan:
        context, T_scan_tracker, registration = _prepare_context(
            points, scan, bounds, params, T_scan_tracker_init
        )
        work_points = apply_transform(T_scan_tracker, points)
        kinds = _classify(work_points, bounds, context, params)
    else:
        work_points = points
        kinds = [("path", 0.0)] * len(bounds)

    results = []
    segments = []
    method = _anchored_segment if params.method == "anchored" else _paper_segment
    for (start, stop), (kind, fraction) in zip(bounds, kinds, strict=True):
        seg_points = work_points[start:stop]
        segments.append(Segment(start=start, stop=stop, kind=kind, edge_fraction=fraction))
        if len(seg_points) < 3:
            results.append(_SegmentResult.unchanged(seg_points))
            notes.append(f"segment {len(segments) - 1} has {len(seg_points)} points: left as is")
            continue
        results.append(method(seg_points, kind, context, params, half_width))
        if kind == "path" and context is not None:
            notes.append(f"segment {len(segments) - 1} has no scan near it: path only")
    if context is not None:
        T_tracker_scan = invert_transform(T_scan_tracker)
        for result in results:
            result.points = apply_transform(T_tracker_scan, result.points)

    return _assemble(resampled, bounds, segments, results, registration, params, notes)


def scan_context(
    points_m: FloatArray,
    scan: Scan,
    *,
    params: ReconParams | None = None,
    T_scan_tracker_init: FloatArray | None = None,
) -> tuple[ScanContext, FloatArray, Registration | None]:
    """The scan's structure near a path (scan frame) and the path's registration to it.

    What :func:`reconstruct` does before its per-point stage, for callers that need the scan at
    points of their own (tool orientations at a reconstructed path).

    Returns
    -------
    context : ScanContext
    T_scan_tracker : ndarray of shape (4, 4)
    registration : Registration or None
    """
    params = params or ReconParams()
    plan = plan_segments(Recording(points_m=points_m), params)
    return _prepare_context(plan.resampled.points_m, scan, plan.bounds, params, T_scan_tracker_init)


def _prepare_context(
    points: FloatArray,
    scan: Scan,
    bounds: list[tuple[int, int]],
    params: ReconParams,
    T_init: FloatArray | None,
) -> tuple[ScanContext, FloatArray, Registration | None]:
    """Features of the scan near the path (scan frame), and T_scan_tracker after registration."""
    T_scan_tracker = np.eye(4) if T_init is None else np.asarray(T_init, dtype=np.float64)
    path_in_scan = apply_transform(T_scan_tracker, points)
    features = prepare_scan(
        scan.points_m,
        path_in_scan,
        crop_margin_m=params.crop_margin_m,
        voxel_m=params.voxel_m,
        curvature_radius_m=params.curvature_radius_m,
        edge_curvature=params.edge_curvature,
    )
    fit_radius = EDGE_FIT_RADIUS_FACTOR * params.curvature_radius_m
    query_spacing = EDGE_QUERY_SPACING_FRACTION * fit_radius
    context = ScanContext(features, edge_spacing_m=query_spacing, edge_fit_radius_m=fit_radius)
    edges = thin_edges(
        features,
        path_in_scan,
        radius_m=fit_radius,
        query_spacing_m=query_spacing,
        sample_spacing_m=EDGE_SAMPLE_SPACING_M,
        trees=(context.coarse_tree, context.dense_tree),
    )
    context.edges = edges

    registration = None
    if params.register:
        kinds = _classify(path_in_scan, bounds, context, params)
        on_edge = np.zeros(len(points), dtype=bool)
        for (start, stop), (kind, _) in zip(bounds, kinds, strict=True):
            on_edge[start:stop] |= kind == "edge"
        if np.count_nonzero(on_edge) >= 0.5 * len(points) and len(edges) >= 10:
            registration = register_icp(
                points[on_edge],
                edges.points_m,
                init_T_target_source=T_scan_tracker,
                max_distance_m=params.icp_max_distance_m,
                target_directions=edges.directions,
                target_label="edge",
            )
        else:
            registration = register_icp(
                points,
                features.points_m,
                init_T_target_source=T_scan_tracker,
                max_distance_m=params.icp_max_distance_m,
                target_normals=features.normals,
                target_label="surface",
            )
        T_scan_tracker = registration.T_scan_tracker
    return context, T_scan_tracker, registration


def _classify(
    points: FloatArray, bounds: list[tuple[int, int]], context: ScanContext, params: ReconParams
) -> list[tuple[str, float]]:
    """Per segment: follows an "edge", a "surface", or nothing of the scan ("path").

    The paper's rule: a segment follows an edge when a large fraction (``edge_fraction``) of the
    scan points nearest to it are edge points. Curvature flags thin out as scan noise grows
    (at 1.5 mm the fraction on a traced right-angle ridge fell to 0.48), so a segment also
    follows an edge when the thinned edge (the fitted intersection of two faces) runs within
    :data:`EDGE_FOLLOW_DISTANCE_M` of it on median. Either way it must have thinned edge points
    along at least half of it. A segment with scan points near less than half of its points has
    nothing to follow.
    """
    reach = params.icp_max_distance_m
    dist, idx = context.coarse_tree.query(points, k=5, distance_upper_bound=reach, workers=-1)
    near = np.isfinite(dist)
    n_coarse = context.coarse_tree.n
    is_edge = gather(context.features.is_edge.astype(np.float64), idx, n_coarse) > 0.5
    supported = near.any(axis=1)
    point_fraction = (is_edge & near).sum(axis=1) / np.maximum(near.sum(axis=1), 1)
    if context.edge_tree is not None:
        edge_dist, _ = context.edge_tree.query(points, distance_upper_bound=params.radius_m)
    else:
        edge_dist = np.full(len(points), np.inf)
    edge_near = np.isfinite(edge_dist)
    kinds = []
    for start, stop in bounds:
        seg = slice(start, stop)
        if supported[seg].mean() < 0.5:
            kinds.append(("path", 0.0))
            continue
        fraction = float(point_fraction[seg][supported[seg]].mean())
        on_thinned_edge = np.median(edge_dist[seg]) <= EDGE_FOLLOW_DISTANCE_M
        if (fraction >= params.edge_fraction or on_thinned_edge) and edge_near[seg].mean() >= 0.5:
            kinds.append(("edge", fraction))
        else:
            kinds.append(("surface", fraction))
    return kinds


def _path_frame(neighbourhoods: FloatArray) -> PCA:
    """PCA of N_P with C^x pointing along the direction of travel (right-handed frame)."""
    pca = weighted_pca(neighbourhoods)
    axes = pca.axes.copy()
    travel = neighbourhoods[:, -1] - neighbourhoods[:, 0]
    flip = np.einsum("bi,bi->b", axes[:, :, 0], travel) < 0
    axes[flip, :, 0] *= -1
    axes[:, :, 2] = np.cross(axes[:, :, 0], axes[:, :, 1])
    return PCA(mean=pca.mean, axes=axes, variances=pca.variances, weight=pca.weight)


def align_scan_axes(scan_axes: FloatArray, path_axes: FloatArray) -> FloatArray:
    """Order and sign the scan neighbourhood's principal axes to match the path's.

    PCA axes have arbitrary signs, and for a patch of surface the in-plane axes may come in any
    order relative to the path. C_S^x is signed like C_P^x; C_S^y is whichever of the scan's
    second and third axes is closer to C_P^y, signed like it; C_S^z completes a right-handed frame.

    Parameters
    ----------
    scan_axes, path_axes : ndarray of shape (B, 3, 3)
        Columns are principal directions, largest variance first.

    Returns
    -------
    ndarray of shape (B, 3, 3)
    """
    x = (
        scan_axes[:, :, 0]
        * np.sign(np.einsum("bi,bi->b", scan_axes[:, :, 0], path_axes[:, :, 0]) + 1e-300)[:, None]
    )
    dot2 = np.einsum("bi,bi->b", scan_axes[:, :, 1], path_axes[:, :, 1])
    dot3 = np.einsum("bi,bi->b", scan_axes[:, :, 2], path_axes[:, :, 1])
    use_third = np.abs(dot3) > np.abs(dot2)
    y = np.where(use_third[:, None], scan_axes[:, :, 2], scan_axes[:, :, 1])
    y *= np.sign(np.where(use_third, dot3, dot2) + 1e-300)[:, None]
    return np.stack([x, y, np.cross(x, y)], axis=2)


def _edge_neighbourhoods(
    centres: FloatArray, path_direction: FloatArray, context: ScanContext, radius_m: float
) -> tuple[FloatArray, FloatArray]:
    """N_S on an edge: thinned edge points within ``radius_m`` that run along the path.

    Returns
    -------
    points : ndarray of shape (B, K, 3)
    weights : ndarray of shape (B, K)
    index : ndarray of shape (B, K), int
        Into ``context.edges``; ``len(context.edges)`` marks padding.
    """
    edges = context.edges
    k = min(64, len(edges))
    dist, idx = context.edge_tree.query(centres, k=k, distance_upper_bound=radius_m, workers=-1)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    pts = gather(edges.points_m, idx, fill_index=len(edges))
    dirs = gather(edges.directions, idx, fill_index=len(edges))
    along = np.abs(np.einsum("bki,bi->bk", dirs, path_direction))
    weights = np.isfinite(dist) & (along >= np.cos(np.radians(EDGE_DIRECTION_TOLERANCE_DEG)))
    return pts, weights.astype(np.float64), idx


def _path_fit(points, windows, rows, degree, scale, outputs):
    """N_P's principal frame and a polynomial fit of its transverse components.

    Parameters
    ----------
    points : ndarray of shape (n, 3)
        The segment.
    windows : ndarray of shape (B, w), int
        N_P of the chunk's points.
    rows : slice
        The chunk's points.
    outputs : {1, 2}
        Fit the second principal component only (Eq. 3), or the second and third.

    Returns
    -------
    frame : PCA
    x_i : ndarray of shape (B,)
        The points' first principal coordinates.
    design_at : ndarray of shape (B, degree + 1)
        The polynomial basis at x_i.
    fit : LinearFit
    """
    neighbourhood = points[windows]
    frame = _path_frame(neighbourhood)
    local = frame.to_local(neighbourhood)
    x_i = frame.to_local(points[rows])[:, 0]
    design_at = poly_design(x_i, degree=degree, scale=scale)
    fit = fit_linear(
        poly_design(local[..., 0], degree=degree, scale=scale), local[..., 1 : 1 + outputs], None
    )
    return frame, x_i, design_at, fit


def _paper_segment(
    points: FloatArray,
    kind: str,
    context: ScanContext | None,
    params: ReconParams,
    half_width: int,
) -> _SegmentResult:
    """Eq. (4) of the paper for every point of one segment."""
    n = len(points)
    windows = window_indices(n, half_width)
    degree = min(params.degree, windows.shape[1] - 2)
    scale = params.radius_m
    use_scan = kind != "path" and params.alpha != 1.0
    if use_scan and kind == "surface":
        # N_S on a surface: the k nearest scan points of every point of N_P.
        _, knn = context.dense_tree.query(points, k=params.surface_k, workers=-1)
    out = _SegmentResult.unchanged(points)
    for rows in _chunks(n):
        # Eq. (3)'s path polynomial lives in the principal plane: only the second component.
        frame, x_i, design_at, fit_p = _path_fit(points, windows[rows], rows, degree, scale, 1)
        f_p = fit_p.predict(design_at)[:, 0]
        alpha = np.ones(len(x_i))
        f_s = np.zeros(len(x_i))
        n_surface = np.zeros(len(x_i), np.int64)
        residual_s = np.full(len(x_i), np.nan)
        if use_scan:
            if kind == "edge":
                ns, ws, _ = _edge_neighbourhoods(
                    points[rows], frame.axes[:, :, 0], context, params.radius_m
                )
            else:
                ns = context.features.dense_points_m[knn[windows[rows]].reshape(len(x_i), -1)]
                ws = np.ones(ns.shape[:2])
            scan_frame = weighted_pca(ns, ws)
            axes_s = align_scan_axes(scan_frame.axes, frame.axes)
            local_s = np.einsum("bij,bki->bkj", axes_s, ns - scan_frame.mean[:, None])
            fit_s, ws = fit_linear_robust(
                poly_design(local_s[..., 0], degree=degree, scale=scale),
                local_s[..., 1],
                ws,
                floor=1e-5,
            )
            ok = fit_s.dof >= 1
            f_s = fit_s.predict(design_at)[:, 0]
            if params.alpha == "auto":
                var_p = fit_p.rms**2 * fit_p.leverage(design_at)
                var_s = fit_s.rms**2 * fit_s.leverage(design_at)
                alpha = var_s / np.maximum(var_p + var_s, 1e-300)
            else:
                alpha = np.full(len(x_i), float(params.alpha))
            alpha = np.where(ok, alpha, 1.0)
            f_s = np.where(ok, f_s, 0.0)
            n_surface = np.where(ok, np.count_nonzero(ws, axis=1), 0)
            residual_s = np.where(ok, fit_s.rms, np.nan)
            out.mode[rows] = np.where(
                ok, PointMode.EDGE if kind == "edge" else PointMode.SURFACE, PointMode.PATH
            )
        else:
            out.mode[rows] = PointMode.PATH
        beta = params.beta
        offset = beta * (alpha * f_p + (1.0 - alpha) * f_s)
        out.points[rows] = (
            frame.mean + frame.axes[:, :, 0] * x_i[:, None] + frame.axes[:, :, 1] * offset[:, None]
        )
        out.n_path[rows] = windows.shape[1]
        out.n_surface[rows] = n_surface
        out.residual_path[rows] = fit_p.rms
        out.residual_surface[rows] = residual_s
        out.alpha[rows] = alpha
    return out


def _anchored_segment(
    points: FloatArray,
    kind: str,
    context: ScanContext | None,
    params: ReconParams,
    half_width: int,
) -> _SegmentResult:
    """The anchored method for every point of one segment (see the module docstring)."""
    n = len(points)
    windows = window_indices(n, half_width)
    degree = min(params.degree, windows.shape[1] - 2)
    scale = params.radius_m
    use_scan = kind != "path" and params.alpha != 1.0
    out = _SegmentResult.unchanged(points)
    smoothed = np.empty_like(points)
    target = points.copy()
    var_path_fit = np.zeros(n)
    var_target = np.full(n, np.inf)
    supported = np.zeros(n, dtype=bool)
    for rows in _chunks(n):
        # A 3-D curve: both transverse components as polynomials of the first.
        frame, x_i, design_at, fit_p = _path_fit(points, windows[rows], rows, degree, scale, 2)
        on_curve = np.column_stack([x_i, fit_p.predict(design_at)])
        smoothed[rows] = frame.to_world(on_curve)
        var_path_fit[rows] = fit_p.rms**2 * fit_p.leverage(design_at)
        out.n_path[rows] = windows.shape[1]
        out.residual_path[rows] = fit_p.rms
        if not use_scan:
            continue
        if kind == "edge":
            t, var_t, count, resid = _edge_targets(
                smoothed[rows], frame.axes[:, :, 0], context, params, degree
            )
        else:
            t, var_t, count, resid = _surface_targets(smoothed[rows], context, params)
        ok = np.isfinite(var_t)
        target[rows] = np.where(ok[:, None], t, smoothed[rows])
        var_target[rows] = var_t
        supported[rows] = ok
        out.n_surface[rows] = np.where(ok, count, 0)
        out.residual_surface[rows] = np.where(ok, resid, np.nan)

    if use_scan:
        if params.alpha == "auto":
            alpha = _auto_alpha(smoothed, target, var_target, var_path_fit, supported, half_width)
        else:
            alpha = np.full(n, float(params.alpha))
        alpha = np.where(supported, alpha, 1.0)
        out.mode[:] = np.where(
            supported, PointMode.EDGE if kind == "edge" else PointMode.SURFACE, PointMode.PATH
        )
    else:
        alpha = np.ones(n)
        out.mode[:] = PointMode.PATH
    blended = alpha[:, None] * smoothed + (1.0 - alpha[:, None]) * target
    out.points[:] = points + params.beta * (blended - points)
    out.alpha[:] = alpha
    return out


def _edge_targets(centres, direction, context, params, degree):
    """Nearest point of the local edge curve to each smoothed path point.

    A 3-D polynomial (both transverse components of the edge points' principal frame as
    functions of the first) is fitted robustly to the thinned edge points near the point.

    Returns
    -------
    target : (B, 3); var : (B,) (inf where unfit); count : (B,); residual : (B,)
    """
    if context.edge_tree is None:
        b = len(centres)
        return centres, np.full(b, np.inf), np.zeros(b, np.int64), np.full(b, np.nan)
    ns, ws, idx_s = _edge_neighbourhoods(
        centres, direction, context, EDGE_SCAN_RADII * params.radius_m
    )
    frame = weighted_pca(ns, ws)
    axes = frame.axes.copy()
    flip = np.einsum("bi,bi->b", axes[:, :, 0], direction) < 0
    axes[flip, :, 0] *= -1
    local = np.einsum("bij,bki->bkj", axes, ns - frame.mean[:, None])
    scale = params.radius_m
    fit, ws = fit_linear_robust(
        poly_design(local[..., 0], degree=degree, scale=scale), local[..., 1:], ws, floor=1e-5
    )
    x_at = np.einsum("bi,bi->b", axes[:, :, 0], centres - frame.mean)
    design_at = poly_design(x_at, degree=degree, scale=scale)
    target = frame.mean + np.einsum(
        "bij,bj->bi", axes, np.column_stack([x_at, fit.predict(design_at)])
    )
    var_from_scatter = fit.rms**2 * np.minimum(
        fit.leverage(design_at) * edge_dependence(context), 1.0
    )
    # The scatter about the local curve hides what the line fits share over a ball's diameter,
    # so the fits' own precision bounds the target's variance from below.
    line_variance = gather(context.edges.variance_m2, idx_s, fill_index=len(context.edges))
    var_from_fits = (ws * line_variance).sum(axis=1) / np.maximum(ws.sum(axis=1), 1e-300)
    var = np.maximum(var_from_scatter, var_from_fits)
    # Require support on both sides of short extrapolation: the point must lie within the span.
    span_ok = _within_span(local[..., 0], ws, x_at, margin=0.5 * params.radius_m)
    ok = (fit.dof >= 2) & span_ok
    count = np.count_nonzero(ws, axis=1)
    return target, np.where(ok, var, np.inf), count, fit.rms


def edge_dependence(context: ScanContext) -> float:
    """How many edge samples carry one sample's worth of independent information.

    Edge samples come from line fits in overlapping balls of the scan, so their errors are shared
    over a ball's diameter: count one independent sample per diameter, not one per sample.
    """
    return 2.0 * context.edge_fit_radius_m / EDGE_SAMPLE_SPACING_M


def _surface_targets(centres, context, params):
    """Each smoothed path point moved along the local surface normal onto a fitted quadric.

    Returns
    -------
    target : (B, 3); var : (B,) (inf where unfit); count : (B,); residual : (B,)
    """
    dense = context.features.dense_points_m
    k = min(SURFACE_NEIGHBOURS, len(dense))
    dist, idx = context.dense_tree.query(
        centres, k=k, distance_upper_bound=SURFACE_SCAN_RADII * params.radius_m, workers=-1
    )
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    ns = gather(dense, idx, fill_index=len(dense))
    ws = np.isfinite(dist).astype(np.float64)
    frame = weighted_pca(ns, ws)
    local = frame.to_local(ns)
    scale = params.radius_m
    fit, ws = fit_linear_robust(
        quadric_design(local[..., 0], local[..., 1], scale=scale), local[..., 2], ws, floor=1e-5
    )
    at = frame.to_local(centres)
    design_at = quadric_design(at[:, 0], at[:, 1], scale=scale)
    height = fit.predict(design_at)[:, 0]
    normal = frame.axes[:, :, 2]
    target = centres + (height - at[:, 2])[:, None] * normal
    var = fit.rms**2 * np.minimum(fit.leverage(design_at), 1.0)
    ok = fit.dof >= 4
    count = np.count_nonzero(ws, axis=1)
    return target, np.where(ok, var, np.inf), count, fit.rms


def _within_span(x: FloatArray, weights: FloatArray, x_at: FloatArray, *, margin: float):
    """Whether ``x_at`` lies within the weighted points' extent along x, plus ``margin``."""
    lo = np.where(weights > 0, x, np.inf).min(axis=1)
    hi = np.where(weights > 0, x, -np.inf).max(axis=1)
    return (x_at >= lo - margin) & (x_at <= hi + margin)


def _auto_alpha(smoothed, target, var_target, var_path_fit, supported, half_width):
    """Inverse-variance weight of the path (see the module docstring)."""
    discrepancy = np.where(supported, np.sum((smoothed - target) ** 2, axis=1), 0.0)
    size = int(2 * DRIFT_WINDOW_RADII * half_width + 1)
    weight = uniform_filter1d(supported.astype(np.float64), size, mode="nearest")
    mean_discrepancy = uniform_filter1d(discrepancy, size, mode="nearest") / np.maximum(
        weight, 1e-12
    )
    var_t = np.where(supported, var_target, 0.0)
    var_path = np.maximum(mean_discrepancy - var_t, var_path_fit)
    return var_t / np.maximum(var_t + var_path, 1e-300)


def _chunks(n: int):
    for start in range(0, n, CHUNK):
        yield slice(start, min(start + CHUNK, n))


def _assemble(
    resampled: ResampledPath,
    bounds: list[tuple[int, int]],
    segments: list[Segment],
    results: list[_SegmentResult],
    registration: Registration | None,
    params: ReconParams,
    notes: list[str],
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
    )
