"""A straightforward per-point-loop implementation of the reconstruction's per-point stage.

Independent of ``recon.fitting``: one point at a time with ``numpy.linalg.eigh`` for PCA,
``numpy.linalg.lstsq`` for the fits and a KD-tree ball query per point. Two uses:

* the tests check that the vectorised implementation gives the same points (an independent
  method, written from the paper and the module docstrings rather than from the batched code);
* the speed benchmark runs it as a whole command (``tests/bench/loop_command.py``) beside
  ``teachpath reconstruct``.

It consumes the same scan model (features, thinned edges, trees) as the vectorised code, so it
covers Algorithm 2 and the anchored method, not the scan preparation they share.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from recon import reconstruct as R
from recon.classify import PATH_ONLY, SegmentKind, check_consistency, classify_segments
from recon.methods import anchored as A
from recon.methods import common as C
from recon.methods.common import EDGE_DIRECTION_TOLERANCE_DEG
from recon.methods.paper import align_scan_axes
from recon.transforms import apply_transform, invert_transform
from recon.types import ReconParams


def _pca(points: np.ndarray, weights: np.ndarray | None = None):
    """Mean and principal axes (columns, largest variance first) of one neighbourhood."""
    if weights is None:
        weights = np.ones(len(points))
    w = weights / weights.sum()
    mean = w @ points
    centred = points - mean
    cov = (centred * w[:, None]).T @ centred
    values, vectors = np.linalg.eigh(cov)
    return mean, vectors[:, ::-1]


def _design(x: np.ndarray, degree: int, scale: float) -> np.ndarray:
    return np.vander(x / scale, degree + 1, increasing=True)


def _fit(design: np.ndarray, y: np.ndarray):
    """Least squares with the residual standard deviation and the normal matrix's inverse."""
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    y2 = y.reshape(len(y), -1)
    residual = y2 - design @ coef.reshape(design.shape[1], -1)
    dof = len(y) - design.shape[1]
    rms = np.sqrt(np.sum(residual**2) / max(dof * y2.shape[1], 1))
    return coef.reshape(design.shape[1], -1), rms, np.linalg.inv(design.T @ design), dof


def _fit_robust(design: np.ndarray, y: np.ndarray, *, floor: float = 1e-5):
    """Two rounds of dropping points more than 3 RMS (at least 3 ``floor``) off the fit."""
    keep = np.ones(len(y), dtype=bool)
    coef, rms, inverse, dof = _fit(design, y)
    for _ in range(2):
        y2 = y.reshape(len(y), -1)
        residual = np.linalg.norm(y2 - design @ coef, axis=1)
        keep = residual <= 3.0 * max(rms, floor)
        coef, rms, inverse, dof = _fit(design[keep], y[keep])
    return coef, rms, inverse, dof, keep


def _path_frame(window: np.ndarray):
    mean, axes = _pca(window)
    if axes[:, 0] @ (window[-1] - window[0]) < 0:
        axes[:, 0] *= -1
    axes[:, 2] = np.cross(axes[:, 0], axes[:, 1])
    return mean, axes


def _window(i: int, n: int, half: int) -> np.ndarray:
    w = min(2 * half + 1, n)
    start = min(max(i - half, 0), n - w)
    return np.arange(start, start + w)


def _edge_nbrs(centre, direction, model, radius):
    """Edge points near ``centre`` running along ``direction``, and their line-fit variances."""
    edges = model.edges
    idx = model.edge_tree.query_ball_point(centre, radius)
    idx = sorted(idx, key=lambda j: np.linalg.norm(edges.points_m[j] - centre))[:64]
    idx = np.array(
        [
            j
            for j in idx
            if abs(edges.directions[j] @ direction)
            >= np.cos(np.radians(EDGE_DIRECTION_TOLERANCE_DEG))
        ],
        dtype=int,
    )
    if not len(idx):
        return np.zeros((0, 3)), np.zeros(0)
    return edges.points_m[idx], edges.variance_m2[idx]


def paper_segment_loop(points, kind, model, params: ReconParams, half_width: int):
    """Eq. (4), one point at a time. Returns (points (n, 3), alpha (n,))."""
    n = len(points)
    degree = min(params.degree, min(2 * half_width + 1, n) - 2)
    scale = params.radius_m
    use_scan = kind != SegmentKind.PATH and params.alpha != 1.0
    out = np.empty_like(points)
    alphas = np.ones(n)
    for i in range(n):
        window = points[_window(i, n, half_width)]
        mean, axes = _path_frame(window)
        local = (window - mean) @ axes
        x_i = (points[i] - mean) @ axes[:, 0]
        design_at = _design(np.array([x_i]), degree, scale)[0]
        coef_p, rms_p, inv_p, _ = _fit(_design(local[:, 0], degree, scale), local[:, 1])
        f_p = float(design_at @ coef_p[:, 0])
        alpha, f_s = 1.0, 0.0
        if use_scan:
            if kind == SegmentKind.EDGE:
                ns, _ = _edge_nbrs(points[i], axes[:, 0], model, params.radius_m)
            else:
                ns = np.concatenate(
                    [
                        model.features.dense_points_m[
                            model.dense_tree.query(points[j], k=params.surface_k)[1]
                        ]
                        for j in _window(i, n, half_width)
                    ]
                )
            if len(ns) >= degree + 2:
                mean_s, axes_s = _pca(ns)
                axes_s = align_scan_axes(axes_s[None], axes[None])[0]
                local_s = (ns - mean_s) @ axes_s
                coef_s, rms_s, inv_s, dof_s, _ = _fit_robust(
                    _design(local_s[:, 0], degree, scale), local_s[:, 1]
                )
                if dof_s >= 1:
                    f_s = float(design_at @ coef_s[:, 0])
                    if params.alpha == "auto":
                        var_p = rms_p**2 * design_at @ inv_p @ design_at
                        var_s = rms_s**2 * design_at @ inv_s @ design_at
                        alpha = var_s / max(var_p + var_s, 1e-300)
                    else:
                        alpha = float(params.alpha)
        offset = params.beta * (alpha * f_p + (1.0 - alpha) * f_s)
        out[i] = mean + axes[:, 0] * x_i + axes[:, 1] * offset
        alphas[i] = alpha
    return out, alphas


def _adaptive_point(points, i, half_width, params):
    """Point i smoothed by the widest window that agrees with every narrower one (see
    recon.methods.common.adaptive_smoothing), as (point, variance)."""
    n = len(points)
    estimates = []
    for factor in C.ADAPTIVE_FACTORS:
        h = half_width * factor
        if factor > 1 and 2 * h + 1 > n:
            break
        window = points[_window(i, n, h)]
        degree = min(params.degree, len(window) - 2)
        scale = params.radius_m * factor
        mean, axes = _path_frame(window)
        local = (window - mean) @ axes
        x_i = (points[i] - mean) @ axes[:, 0]
        design_at = _design(np.array([x_i]), degree, scale)[0]
        coef, rms, inverse, _ = _fit(_design(local[:, 0], degree, scale), local[:, 1:])
        point = mean + axes @ np.concatenate([[x_i], design_at @ coef])
        estimates.append((point, rms**2 * design_at @ inverse @ design_at))
    chosen = 0
    for j in range(1, len(estimates)):
        agree = all(
            np.linalg.norm(estimates[j][0] - estimates[k][0])
            <= C.ADAPTIVE_GAMMA * (np.sqrt(estimates[j][1]) + np.sqrt(estimates[k][1]))
            for k in range(j)
        )
        if not agree:
            break
        chosen = j
    return estimates[chosen]


def anchored_segment_loop(points, kind, model, params: ReconParams, half_width: int):
    """The anchored method, one point at a time. Returns (points (n, 3), alpha (n,))."""
    n = len(points)
    degree = min(params.degree, min(2 * half_width + 1, n) - 2)
    scale = params.radius_m
    use_scan = kind != SegmentKind.PATH and params.alpha != 1.0
    smoothed = np.empty_like(points)
    target = points.copy()
    var_fit = np.zeros(n)
    var_t = np.full(n, np.inf)
    for i in range(n):
        window = points[_window(i, n, half_width)]
        mean, axes = _path_frame(window)
        local = (window - mean) @ axes
        x_i = (points[i] - mean) @ axes[:, 0]
        design_at = _design(np.array([x_i]), degree, scale)[0]
        coef, rms, inverse, _ = _fit(_design(local[:, 0], degree, scale), local[:, 1:])
        smoothed[i] = mean + axes @ np.concatenate([[x_i], design_at @ coef])
        var_fit[i] = rms**2 * design_at @ inverse @ design_at
        if kind != SegmentKind.EDGE:
            smoothed[i], var_fit[i] = _adaptive_point(points, i, half_width, params)
        if not use_scan:
            continue
        if kind == SegmentKind.EDGE:
            ns, line_var = _edge_nbrs(
                smoothed[i], axes[:, 0], model, A.EDGE_SCAN_RADII * params.radius_m
            )
            if len(ns) < degree + 3:
                continue
            mean_s, axes_s = _pca(ns)
            if axes_s[:, 0] @ axes[:, 0] < 0:
                axes_s[:, 0] *= -1
            local_s = (ns - mean_s) @ axes_s
            coef_s, rms_s, inv_s, dof_s, keep = _fit_robust(
                _design(local_s[:, 0], degree, scale), local_s[:, 1:]
            )
            x_at = (smoothed[i] - mean_s) @ axes_s[:, 0]
            d_at = _design(np.array([x_at]), degree, scale)[0]
            xs = local_s[keep, 0]
            margin = A.EDGE_SPAN_MARGIN_RADII * params.radius_m
            inside = xs.min() - margin <= x_at <= xs.max() + margin
            if dof_s >= 2 and inside and np.count_nonzero(keep) >= A.MIN_EDGE_SAMPLES:
                target[i] = mean_s + axes_s @ np.concatenate([[x_at], d_at @ coef_s])
                scatter = rms_s**2 * min(d_at @ inv_s @ d_at * A.edge_dependence(model), 1.0)
                # The line fits' own precision, averaged over the points the fit kept.
                var_t[i] = max(scatter, float(np.mean(line_var[keep])))
        else:
            dense = model.features.dense_points_m
            idx = model.dense_tree.query_ball_point(
                smoothed[i], A.SURFACE_SCAN_RADII * params.radius_m
            )
            idx = sorted(idx, key=lambda j: np.linalg.norm(dense[j] - smoothed[i]))
            ns = dense[np.array(idx[: A.SURFACE_NEIGHBOURS], dtype=int)]
            if len(ns) < 7:
                continue
            mean_s, axes_s = _pca(ns)
            local_s = (ns - mean_s) @ axes_s
            u, v = local_s[:, 0] / scale, local_s[:, 1] / scale
            design = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
            coef_s, rms_s, inv_s, dof_s, _ = _fit_robust(design, local_s[:, 2])
            at = (smoothed[i] - mean_s) @ axes_s
            a, b = at[0] / scale, at[1] / scale
            d_at = np.array([1.0, a, b, a * a, a * b, b * b])
            if dof_s >= 4:
                height = float(d_at @ coef_s[:, 0])
                target[i] = smoothed[i] + (height - at[2]) * axes_s[:, 2]
                var_t[i] = rms_s**2 * min(d_at @ inv_s @ d_at, 1.0)
    supported = np.isfinite(var_t)
    if not use_scan:
        alpha = np.ones(n)
    elif params.alpha == "auto":
        size = int(2 * A.DRIFT_WINDOW_RADII * half_width + 1)
        half = size // 2
        disc = np.where(supported, np.sum((smoothed - target) ** 2, axis=1), 0.0)
        alpha = np.ones(n)
        for i in range(n):
            idx = np.clip(np.arange(i - half, i - half + size), 0, n - 1)
            mean_disc = disc[idx].mean() / max(supported[idx].mean(), 1e-12)
            vt = var_t[i] if supported[i] else 0.0
            var_path = max(mean_disc - vt, var_fit[i])
            alpha[i] = vt / max(vt + var_path, 1e-300)
    else:
        alpha = np.full(n, float(params.alpha))
    alpha = np.where(supported, alpha, 1.0)
    blended = alpha[:, None] * smoothed + (1.0 - alpha[:, None]) * target
    return points + params.beta * (blended - points), alpha


def reconstruct_loop(recording, scan, params: ReconParams, T_scan_tracker_init=None):
    """The whole reconstruction with the per-point stage replaced by the loops above.

    Returns
    -------
    points : ndarray of shape (N, 3)
        Tracker frame, one per resampled point (the corner point of two segments from the later
        one, as in ``recon.reconstruct``).
    """
    plan = R.plan_segments(recording, params)
    points, bounds, half = plan.resampled.points_m, plan.bounds, plan.half_width
    T = np.eye(4)
    model = None
    if scan is not None and params.uses_scan:
        prepared = R.prepare_scan_model(
            points, scan, bounds, params, T_scan_tracker_init=T_scan_tracker_init
        )
        model, T = prepared.model, prepared.T_scan_tracker
    work = apply_transform(T, points)
    # Where the segments are is the pipeline's structure, not the per-point stage: shared.
    corners = R.judge_corners(plan, work, model, params)
    bounds = plan.split([c.index for c in corners if c.split])
    if model is not None:
        model = R.with_corner_edges(model, corners)
        classes = classify_segments(work, bounds, model, params)
        classes, _ = check_consistency(work, bounds, classes, model)
    else:
        classes = [PATH_ONLY] * len(bounds)
    loop = anchored_segment_loop if params.method == "anchored" else paper_segment_loop
    results = []
    for (start, stop), segment_class in zip(bounds, classes, strict=True):
        result, _ = loop(work[start:stop], segment_class.kind, model, params, half)
        results.append(SimpleNamespace(points=result))
    R.join_at_corners(
        bounds,
        results,
        corners,
        [c.kind for c in classes],
        work,
        spacing_m=plan.resampled.spacing_m,
        beta=params.beta,
    )
    out = np.empty_like(points)
    for (start, stop), result in zip(bounds, results, strict=True):
        out[start:stop] = result.points
    return apply_transform(invert_transform(T), out)
