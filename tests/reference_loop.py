"""A straightforward per-point-loop implementation of the reconstruction's per-point stage.

One point at a time, with plain numpy: ``numpy.linalg.eigh`` for every PCA,
``numpy.linalg.lstsq`` for every fit (the leverage from the pseudo-inverse of the normal matrix)
and a KD-tree query per point. Two uses:

* the tests check that the vectorised implementation gives the same points (an independent
  method, written from the module docstrings and the maths rather than from the batched code);
* the speed benchmark runs it as a whole command (``tests/bench/loop_command.py``) beside
  ``teachpath reconstruct``.

Shared with ``recon.reconstruct.reconstruct`` (the pipeline's structure, not the per-point stage):
resampling and corner candidates (``plan_segments``), the scan model and its registration
(``prepare_scan_model``, or ``build_scan_model`` and ``touch_registration`` with touches), the
fused demonstrations and their prior, the corners (``judge_corners``, ``with_corner_edges``),
what each segment follows and which corners an edge segment follows (``classify_segments``), the
registration's share of the placement variance (``transform_sigma_m``), and the joins at the
corners (``join_at_corners``). From the scan model only its precomputed arrays and trees are read:
the thinned edge (points, directions, variances, corners), the dense cloud, the voxels' normals
and curvature, the small-scale normals (``ScanModel.fine_normals``, computed once for the whole
scan and tested with the scan model) and the cross-sections (``ScanModel.profiles``).
Constants (thresholds, radii) are imported from the recon modules.

Where the batched code's answer for a point depends on the other points it is batched with, this
one follows the docstrings instead (see :func:`_scan_along` and :func:`_lifted_off`); the scenes
of the test do not tell the two apart.

Re-implemented here, per point, without ``recon.fitting``, ``path_fit``, ``adaptive_smoothing``,
``edge_neighbourhoods``, ``weigh_evidence``, ``fit_faces`` or ``ScanModel.faces_under``:

* the paper's Eq. (4): N_P's frame and path polynomial, N_S (the corners' edge samples along the
  path, or the k nearest scan points of N_P) with its axes matched to the path's, the robust scan
  polynomial, the inverse-variance alpha and the variance;
* the anchored method: the path smoothed by a 3-D polynomial (edges) or by the widest window of
  arc-length polynomials that agrees with every narrower one (elsewhere); the edge targets (N_S
  over three reaches, the corner filter, the robust 3-D polynomial, the continued line past the
  samples' ends near a segment's ends, the window chosen by the intersection of confidence
  intervals); the one face under a point (the cross-section's line under it or the flattest
  voxel, the seed, two stages of growth, the quadric, the point's foot on it along its own
  normal, the check that it faces the way the face under the point does); the checks that the
  move is explained by the hand's error and the scan's placement (support under an edge target,
  the distance, lift-offs off a face: the run flanked by the trace on the face, the scan along
  the way, the free air above it); the ramp at the ends of the evidence, the drift estimate, the
  blend and the variance.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from recon import reconstruct as R
from recon.classify import PATH_ONLY, SegmentKind, classify_segments
from recon.faces import (
    FOOT_ITERATIONS,
    HEIGHT_FLOOR_M,
    MAX_SUPPORT_GAP_M,
    MIN_FACE_POINTS,
    MIN_FACE_RADIUS_M,
    NORMAL_TOLERANCE_DEG,
    SEED_HEIGHT_M,
    SEED_POINTS,
    STAGE_ONE_RADIUS_M,
)
from recon.fusion import fuse_traces
from recon.inputs import Recording
from recon.methods import anchored as A
from recon.methods.common import (
    ADAPTIVE_FACTORS,
    ADAPTIVE_GAMMA,
    EDGE_DIRECTION_TOLERANCE_DEG,
    HAND_ERROR_PRIOR_M,
)
from recon.recon_params import ReconParams
from recon.results import PointMode, PointReason
from recon.scan_model import (
    FACE_FOOT_MARGIN_M,
    FACE_HEIGHT_REACH_M,
    FACE_SLICE_REACH_M,
    build_scan_model,
)
from recon.transforms import apply_transform, invert_transform

# --- Small numerics, one neighbourhood at a time ---------------------------------------------


def _pca(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, principal axes (columns, largest variance first) and variances (descending) of
    one neighbourhood; mean 0 and axes reversed identity for an empty one (as ``eigh`` of a zero
    covariance gives)."""
    if len(points) == 0:
        return np.zeros(3), np.eye(3)[:, ::-1].copy(), np.zeros(3)
    mean = points.mean(axis=0)
    centred = points - mean
    values, vectors = np.linalg.eigh(centred.T @ centred / len(points))
    return mean, vectors[:, ::-1].copy(), np.maximum(values[::-1], 0.0)


def _poly(x, degree: int, scale: float) -> np.ndarray:
    """``(x / scale)^0 .. (x / scale)^degree`` (one row per abscissa)."""
    return np.vander(np.atleast_1d(np.asarray(x, dtype=np.float64)) / scale, degree + 1, True)


def _poly_slope(x: float, degree: int, scale: float) -> np.ndarray:
    """d/dx of :func:`_poly`'s row at ``x``."""
    u = x / scale
    return np.array([k * u ** (k - 1) if k else 0.0 for k in range(degree + 1)]) / scale


def _quadric(u, v, scale: float) -> np.ndarray:
    """``1, u, v, u^2, u v, v^2`` (scaled), one row per point."""
    a = np.atleast_1d(np.asarray(u, dtype=np.float64)) / scale
    b = np.atleast_1d(np.asarray(v, dtype=np.float64)) / scale
    return np.column_stack([np.ones_like(a), a, b, a * a, a * b, b * b])


def _quadric_gradient(u: float, v: float, scale: float) -> np.ndarray:
    """d/du and d/dv of :func:`_quadric`'s row at (u, v), shape (2, 6)."""
    a, b = u / scale, v / scale
    return np.array([[0, 1, 0, 2 * a, b, 0], [0, 0, 1, 0, a, 2 * b]], dtype=np.float64) / scale


@dataclass
class _Fit:
    """Least squares over the kept rows: coefficients (p, m), residual standard deviation over
    all outputs (dof-corrected), residual degrees of freedom per output, and the normal matrix's
    (pseudo-)inverse for leverages."""

    coef: np.ndarray
    rms: float
    dof: int
    normal_inverse: np.ndarray

    def at(self, row: np.ndarray) -> np.ndarray:
        return row @ self.coef

    def leverage(self, row: np.ndarray) -> float:
        return float(row @ self.normal_inverse @ row)


def _least_squares(design: np.ndarray, y: np.ndarray, keep: np.ndarray) -> _Fit:
    """Ordinary least squares of ``y`` (K, m) on the rows of ``design`` (K, p) where ``keep``.

    A neighbourhood with no more rows than coefficients gets the minimum-norm solution (callers
    reject it by its dof); an empty one fits zero.
    """
    a, b = design[keep], y[keep]
    p, m = design.shape[1], y.shape[1]
    if len(a) == 0:
        return _Fit(np.zeros((p, m)), 0.0, -p, np.zeros((p, p)))
    coef = np.linalg.lstsq(a, b, rcond=None)[0]
    dof = len(a) - p
    rms = float(np.sqrt(np.sum((b - a @ coef) ** 2) / max(dof * m, 1)))
    return _Fit(coef, rms, dof, np.linalg.pinv(a.T @ a))


def _robust(
    design: np.ndarray, y: np.ndarray, base: np.ndarray, *, floor: float
) -> tuple[_Fit, np.ndarray]:
    """Least squares, then twice again without the rows more than 3 RMS (at least 3 ``floor``)
    off the last fit: a scan's few gross errors must not pull the fit. Each round judges every
    row of ``base`` afresh. Returns the fit and the rows it kept."""
    fit = _least_squares(design, y, base)
    keep = base
    for _ in range(2):
        residual = np.linalg.norm(y - design @ fit.coef, axis=1)
        keep = base & (residual <= 3.0 * max(fit.rms, floor))
        fit = _least_squares(design, y, keep)
    return fit, keep


def _window(i: int, n: int, half: int) -> np.ndarray:
    """N_P of point i: ``2 half + 1`` consecutive points (all n if fewer), slid inwards at the
    ends rather than shrunk."""
    w = min(2 * half + 1, n)
    start = min(max(i - half, 0), n - w)
    return np.arange(start, start + w)


def _nearest(tree, point: np.ndarray, k: int, radius_m: float = np.inf) -> np.ndarray:
    """Indices of the (at most) ``k`` nearest tree points within ``radius_m``, nearest first."""
    if k <= 0:
        return np.zeros(0, np.int64)
    dist, idx = tree.query(point, k=k, distance_upper_bound=radius_m)
    dist, idx = np.atleast_1d(dist), np.atleast_1d(idx)
    return idx[np.isfinite(dist)].astype(np.int64)


def _clear_within(tree, point: np.ndarray, reach_m: float) -> bool:
    """Whether no tree point lies within ``reach_m`` of ``point``."""
    return not np.isfinite(tree.query(point, distance_upper_bound=reach_m)[0])


# --- The path --------------------------------------------------------------------------------


def _path_fit(points: np.ndarray, i: int, half: int, degree: int, scale: float, outputs: int):
    """N_P's principal frame (C^x along the travel, right-handed) and the polynomial of its
    ``outputs`` transverse components in its first. Returns (mean, axes, x_i, row at x_i, fit)."""
    window = points[_window(i, len(points), half)]
    mean, axes, _ = _pca(window)
    if axes[:, 0] @ (window[-1] - window[0]) < 0:
        axes[:, 0] *= -1
    axes[:, 2] = np.cross(axes[:, 0], axes[:, 1])
    local = (window - mean) @ axes
    x_i = float((points[i] - mean) @ axes[:, 0])
    fit = _least_squares(
        _poly(local[:, 0], degree, scale), local[:, 1 : 1 + outputs], np.ones(len(window), bool)
    )
    return mean, axes, x_i, _poly(x_i, degree, scale)[0], fit


def _smoothed(points, arc_m, i, half, degree, scale):
    """Point i as a polynomial of arc length over its window, each coordinate (a 3-D
    Savitzky-Golay filter). Returns (point, variance, half-width, rms)."""
    window = _window(i, len(points), half)
    deg = min(degree, len(window) - 2)
    fit = _least_squares(
        _poly(arc_m[window] - arc_m[i], deg, scale), points[window], np.ones(len(window), bool)
    )
    at = _poly(0.0, deg, scale)[0]
    return fit.at(at), fit.rms**2 * fit.leverage(at), len(window) // 2, fit.rms


def _adaptive(points, arc_m, i, half, degree, scale):
    """Point i smoothed by the widest of the windows ``ADAPTIVE_FACTORS x half`` whose estimate
    lies within ``ADAPTIVE_GAMMA`` of the summed standard deviations of every narrower one's (the
    intersection of confidence intervals), each standard deviation from the narrowest fit's
    noise. Returns (point, variance, half-width, rms) of the chosen window."""
    n = len(points)
    fits = [_smoothed(points, arc_m, i, half, degree, scale)]
    for factor in ADAPTIVE_FACTORS[1:]:
        if 2 * half * factor + 1 > n:
            break
        fits.append(_smoothed(points, arc_m, i, int(round(half * factor)), degree, scale * factor))
    noise = max(fits[0][3], 1e-300)
    sigma = [noise * np.sqrt(f[1]) / max(f[3], 1e-300) for f in fits]
    chosen = 0
    for j in range(1, len(fits)):
        gaps = [np.linalg.norm(fits[j][0] - fits[k][0]) for k in range(j)]
        if not all(g <= ADAPTIVE_GAMMA * (sigma[k] + sigma[j]) for k, g in enumerate(gaps)):
            break
        chosen = j
    return fits[chosen]


# --- The scan's edge -------------------------------------------------------------------------


def _edge_samples(centre, direction, model, radius_m, corners, max_points) -> np.ndarray:
    """N_S on an edge: of the ``max_points`` thinned-edge samples nearest to ``centre`` within
    ``radius_m``, those running along ``direction`` (within the tolerance) and, where corners are
    given, of one of them or of no known corner."""
    edges = model.edges
    idx = _nearest(model.edge_tree, centre, min(max_points, len(edges)), radius_m)
    along = np.abs(edges.directions[idx] @ direction)
    keep = along >= np.cos(np.radians(EDGE_DIRECTION_TOLERANCE_DEG))
    if corners is not None:
        corner = edges.corner[idx]
        keep &= np.isin(corner, corners) | (corner == -1)
    return idx[keep]


def _edge_target_within(centre, direction, model, params, degree, corners, factor, near_end):
    """The edge's target for one point with N_S reaching ``factor`` times the narrowest reach:
    a robust 3-D polynomial of the samples' principal frame, read at the point's abscissa, and
    continued along its tangent past the samples' ends. Returns (target, variance (inf where
    not accepted), count, rms, how far past the samples' ends)."""
    idx = _edge_samples(
        centre,
        direction,
        model,
        A.EDGE_SCAN_RADII * params.radius_m * factor,
        corners,
        A.EDGE_NEIGHBOURS * factor,
    )
    samples = model.edges.points_m[idx]
    mean, axes, _ = _pca(samples)
    if axes[:, 0] @ direction < 0:
        axes[:, 0] *= -1
    local = (samples - mean) @ axes
    scale = params.radius_m * factor
    design = _poly(local[:, 0], degree, scale)
    fit, kept = _robust(design, local[:, 1:], np.ones(len(idx), bool), floor=1e-5)
    count = int(np.count_nonzero(kept))
    if count == 0:
        return centre.copy(), np.inf, 0, fit.rms, np.inf
    x_at = float(axes[:, 0] @ (centre - mean))
    x_end = float(np.clip(x_at, local[kept, 0].min(), local[kept, 0].max()))
    past = abs(x_at - x_end)
    row = _poly(x_end, degree, scale)[0]
    across = fit.at(row) + _poly_slope(x_end, degree, scale) @ fit.coef * (x_at - x_end)
    target = mean + axes @ np.r_[x_at, across]
    if not np.all(np.isfinite(target)):
        target = centre.copy()
    # The scatter about the curve (its samples correlated, EDGE_SAMPLES_PER_INDEPENDENT to one),
    # never below what the corners' own fits say (the kept samples' mean), per reach.
    scatter = fit.rms**2 * min(fit.leverage(row) * A.edge_dependence(model), 1.0)
    variance = max(scatter, float(np.mean(model.edges.variance_m2[idx[kept]])) / factor)
    # The continued line is as uncertain as its slope: rms / sqrt(count) over the reach.
    slope_sigma = max(fit.rms, 1e-5) / np.sqrt(count) / scale
    variance += (past * slope_sigma) ** 2
    within = past <= A.SPAN_SLACK_M or (near_end and past <= A.CONTINUE_PAST_END_M)
    ok = fit.dof >= 2 and within and count >= A.MIN_EDGE_SAMPLES
    return target, variance if ok else np.inf, count, fit.rms, past


def _edge_target(centre, direction, model, params, degree, corners, end_distance_m):
    """The edge's target over the widest reach that does not bend it: from the narrowest reach
    that fits, widened while the next one fits and agrees with every narrower one that fits
    (within ``EDGE_ICI_GAMMA`` of their summed standard deviations)."""
    if model.edge_tree is None:
        return centre.copy(), np.inf, 0, np.nan, 0.0
    near_end = end_distance_m <= A.CONTINUE_PAST_END_M + A.SPAN_SLACK_M
    fits = [
        _edge_target_within(centre, direction, model, params, degree, corners, f, near_end)
        for f in A.EDGE_WINDOW_FACTORS
    ]
    valid = [np.isfinite(f[1]) for f in fits]
    if not any(valid):
        return fits[0]
    start = valid.index(True)
    chosen = start
    for j in range(start + 1, len(fits)):
        if not valid[j]:
            break
        agree = all(
            np.linalg.norm(fits[j][0] - fits[i][0])
            <= A.EDGE_ICI_GAMMA * (np.sqrt(fits[i][1]) + np.sqrt(fits[j][1]))
            for i in range(start, j)
            if valid[i]
        )
        if not agree:
            break
        chosen = j
    return fits[chosen]


# --- The one face under a point --------------------------------------------------------------


def _face_under(centre: np.ndarray, model) -> tuple[np.ndarray, np.ndarray, bool]:
    """The face the nearest cross-section shows under the point: of that slice's lines within
    reach of the point whose points reach past its foot, the nearest. Returns (unit normal, the
    point's foot on that line, found)."""
    profiles = model.profiles
    if profiles is None or len(profiles) == 0:
        return np.zeros(3), centre.copy(), False
    distance = np.linalg.norm(profiles.origin_m - centre, axis=1)
    station = int(np.argmin(distance))
    axes = profiles.axes[station]  # (2, 3)
    local = axes @ (centre - profiles.origin_m[station])
    best, best_height, best_foot = None, np.inf, None
    for line in range(profiles.normal.shape[1]):
        normal2 = profiles.normal[station, line]
        signed = normal2 @ local - profiles.offset_m[station, line]
        along = np.array([-normal2[1], normal2[0]]) @ local
        lo, hi = profiles.extent_m[station, line]
        covers = lo - FACE_FOOT_MARGIN_M <= along <= hi + FACE_FOOT_MARGIN_M
        if not (profiles.line_ok[station, line] and covers and abs(signed) <= FACE_HEIGHT_REACH_M):
            continue
        if abs(signed) < best_height:
            normal = normal2[0] * axes[0] + normal2[1] * axes[1]
            best, best_height, best_foot = normal, abs(signed), centre - signed * normal
    if best is None or distance[station] > FACE_SLICE_REACH_M:
        return np.zeros(3), centre.copy(), False
    return best, best_foot, True


def _flattest_normal(centre: np.ndarray, model) -> np.ndarray:
    """The normal of the least curved of the (up to) eight voxels nearest to the point."""
    features = model.features
    nearest = np.atleast_1d(model.coarse_tree.query(centre, k=min(8, len(features.points_m)))[1])
    return features.normals[nearest[np.argmin(features.curvature[nearest])]]


def _face(centre: np.ndarray, model, params: ReconParams):
    """The one face under a path point and the point moved onto it (see recon.faces).

    Returns
    -------
    SimpleNamespace
        ``target`` (3,): the point's foot on the quadric; ``variance`` of its height (inf where
        not ok); ``ok``: enough points, one near the target, facing the way the face under the
        point does.
    """
    scale = params.radius_m
    dense = model.features.dense_points_m
    idx = _nearest(
        model.dense_tree,
        centre,
        min(A.SURFACE_NEIGHBOURS, len(dense)),
        A.SURFACE_SCAN_RADII * params.radius_m,
    )
    points, normals = dense[idx], model.fine_normals[idx]
    reference, foot, found = _face_under(centre, model)
    if not found:
        reference = _flattest_normal(centre, model)
    cos_tolerance = np.cos(np.radians(NORMAL_TOLERANCE_DEG))
    agree = np.abs(normals @ reference) >= cos_tolerance
    level = np.ones(len(idx), bool)
    if found:
        level = np.abs((points - foot) @ reference) <= SEED_HEIGHT_M
    # The seed: the nearest points that face that way (and lie on that face). Without any, the
    # frame is the empty one of _pca (never seen on the real parts), as the batched PCA's is.
    seed = np.zeros(len(idx), bool)
    seed[np.flatnonzero(agree & level)[:SEED_POINTS]] = True
    mean, axes, variances = _pca(points[seed])
    local = (points - mean) @ axes
    u, v, h = local[:, 0], local[:, 1], local[:, 2:]
    rho2 = u * u + v * v
    seed_sigma = np.sqrt(max(variances[2], HEIGHT_FLOOR_M**2))
    stage_one = (
        agree
        & (rho2 <= STAGE_ONE_RADIUS_M**2)
        & (np.abs(h[:, 0]) <= 3.0 * seed_sigma + rho2 / (2.0 * MIN_FACE_RADIUS_M))
    )
    # Stage one: the seed's plane grown within STAGE_ONE_RADIUS_M (allowing a face that curves);
    # stage two: the first stage's quadric grown over the whole neighbourhood.
    design = _quadric(u, v, scale)
    fit, _ = _robust(design, h, stage_one, floor=HEIGHT_FLOOR_M)
    residual = np.abs(h - design @ fit.coef)[:, 0]
    stage_two = agree & (residual <= 3.0 * max(fit.rms, HEIGHT_FLOOR_M))
    fit, used = _robust(design, h, stage_two, floor=HEIGHT_FLOOR_M)
    # The point's foot on the quadric: from straight down the seed frame's axis, FOOT_ITERATIONS
    # steps onto the tangent plane where the last one landed (the quadric's normal through the
    # point, not the seed patch's, which tilts in the scan's noise).
    at = (centre - mean) @ axes
    foot = at[:2].copy()
    for _ in range(FOOT_ITERATIONS):
        on_face = np.r_[foot, fit.at(_quadric(foot[0], foot[1], scale)[0])[0]]
        normal = np.r_[-(_quadric_gradient(foot[0], foot[1], scale) @ fit.coef[:, 0]), 1.0]
        normal /= np.linalg.norm(normal)
        foot = (at - ((at - on_face) @ normal) * normal)[:2]
    row = _quadric(foot[0], foot[1], scale)[0]
    target = mean + axes @ np.r_[foot, fit.at(row)]
    count = int(np.count_nonzero(used))
    gap = np.sqrt(np.min((u[used] - foot[0]) ** 2 + (v[used] - foot[1]) ** 2, initial=np.inf))
    # It is the face under the point only if it faces that face's way at the target (seeded by
    # a few points, the fit may have grown over a neighbouring face instead).
    normal = axes @ np.r_[-(_quadric_gradient(foot[0], foot[1], scale) @ fit.coef[:, 0]), 1.0]
    facing = abs(normal @ reference) / np.linalg.norm(normal) >= cos_tolerance
    ok = fit.dof >= 4 and count >= MIN_FACE_POINTS and gap <= MAX_SUPPORT_GAP_M and facing
    variance = fit.rms**2 * min(fit.leverage(row), 1.0)
    return SimpleNamespace(target=target, variance=variance if ok else np.inf, ok=ok)


# --- Whether a move is what the trace's error explains ---------------------------------------


def _scan_along(start: np.ndarray, end: np.ndarray, model) -> bool:
    """Whether the scan runs along the straight way from ``start`` to ``end`` (one face, no step
    between): a point within ``LIFT_OFF_SAME_FACE_M`` of every millimetre of it, but for gaps of
    at most ``LIFT_OFF_SCAN_GAP_M`` (a random scan's own).

    Each way is probed along its own length, at most a millimetre apart, as the docstring of
    ``recon.methods.anchored._scan_along`` says. (The batched code probes every way of a run as
    densely as its longest needs and still allows two missing probes, so on a shorter way the gap
    it allows shrinks with the run's longest way: a point's answer depends on its neighbours.)
    """
    length = float(np.linalg.norm(end - start))
    probes_apart_m = 0.001
    allowed = int(A.LIFT_OFF_SCAN_GAP_M / probes_apart_m)
    missing = 0
    for s in np.linspace(0.0, 1.0, int(np.ceil(length / probes_apart_m)) + 2):
        uncovered = _clear_within(
            model.dense_tree, start + s * (end - start), A.LIFT_OFF_SAME_FACE_M
        )
        missing = missing + 1 if uncovered else 0
        if missing > allowed:  # more than LIFT_OFF_SCAN_GAP_M without the scan
            return False
    return True


def _in_free_air(start: np.ndarray, target: np.ndarray, model) -> bool:
    """Whether the straight way from ``start`` to ``target``, but for its last
    ``LIFT_OFF_LANDING_M``, passes no scan point within ``LINE_OF_SIGHT_M`` (probed every half
    of that, up to ``MAX_LIFT_OFF_M``)."""
    way = target - start
    length = float(np.linalg.norm(way))
    reach = max(length - A.LIFT_OFF_LANDING_M, 0.0)
    unit = way / max(length, 1e-12)
    for step in np.arange(0.0, A.MAX_LIFT_OFF_M, 0.5 * A.LINE_OF_SIGHT_M):
        if not _clear_within(model.dense_tree, start + min(step, reach) * unit, A.LINE_OF_SIGHT_M):
            return False
    return True


def _lifted_off(centres, targets, near, lifted, model) -> np.ndarray:
    """Which of the ``lifted`` points (beyond the hand's error, within ``MAX_LIFT_OFF_M`` of
    their face) are a lift-off: a run of them no longer than ``MAX_LIFT_OFF_LENGTH_M``, flanked
    on each side the segment has by a point ``near`` its face, the scan running from each flank's
    target to the lifted one's, and free air between the lifted point and its target.

    The runs are the whole segment's (the batched code takes them within each of its chunks,
    ``recon.methods.common.balanced_chunks``, which only a segment longer than
    ``recon.methods.common.CHUNK`` points tells apart).
    """
    n = len(centres)
    out = np.zeros(n, bool)
    if n < 2:
        return out  # a lone point has no flank on the face
    spacing = float(np.median(np.linalg.norm(np.diff(centres, axis=0), axis=1)))
    longest = max(1, int(round(A.MAX_LIFT_OFF_LENGTH_M / max(spacing, 1e-9))))
    i = 0
    while i < n:
        if not lifted[i]:
            i += 1
            continue
        start = i
        while i < n and lifted[i]:
            i += 1
        flanks = [k for k in (start - 1, i) if 0 <= k < n]
        if i - start > longest or not flanks or not all(near[k] for k in flanks):
            continue
        for j in range(start, i):
            out[j] = all(_scan_along(targets[k], targets[j], model) for k in flanks) and (
                _in_free_air(centres[j], targets[j], model)
            )
    return out


def _evidence(smoothed, directions, kind, model, params, degree, max_move_m, end_m, corners):
    """What the scan says at each smoothed point of a segment, accepted only where it holds:
    the edge (on an edge segment; supported by a scan point near it, or continued past its
    samples, and within the hand's error), else the one face under the point (within the hand's
    error, or a lift-off), else nothing.

    Returns
    -------
    SimpleNamespace
        ``target`` (n, 3), ``variance`` (n,) (inf where nothing was accepted), ``mode`` (n,)
        and ``reason`` (n,).
    """
    n = len(smoothed)
    target = smoothed.copy()
    variance = np.full(n, np.inf)
    mode = np.full(n, PointMode.PATH, np.int8)
    reason = np.full(n, PointReason.NONE, np.int8)
    failure = np.full(n, PointReason.NO_FEATURE, np.int8)
    todo = np.ones(n, bool)
    if kind == SegmentKind.EDGE:
        for i in range(n):
            t, var, _, _, past = _edge_target(
                smoothed[i], directions[i], model, params, degree, corners, end_m[i]
            )
            found = np.isfinite(var)
            support = model.dense_tree.query(t)[0] <= A.EDGE_SUPPORT_M or past > 0
            if found and support and np.linalg.norm(t - smoothed[i]) <= max_move_m[i]:
                target[i], variance[i], mode[i], todo[i] = t, var, PointMode.EDGE, False
                far_past = past > A.CONTINUED_NOTE_M
                reason[i] = PointReason.CONTINUED if far_past else PointReason.NONE
            elif not found:
                ended = past > A.CONTINUE_PAST_END_M
                failure[i] = PointReason.PAST_END if ended else PointReason.NO_FEATURE
            else:
                failure[i] = PointReason.FAR_FROM_TRACE if support else PointReason.OFF_EVIDENCE
    faces = [_face(smoothed[i], model, params) if todo[i] else None for i in range(n)]
    candidate = np.array([f is not None and f.ok for f in faces])
    face_target = np.array([smoothed[i] if f is None else f.target for i, f in enumerate(faces)])
    move = np.linalg.norm(face_target - smoothed, axis=1)
    near = candidate & (move <= max_move_m)
    lifted = candidate & ~near & (move <= A.MAX_LIFT_OFF_M)
    accept = near | _lifted_off(smoothed, face_target, near, lifted, model)
    for i in np.flatnonzero(accept):
        target[i], variance[i], todo[i] = faces[i].target, faces[i].variance, False
        mode[i] = PointMode.SURFACE
        reason[i] = PointReason.ONE_FACE if kind == SegmentKind.EDGE else PointReason.NONE
    if kind == SegmentKind.SURFACE:
        failure = np.where(candidate, PointReason.FAR_FROM_TRACE, PointReason.NO_FEATURE)
    reason[todo] = failure[todo]
    return SimpleNamespace(target=target, variance=variance, mode=mode, reason=reason)


# --- The methods, one segment at a time ------------------------------------------------------


def _prior(prior_variance_m2, n: int) -> np.ndarray:
    """What only the path decides is off by across it (the hand's error unless given)."""
    if prior_variance_m2 is None:
        return np.full(n, HAND_ERROR_PRIOR_M**2)
    return np.asarray(prior_variance_m2, dtype=np.float64)


def _result(points, alpha, variance, mode, reason=None) -> SimpleNamespace:
    n = len(points)
    reason = np.full(n, PointReason.NONE, np.int8) if reason is None else reason
    return SimpleNamespace(
        points=points, alpha=alpha, variance_m2=variance, mode=np.asarray(mode), reason=reason
    )


def _align_scan_axes(scan_axes: np.ndarray, path_axes: np.ndarray) -> np.ndarray:
    """C_S^x signed like C_P^x; C_S^y whichever of the scan's second and third axes is closer to
    C_P^y, signed like it; C_S^z completing a right-handed frame."""
    x = scan_axes[:, 0] * np.sign(scan_axes[:, 0] @ path_axes[:, 0] + 1e-300)
    dots = [scan_axes[:, 1] @ path_axes[:, 1], scan_axes[:, 2] @ path_axes[:, 1]]
    pick = 2 if abs(dots[1]) > abs(dots[0]) else 1
    y = scan_axes[:, pick] * np.sign(dots[pick - 1] + 1e-300)
    return np.column_stack([x, y, np.cross(x, y)])


def paper_segment_loop(
    points,
    kind,
    model,
    params: ReconParams,
    half_width: int,
    *,
    prior_variance_m2=None,
    placement_variance_m2=None,
    corners=None,
) -> SimpleNamespace:
    """Eq. (4) of the paper, one point at a time (``placement_variance_m2`` is not used).

    Returns
    -------
    SimpleNamespace
        ``points`` (n, 3), ``alpha``, ``variance_m2``, ``mode`` and ``reason`` (n,).
    """
    n = len(points)
    prior = _prior(prior_variance_m2, n)
    degree = min(params.degree, min(2 * half_width + 1, n) - 2)
    scale = params.radius_m
    use_scan = kind != SegmentKind.PATH and params.alpha != 1.0
    followed = PointMode.EDGE if kind == SegmentKind.EDGE else PointMode.SURFACE
    if use_scan and kind == SegmentKind.SURFACE:
        # N_S on a surface: the k nearest scan points of every point of N_P (repeats kept).
        knn = [np.atleast_1d(model.dense_tree.query(p, k=params.surface_k)[1]) for p in points]
    out = np.empty_like(points)
    alphas, variances, modes = np.ones(n), np.empty(n), np.full(n, PointMode.PATH, np.int8)
    for i in range(n):
        mean, axes, x_i, row, fit_p = _path_fit(points, i, half_width, degree, scale, 1)
        f_p = float(fit_p.at(row)[0])
        var_p = fit_p.rms**2 * fit_p.leverage(row)
        alpha, f_s, var_s = 1.0, 0.0, 0.0
        if use_scan:
            if kind == SegmentKind.EDGE:
                # The segment's corners filter N_S, as recon.methods.paper.paper_segment does
                # (although its docstring says ``corners`` is not used).
                idx = _edge_samples(
                    points[i], axes[:, 0], model, params.radius_m, corners, max_points=64
                )
                ns = model.edges.points_m[idx]
            else:
                window = _window(i, n, half_width)
                ns = model.features.dense_points_m[np.concatenate([knn[j] for j in window])]
            mean_s, axes_s, _ = _pca(ns)
            axes_s = _align_scan_axes(axes_s, axes)
            local_s = (ns - mean_s) @ axes_s
            fit_s, _ = _robust(
                _poly(local_s[:, 0], degree, scale),
                local_s[:, 1:2],
                np.ones(len(ns), bool),
                floor=1e-5,
            )
            if fit_s.dof >= 1:
                f_s = float(fit_s.at(row)[0])
                var_s = fit_s.rms**2 * fit_s.leverage(row)
                if params.alpha == "auto":
                    alpha = var_s / max(var_p + var_s, 1e-300)
                else:
                    alpha = float(params.alpha)
                modes[i] = followed
        offset = params.beta * (alpha * f_p + (1.0 - alpha) * f_s)
        out[i] = mean + axes[:, 0] * x_i + axes[:, 1] * offset
        alphas[i] = alpha
        # Both offsets are across the path in its plane; the scan's position never enters.
        fit_var = 2.0 * (alpha**2 * var_p + (1.0 - alpha) ** 2 * var_s)
        variances[i] = prior[i] + params.beta**2 * fit_var
    return _result(out, alphas, variances, modes)


def _ramp(supported: np.ndarray, half_width: int) -> np.ndarray:
    """Per point: 0 where unsupported, else its distance (in points) to the nearest unsupported
    point over ``half_width``, at most 1 (segment ends do not count)."""
    n = len(supported)
    gaps = np.flatnonzero(~supported)
    if half_width <= 0 or len(gaps) == 0:
        return supported.astype(np.float64)
    out = np.zeros(n)
    for i in np.flatnonzero(supported):
        out[i] = min(np.min(np.abs(gaps - i)) / half_width, 1.0)
    return out


def anchored_segment_loop(
    points,
    kind,
    model,
    params: ReconParams,
    half_width: int,
    *,
    prior_variance_m2=None,
    placement_variance_m2=None,
    corners=None,
) -> SimpleNamespace:
    """The anchored method, one point at a time (see recon.methods.anchored).

    Returns
    -------
    SimpleNamespace
        ``points`` (n, 3), ``alpha``, ``variance_m2``, ``mode`` and ``reason`` (n,).
    """
    n = len(points)
    prior = _prior(prior_variance_m2, n)
    placement = np.zeros(n) if placement_variance_m2 is None else placement_variance_m2
    # A move onto the scan's evidence is explained by the hand's error and the scan's placement.
    max_move_m = params.evidence_sigmas * np.sqrt(prior + placement)
    degree = min(params.degree, min(2 * half_width + 1, n) - 2)
    scale = params.radius_m
    use_scan = kind != SegmentKind.PATH and params.alpha != 1.0
    arc_m = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    end_m = np.minimum(arc_m, arc_m[-1] - arc_m)
    smoothed = np.empty_like(points)
    var_fit = np.empty(n)
    directions = np.zeros((n, 3))
    for i in range(n):
        if kind == SegmentKind.EDGE:
            # A 3-D curve: both transverse components of N_P's frame as polynomials of the first.
            mean, axes, x_i, row, fit = _path_fit(points, i, half_width, degree, scale, 2)
            smoothed[i] = mean + axes @ np.r_[x_i, fit.at(row)]
            var_fit[i] = fit.rms**2 * fit.leverage(row)
            directions[i] = axes[:, 0]
        else:
            smoothed[i], var_fit[i], _, _ = _adaptive(
                points, arc_m, i, half_width, params.degree, scale
            )
    path_only_var = prior + 2.0 * var_fit
    if not use_scan:
        out = points + params.beta * (smoothed - points)
        variance = params.beta**2 * path_only_var + (1.0 - params.beta) ** 2 * prior
        return _result(out, np.ones(n), variance, np.full(n, PointMode.PATH, np.int8))

    evidence = _evidence(
        smoothed, directions, kind, model, params, degree, max_move_m, end_m, corners
    )
    supported = evidence.mode != PointMode.PATH
    target = np.where(supported[:, None], evidence.target, smoothed)
    var_target = np.where(supported, evidence.variance, 0.0)
    # The path's variance against the target, drift included: the mean discrepancy over
    # DRIFT_WINDOW_RADII radii either side (the ends repeated), less the target's own variance,
    # and never below the smoothing's own.
    size = int(2 * A.DRIFT_WINDOW_RADII * half_width + 1)
    discrepancy = np.where(supported, np.sum((smoothed - target) ** 2, axis=1), 0.0)
    var_path = np.empty(n)
    for i in range(n):
        near = np.clip(np.arange(i - size // 2, i - size // 2 + size), 0, n - 1)
        mean_discrepancy = discrepancy[near].mean() / max(supported[near].mean(), 1e-12)
        var_path[i] = max(mean_discrepancy - var_target[i], var_fit[i])
    if params.alpha == "auto":
        alpha = var_target / np.maximum(var_target + var_path, 1e-300)
    else:
        alpha = np.full(n, float(params.alpha))
    weight = _ramp(supported, half_width)
    alpha = 1.0 - weight * (1.0 - np.where(supported, alpha, 1.0))
    variance = path_only_var.copy()
    for i in np.flatnonzero(supported):
        # Two components across an edge; on a face the height, and the in-plane one is the
        # path's alone. The scan's accuracy beyond its scatter counts in the variance only.
        components = 2 if evidence.mode[i] == PointMode.EDGE else 1
        scan_var = var_target[i] + A.SCAN_ACCURACY_M**2
        blend = alpha[i] ** 2 * var_path[i] + components * (1.0 - alpha[i]) ** 2 * scan_var
        if components == 1:
            blend += 0.5 * path_only_var[i]
        variance[i] = weight[i] * blend + (1.0 - weight[i]) * path_only_var[i]
    blended = alpha[:, None] * smoothed + (1.0 - alpha[:, None]) * target
    out = points + params.beta * (blended - points)
    variance = params.beta**2 * variance + (1.0 - params.beta) ** 2 * prior
    return _result(out, alpha, variance, evidence.mode, evidence.reason)


# --- The whole reconstruction ----------------------------------------------------------------


def reconstruct_loop_details(
    path,
    scan,
    params: ReconParams,
    T_scan_tracker_init=None,
    touches=None,
) -> SimpleNamespace:
    """:func:`reconstruct_loop` with what it found per point.

    Parameters
    ----------
    path : Recording, ndarray of shape (N, 3), metres, or sequence of Recording
        Several recordings are fused first, as ``recon.reconstruct.reconstruct`` does.
    scan : Scan or None
    params : ReconParams
    T_scan_tracker_init : ndarray of shape (4, 4), optional
    touches : TouchRegistration, optional
        The scanner registered by touches (its transform used as it is).

    Returns
    -------
    SimpleNamespace
        ``points_m`` (N, 3), tracker frame; ``alpha``, ``variance_m2`` (the segment's own, without
        the registration's share), ``mode`` and ``reason`` (N,), as ``Reconstruction`` holds them
        (the corner point of two segments from the later one).
    """
    fused = None
    if isinstance(path, Sequence) and not isinstance(path, np.ndarray):
        recordings = list(path)
        if len(recordings) > 1:
            fused = fuse_traces(recordings, spacing_m=params.spacing_m)
            path = fused.recording
        else:
            path = recordings[0]
    recording = path if isinstance(path, Recording) else Recording(points_m=path)
    plan = R.plan_segments(recording, params)
    points, bounds, half = plan.resampled.points_m, plan.bounds, plan.half_width
    prior = None if fused is None else R._prior_from_fusion(fused, plan.resampled)
    registration, model, T = None, None, None
    if scan is not None and params.uses_scan and touches is not None:
        model = build_scan_model(scan, apply_transform(touches.T_scan_tracker, points), params)
        registration = R.touch_registration(
            points, touches, model, bounds, params, T_scan_tracker_init=T_scan_tracker_init
        )
        T = registration.T_scan_tracker
    elif scan is not None and params.uses_scan:
        prepared = R.prepare_scan_model(
            points, scan, bounds, params, T_scan_tracker_init=T_scan_tracker_init
        )
        model, T, registration = prepared.model, prepared.T_scan_tracker, prepared.registration
    work = points if T is None else apply_transform(T, points)
    # Where the segments are and what they follow is the pipeline's structure: shared.
    corners = R.judge_corners(plan, work, model, params)
    bounds = plan.split([c.index for c in corners if c.split])
    if model is not None:
        model = R.with_corner_edges(model, corners)
        classes = classify_segments(work, bounds, model, params)
    else:
        classes = [PATH_ONLY] * len(bounds)
    placement = R.transform_sigma_m(registration, points) ** 2
    loop = anchored_segment_loop if params.method == "anchored" else paper_segment_loop
    results = []
    for (start, stop), segment_class in zip(bounds, classes, strict=True):
        seg = work[start:stop]
        if len(seg) < 3:
            m = len(seg)
            results.append(
                _result(
                    seg.copy(),
                    np.ones(m),
                    np.full(m, HAND_ERROR_PRIOR_M**2),
                    np.full(m, PointMode.UNCHANGED, np.int8),
                )
            )
            continue
        result = loop(
            seg,
            segment_class.kind,
            model,
            params,
            half,
            prior_variance_m2=None if prior is None else prior[start:stop],
            placement_variance_m2=placement[start:stop],
            corners=segment_class.corners,
        )
        results.append(result)
    R.join_at_corners(
        bounds,
        results,
        corners,
        [c.kind for c in classes],
        work,
        spacing_m=plan.resampled.spacing_m,
        beta=params.beta,
    )
    n = len(points)
    out = SimpleNamespace(
        points_m=np.empty((n, 3)),
        alpha=np.empty(n),
        variance_m2=np.empty(n),
        mode=np.empty(n, np.int8),
        reason=np.empty(n, np.int8),
    )
    for (start, stop), result in zip(bounds, results, strict=True):
        for name in ("alpha", "variance_m2", "mode", "reason"):
            getattr(out, name)[start:stop] = getattr(result, name)
        out.points_m[start:stop] = result.points
    if T is not None:
        out.points_m = apply_transform(invert_transform(T), out.points_m)
    return out


def reconstruct_loop(recording, scan, params: ReconParams, T_scan_tracker_init=None):
    """The whole reconstruction with the per-point stage replaced by the loops above.

    Parameters
    ----------
    recording : Recording, ndarray of shape (N, 3), or sequence of Recording
    scan : Scan or None
    params : ReconParams
    T_scan_tracker_init : ndarray of shape (4, 4), optional

    Returns
    -------
    points : ndarray of shape (N, 3)
        Tracker frame, one per resampled point (the corner point of two segments from the later
        one, as in ``recon.reconstruct``).
    """
    details = reconstruct_loop_details(recording, scan, params, T_scan_tracker_init)
    return details.points_m
