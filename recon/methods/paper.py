"""The paper's method (Eq. 4): PCA frames and polynomial fits of N_P and N_S, shape only.

PCA of the path neighbourhood N_P and of the scan neighbourhood N_S separately, polynomials f_P
and f_S fitted in their principal planes, and the point rebuilt from the path's frame as
``mu_P + C_P^x x + C_P^y beta (alpha f_P(x) + (1 - alpha) f_S(x))``. Only the *shape* of the
scan enters, never its position, and the third component is dropped.

``alpha="auto"`` weighs the two fitted values by inverse variance: each the fit's residual
variance times its leverage at x, ``alpha = var_S / (var_S + var_P)``.
"""

from __future__ import annotations

import numpy as np

from recon.arrays import FloatArray
from recon.classify import SegmentKind
from recon.fitting import fit_linear_robust, poly_design, weighted_pca, window_indices
from recon.methods.common import (
    SegmentResult,
    chunks,
    edge_neighbourhoods,
    path_fit,
    prior_variance,
)
from recon.recon_params import ReconParams
from recon.results import PointMode
from recon.scan_model import ScanModel


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


def paper_segment(
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
    """Eq. (4) of the paper for every point of one segment.

    Parameters
    ----------
    points : ndarray of shape (n, 3), metres
        The segment, scan frame (tracker frame without a scan).
    kind : SegmentKind
        What the segment follows; N_S is the thinned edge near each point for an edge, the
        ``params.surface_k`` nearest dense scan points of every point of N_P for a surface.
    model : ScanModel or None
        None only for ``kind`` PATH.
    params : ReconParams
    half_width : int
        N_P's half-width, in points.
    prior_variance_m2 : ndarray of shape (n,), optional
        How far off the trace is known to be, across the path (see
        :func:`recon.methods.anchored.anchored_segment`). Eq. (4) takes the point's position
        from the path (only the scan's shape enters), so this stays in every point's variance.
    placement_variance_m2 : ndarray of shape (n,), optional
        Not used: Eq. (4) accepts the scan's evidence wherever it is.
    corners : tuple of int, optional
        The corners an EDGE segment follows (chosen by :func:`recon.classify.classify_segments`):
        N_S is the thinned edge near each point of those corners only.

    Returns
    -------
    SegmentResult
    """
    n = len(points)
    prior = prior_variance(prior_variance_m2, n)
    windows = window_indices(n, half_width)
    degree = min(params.degree, windows.shape[1] - 2)
    scale = params.radius_m
    use_scan = kind != SegmentKind.PATH and params.alpha != 1.0
    if use_scan and model is None:
        raise ValueError(f"a {kind.name.lower()} segment follows the scan: give its model")
    if use_scan and kind == SegmentKind.SURFACE:
        # N_S on a surface: the k nearest scan points of every point of N_P.
        assert model is not None  # refused above otherwise
        _, knn = model.dense_tree.query(points, k=params.surface_k, workers=-1)
    followed = PointMode.EDGE if kind == SegmentKind.EDGE else PointMode.SURFACE
    out = SegmentResult.unchanged(points)
    for rows in chunks(n):
        # Eq. (3)'s path polynomial lives in the principal plane: only the second component.
        fitted = path_fit(points, windows[rows], rows, degree=degree, scale=scale, outputs=1)
        frame, x_i, design_at, fit_p = fitted.frame, fitted.x_i, fitted.design_at, fitted.fit
        f_p = fit_p.predict(design_at)[:, 0]
        var_p = fit_p.rms**2 * fit_p.leverage(design_at)
        var_s = np.zeros(len(x_i))
        alpha = np.ones(len(x_i))
        f_s = np.zeros(len(x_i))
        n_surface = np.zeros(len(x_i), np.int64)
        residual_s = np.full(len(x_i), np.nan)
        if use_scan:
            assert model is not None  # refused above otherwise
            if kind == SegmentKind.EDGE:
                ns, ws, _ = edge_neighbourhoods(
                    points[rows], frame.axes[:, :, 0], model, params.radius_m, corners=corners
                )
            else:
                ns = model.features.dense_points_m[knn[windows[rows]].reshape(len(x_i), -1)]
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
            var_s = np.where(ok, fit_s.rms**2 * fit_s.leverage(design_at), 0.0)
            if params.alpha == "auto":
                alpha = var_s / np.maximum(var_p + var_s, 1e-300)
            else:
                alpha = np.full(len(x_i), float(params.alpha))
            alpha = np.where(ok, alpha, 1.0)
            f_s = np.where(ok, f_s, 0.0)
            n_surface = np.where(ok, np.count_nonzero(ws, axis=1), 0)
            residual_s = np.where(ok, fit_s.rms, np.nan)
            out.mode[rows] = np.where(ok, followed, PointMode.PATH)
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
        fit_var = 2.0 * (alpha**2 * var_p + (1.0 - alpha) ** 2 * var_s)
        out.variance_m2[rows] = prior[rows] + beta**2 * fit_var
    return out
