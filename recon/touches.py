"""The scanner registered by touching: the pen's tip held still on the workpiece, matched to the
scan's surface.

A moving trace drifts, and registering the scan to it puts the rigid part of that drift into the
transform the robot gets (see :mod:`recon.icp`). A tip at rest on the workpiece is far more
precise (a pivot calibration reaches 0.05 mm; averaging a second of samples takes the tracker's
noise down to a few micrometres), so a handful of touches on two or three faces fixes the scanner's
pose without the trace's drift.

Three steps:

1. :func:`find_dwells`: where the tip rested (at least :data:`MIN_DWELL_S` below a walking speed
   of the tip), averaged.
2. :func:`register_touches`: each touch is matched point-to-plane to the scan's surface where it
   lands (the tangent plane of a quadric fitted to the scan within :data:`PLANE_RADIUS_M`, at the
   touch's foot, re-fitted as the transform moves), solved for the motions the touches fix; the
   motions they leave free keep the initial guess. Touches that stay far off the surface are left
   out and named.
3. :func:`motions_missing`: which motions a traced feature needs fixed that the touches leave free,
   so a calibration that cannot serve the trace is refused rather than used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from recon.errors import DegenerateInputError, RegistrationError
from recon.fitting import fit_linear, quadric_design, weighted_pca
from recon.icp import RigidMotion, fixed_by_ratio, inverse_on_fixed, solve_constrained
from recon.transforms import apply_transform, check_rigid
from recon.types import FloatArray

#: A touch is a rest of the tip at least this long ...
MIN_DWELL_S = 0.3
#: ... during which the tip moves slower than this (a hand resting on a point shakes at well
#: under a millimetre per second once the tracker's noise is averaged over 0.1 s; a hand moving
#: between points goes at centimetres per second).
STILL_SPEED_M_S = 0.005
#: Speeds are measured over this baseline (long enough to average the tracker's noise).
SPEED_BASELINE_S = 0.1
#: This much is cut from each end of a rest (the tip settling and lifting).
SETTLE_S = 0.05
#: A rest whose samples spread more than this (RMS about their mean) slid on the surface.
MAX_DWELL_SPREAD_M = 0.5e-3
#: The scan's surface under a touch is a plane fitted to the scan points within this radius
#: (wide enough that the plane's tilt is known to about a degree on a millimetre-noise scan; a
#: touch should be this far inside its face).
PLANE_RADIUS_M = 8e-3
#: Fewest scan points under a touch for its plane.
MIN_PLANE_POINTS = 12
#: What a touch is assumed to be off by, besides the scan's plane fit: the pivot calibration's
#: error (0.05-0.1 mm, plus the tip's seat in the workpiece's texture).
TOUCH_PRIOR_M = 0.1e-3
#: A touch farther than this many expected errors (and at least :data:`MIN_OUTLIER_M`) from the
#: scan's surface once registered is left out (the tip was not on the scanned workpiece).
OUTLIER_FACTOR = 5.0
MIN_OUTLIER_M = 0.5e-3
#: Fewest touches for a registration.
MIN_TOUCHES = 3
#: A motion is fixed by the touches when they pin it to better than this (1 sigma, as a twist:
#: metres at the touches' extent); otherwise it keeps the initial guess. Absolute rather than a
#: ratio to the best-fixed motion (as the trace's ICP uses): a rotation is pinned by the touches'
#: lever arms, always shorter than their extent, and a ratio would call a rotation pinned to
#: 0.5 mm free. The planes' normals are noisy (a degree or two), which pins motions no face
#: constrains (sliding on a plate) to about 3 mm: not fixed.
FREE_SIGMA_M = 1e-3
#: Iterations of the plane matching.
MAX_ITERATIONS = 30
#: The matching stops when an iteration moves the touches by less than this.
CONVERGED_M = 1e-8


@dataclass(frozen=True)
class Dwell:
    """One rest of the tip.

    Attributes
    ----------
    start, stop : int
        Samples ``[start, stop)`` that were averaged (the settling cut off).
    t_start_s, t_end_s : float
    point_m : ndarray of shape (3,)
        The mean tip position, tracker frame.
    spread_m : float
        RMS distance of the samples from their mean.
    """

    start: int
    stop: int
    t_start_s: float
    t_end_s: float
    point_m: FloatArray
    spread_m: float

    @property
    def n_samples(self) -> int:
        return self.stop - self.start

    @property
    def standard_error_m(self) -> float:
        """The mean's standard error from the tracker's noise (per axis, samples independent)."""
        return self.spread_m / np.sqrt(3.0 * max(self.n_samples, 1))


def find_dwells(
    points_m: FloatArray,
    t_s: FloatArray,
    *,
    min_duration_s: float = MIN_DWELL_S,
    still_speed_m_s: float = STILL_SPEED_M_S,
) -> tuple[list[Dwell], list[str]]:
    """Where the tip rested for at least ``min_duration_s``.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3), metres
        Tip positions, tracker frame.
    t_s : ndarray of shape (N,), seconds
        Their times, increasing.
    min_duration_s : float
    still_speed_m_s : float

    Returns
    -------
    dwells : list of Dwell
        In time order.
    notes : list of str
        Rests that were not used, and why (the tip slid).
    """
    points = np.asarray(points_m, dtype=np.float64)
    t = np.asarray(t_s, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(t) != len(points):
        raise ValueError("points_m must have shape (N, 3) and t_s shape (N,)")
    if len(t) < 2:
        return [], []
    half = SPEED_BASELINE_S / 2
    ahead = np.clip(np.searchsorted(t, t + half), 0, len(t) - 1)
    behind = np.clip(np.searchsorted(t, t - half), 0, len(t) - 1)
    span = np.maximum(t[ahead] - t[behind], 1e-9)
    speed = np.linalg.norm(points[ahead] - points[behind], axis=1) / span
    still = speed < still_speed_m_s
    edges = np.flatnonzero(np.diff(np.r_[0, still.astype(np.int8), 0]))
    dwells, notes = [], []
    for first, end in zip(edges[::2], edges[1::2], strict=True):
        # The speed's baseline reaches into the moves on either side: the rest itself is that
        # much longer than the run of still samples.
        if t[end - 1] - t[first] + SPEED_BASELINE_S < min_duration_s:
            continue
        a = int(np.searchsorted(t, t[first] + SETTLE_S))
        b = int(np.searchsorted(t, t[end - 1] - SETTLE_S, side="right"))
        if b - a < 3:
            a, b = first, end
        rest = points[a:b]
        mean = rest.mean(axis=0)
        spread = float(np.sqrt(np.mean(np.sum((rest - mean) ** 2, axis=1))))
        if spread > MAX_DWELL_SPREAD_M:
            notes.append(
                f"the rest at {t[a]:.2f}-{t[b - 1]:.2f} s was left out: the tip moved "
                f"{spread * 1e3:.2f} mm RMS while resting (it slid); hold it still"
            )
            continue
        dwells.append(Dwell(a, b, float(t[a]), float(t[b - 1]), mean, spread))
    return dwells, notes


@dataclass(frozen=True)
class FoundTouches:
    """The touches of a recording: its rests, averaged.

    Attributes
    ----------
    points_m : ndarray of shape (T, 3)
        Each rest's mean tip position, tracker frame.
    sigma_m : ndarray of shape (T,)
        Each mean's standard error from the tracker's noise.
    dwells : list of Dwell
    notes : list of str
        Rests left out, and why.
    """

    points_m: FloatArray
    sigma_m: FloatArray
    dwells: list[Dwell]
    notes: list[str]


def touches_in(
    points_m: FloatArray, t_s: FloatArray | None, *, label: str = "the touch recording"
) -> FoundTouches:
    """The touches of a recording, refused with what to do when there are too few to register.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3)
    t_s : ndarray of shape (N,) or None
    label : str
        How messages name the recording.

    Raises
    ------
    DegenerateInputError
        No sample times, or fewer than :data:`MIN_TOUCHES` rests.
    """
    if t_s is None:
        raise DegenerateInputError(
            f"{label} has no sample times, so the tip's rests cannot be found: record the "
            "touches with times (a t column, Motive or C3D)"
        )
    dwells, notes = find_dwells(points_m, t_s)
    if len(dwells) < MIN_TOUCHES:
        raise DegenerateInputError(
            f"{label} has {len(dwells)} rests of the tip of {MIN_DWELL_S:g} s or more; at least "
            f"{MIN_TOUCHES} are needed, on two or three faces of the workpiece: hold the tip "
            "still on each point for half a second"
        )
    return FoundTouches(
        points_m=np.array([d.point_m for d in dwells]),
        sigma_m=np.array([d.standard_error_m for d in dwells]),
        dwells=dwells,
        notes=notes,
    )


@dataclass(frozen=True)
class TouchRegistration:
    """The scanner's pose from touches.

    Attributes
    ----------
    T_scan_tracker : ndarray of shape (4, 4)
    touches_m : ndarray of shape (T, 3)
        The touches, tracker frame.
    residual_m : ndarray of shape (T,)
        Each touch's signed distance from the scan's surface once registered (NaN for a touch
        with no surface under it).
    used : ndarray of shape (T,), bool
        The touches the transform was fitted to.
    plane_points : ndarray of shape (T,), int
        Scan points in each touch's plane.
    fixed_motions : int
        How many of the six rigid motions the touches fix.
    free_motions : tuple of str
        The others, in words ("sliding along (1.00, 0.00, 0.00)").
    free_directions : ndarray of shape (F, 6)
        Those motions as unit twists of ``motion``.
    motion : RigidMotion
        The twists' centre and scale.
    covariance : ndarray of shape (6, 6)
        Of the fixed motions' twist (zero along the free ones), from the touches' expected
        errors.
    notes : tuple of str
    """

    T_scan_tracker: FloatArray
    touches_m: FloatArray
    residual_m: FloatArray
    used: NDArray[np.bool_]
    plane_points: NDArray[np.int64]
    fixed_motions: int
    free_motions: tuple[str, ...]
    free_directions: FloatArray
    motion: RigidMotion
    covariance: FloatArray
    notes: tuple[str, ...] = ()

    def point_sigma_m(self, points_tracker_m: FloatArray) -> FloatArray:
        """1-sigma position error that the transform's uncertainty gives points (tracker frame).

        Parameters
        ----------
        points_tracker_m : ndarray of shape (N, 3)

        Returns
        -------
        ndarray of shape (N,), metres
            Zero from the free motions (they are not known at all; see ``free_motions``).
        """
        return self.motion.point_sigma(self.covariance, points_tracker_m)

    def covariance_in_scan_frame(self) -> tuple[FloatArray, RigidMotion]:
        """The covariance and its twists' centre and scale expressed in the scan frame."""
        R = self.T_scan_tracker[:3, :3]
        rotate = np.zeros((6, 6))
        rotate[:3, :3] = R
        rotate[3:, 3:] = R
        centre = apply_transform(self.T_scan_tracker, self.motion.centre_m[None])[0]
        return rotate @ self.covariance @ rotate.T, RigidMotion(centre, self.motion.length_m)


def register_touches(
    touches_tracker_m: FloatArray,
    scan_points_m: FloatArray,
    *,
    T_scan_tracker_init: FloatArray,
    touch_sigma_m: FloatArray | None = None,
    scan_tree: cKDTree | None = None,
) -> TouchRegistration:
    """Register touches of the workpiece (tracker frame) to its scan (scan frame), point to plane.

    Each iteration maps the touches into the scan frame, fits a quadric to the scan points within
    :data:`PLANE_RADIUS_M` of each (its tangent plane at the touch's foot is the touch's plane),
    and takes one Gauss-Newton step on the touches' distances to their planes, in the motions
    the planes' normals fix (the others keep the initial guess). A
    touch whose distance stays large (more than :data:`OUTLIER_FACTOR` times what is expected of
    it) is left out and the fit repeated.

    Parameters
    ----------
    touches_tracker_m : ndarray of shape (T, 3), metres
    scan_points_m : ndarray of shape (M, 3), metres
    T_scan_tracker_init : ndarray of shape (4, 4)
        Within a few millimetres (the planes are found where the touches land).
    touch_sigma_m : ndarray of shape (T,), optional
        Each touch's own error (the tracker's noise averaged over the rest); the pivot
        calibration's :data:`TOUCH_PRIOR_M` is added to it.
    scan_tree : cKDTree, optional
        Over ``scan_points_m``, to reuse.

    Returns
    -------
    TouchRegistration

    Raises
    ------
    ValueError
        Malformed arrays or a non-rigid initial guess.
    RegistrationError
        Fewer than :data:`MIN_TOUCHES` touches on the scanned surface.
    """
    touches = np.asarray(touches_tracker_m, dtype=np.float64)
    if touches.ndim != 2 or touches.shape[1] != 3 or not np.all(np.isfinite(touches)):
        raise ValueError("touches_tracker_m must be finite with shape (T, 3)")
    scan = np.asarray(scan_points_m, dtype=np.float64)
    T = check_rigid(T_scan_tracker_init, name="the initial T_scan_tracker").copy()
    own = np.zeros(len(touches)) if touch_sigma_m is None else np.asarray(touch_sigma_m, float)
    tree = scan_tree if scan_tree is not None else cKDTree(scan)
    if len(touches) < MIN_TOUCHES:
        raise RegistrationError(
            f"{len(touches)} touches were found; at least {MIN_TOUCHES} are needed on two or "
            "three faces of the workpiece: rest the tip for half a second on each"
        )
    motion = RigidMotion.around(touches)
    used = np.ones(len(touches), dtype=bool)
    notes: list[str] = []
    while True:
        T, planes = _match(touches, used, own, scan, tree, T, motion)
        residual = np.full(len(touches), np.nan)
        mapped = apply_transform(T, touches)
        has_plane = planes.count >= MIN_PLANE_POINTS
        residual[has_plane] = np.einsum(
            "ti,ti->t", mapped[has_plane] - planes.centre[has_plane], planes.normal[has_plane]
        )
        expected = np.sqrt(own**2 + TOUCH_PRIOR_M**2 + planes.variance)
        bound = np.maximum(OUTLIER_FACTOR * expected, MIN_OUTLIER_M)
        bad = used & (~has_plane | ~(np.abs(np.nan_to_num(residual, nan=np.inf)) <= bound))
        if not bad.any():
            break
        # Leave out the worst one and fit again: one wrong touch pulls the others off too.
        excess = np.where(bad, np.abs(np.nan_to_num(residual, nan=np.inf)) / bound, -1.0)
        worst = int(np.argmax(excess))
        used[worst] = False
        if has_plane[worst]:
            notes.append(
                f"touch {worst + 1} is {abs(residual[worst]) * 1e3:.2f} mm off the scan's surface "
                "once the others are registered: left out (was the tip on the scanned workpiece?)"
            )
        else:
            notes.append(
                f"touch {worst + 1} has no scanned surface under it: left out (touch where the "
                "scan covers the workpiece)"
            )
        if np.count_nonzero(used) < MIN_TOUCHES:
            raise RegistrationError(
                f"only {np.count_nonzero(used)} of {len(touches)} touches lie on the scanned "
                f"surface ({'; '.join(notes)}); touch at least {MIN_TOUCHES} points the scan "
                "covers, or give a better initial guess (--scan-from-tracker)"
            )
    info, weights = _information(touches, used, planes, expected, T, motion)
    covariance, vectors, fixed = inverse_on_fixed(info, _fixed)
    free = vectors[:, ~fixed].T
    return TouchRegistration(
        T_scan_tracker=T,
        touches_m=touches,
        residual_m=residual,
        used=used,
        plane_points=planes.count,
        fixed_motions=int(np.count_nonzero(fixed)),
        free_motions=tuple(motion.describe(v) for v in free),
        free_directions=free,
        motion=motion,
        covariance=covariance,
        notes=tuple(notes),
    )


@dataclass(frozen=True)
class _Planes:
    centre: FloatArray  # (T, 3), scan frame
    normal: FloatArray  # (T, 3)
    count: NDArray[np.int64]  # (T,)
    variance: FloatArray  # (T,): of the plane's offset at the touch, m^2


def _planes(points_scan_m, scan, tree) -> _Planes:
    """The scan's tangent plane under each point, with its offset's variance.

    A quadric height field is fitted to the scan within :data:`PLANE_RADIUS_M` (robustly: points
    beyond three sigma are left out and it is fitted again) and its tangent plane taken at the
    point's foot. A plain plane would sit inside a curved face by half its sagitta (0.2 mm for a
    6 mm patch of a 50 mm cylinder), which a touch would then be registered to.
    """
    t = len(points_scan_m)
    centre, normal = np.zeros((t, 3)), np.tile([0.0, 0.0, 1.0], (t, 1))
    count, variance = np.zeros(t, np.int64), np.full(t, np.inf)
    for i, indices in enumerate(tree.query_ball_point(points_scan_m, PLANE_RADIUS_M)):
        if len(indices) < MIN_PLANE_POINTS:
            continue
        near = scan[indices]
        keep = np.ones(len(near), dtype=bool)
        frame = weighted_pca(near[None])
        local = frame.to_local(near[None])[0]
        design = quadric_design(local[:, 0], local[:, 1], scale=PLANE_RADIUS_M)
        for _ in range(3):  # robust: refit without the points beyond 3 sigma
            fit = fit_linear(design[None], local[None, :, 2], keep[None].astype(np.float64))
            distance = local[:, 2] - design @ fit.coef[0, :, 0]
            sigma = np.sqrt(np.mean(distance[keep] ** 2))
            keep = np.abs(distance) <= 3.0 * max(sigma, 1e-6)
        # The foot of the touch on the fitted surface, and the surface's normal there.
        at = frame.to_local(points_scan_m[i][None])[0]
        coef = fit.coef[0, :, 0]
        u, v = at[0] / PLANE_RADIUS_M, at[1] / PLANE_RADIUS_M
        row = quadric_design(at[:1], at[1:2], scale=PLANE_RADIUS_M)  # (1, 6)
        height = float(row[0] @ coef)
        slope_u = (coef[1] + 2 * coef[3] * u + coef[4] * v) / PLANE_RADIUS_M
        slope_v = (coef[2] + coef[4] * u + 2 * coef[5] * v) / PLANE_RADIUS_M
        n_local = np.array([-slope_u, -slope_v, 1.0])
        n_local /= np.linalg.norm(n_local)
        axes = frame.axes[0]
        centre[i] = frame.mean[0] + axes @ np.array([at[0], at[1], height])
        normal[i] = axes @ n_local
        count[i] = int(np.count_nonzero(keep))
        # The height's variance at the foot: the fit's leverage there times the scatter.
        variance[i] = sigma**2 * min(float(fit.leverage(row)[0]), 1.0)
    return _Planes(centre, normal, count, variance)


def _match(touches, used, own, scan, tree, T, motion):
    """Iterate planes and point-to-plane steps from ``T``; returns (T, planes at T)."""
    for _ in range(MAX_ITERATIONS):
        mapped = apply_transform(T, touches)
        planes = _planes(mapped, scan, tree)
        ok = used & (planes.count >= MIN_PLANE_POINTS)
        if np.count_nonzero(ok) < MIN_TOUCHES:
            return T, planes
        expected = np.sqrt(own**2 + TOUCH_PRIOR_M**2 + planes.variance)
        # Twists act in the scan frame, about the mapped touches' centre.
        step_motion = RigidMotion(apply_transform(T, motion.centre_m[None])[0], motion.length_m)
        axes = planes.normal[ok][:, None, :]
        jacobian = step_motion.jacobian(mapped[ok], axes)
        residual = np.einsum("ti,ti->t", mapped[ok] - planes.centre[ok], planes.normal[ok])
        weight = 1.0 / expected[ok] ** 2
        info = np.einsum("t,tai,taj->ij", weight, jacobian, jacobian)
        gradient = np.einsum("t,tai,t->i", weight, jacobian, residual)
        twist, _ = solve_constrained(info, gradient, _fixed)
        T = step_motion.transform(twist) @ T
        if np.linalg.norm(twist) < CONVERGED_M:
            break
    return T, _planes(apply_transform(T, touches), scan, tree)


def _fixed(values: FloatArray) -> np.ndarray:
    """Which eigenvalues of a touch information matrix belong to fixed motions."""
    return values > 1.0 / FREE_SIGMA_M**2


def _information(touches, used, planes, expected, T, motion):
    """The touches' information about the twist of ``motion`` (tracker frame), 6x6."""
    ok = used & (planes.count >= MIN_PLANE_POINTS)
    # The planes' normals back in the tracker frame, where the twist is expressed.
    normals = planes.normal[ok] @ T[:3, :3]
    jacobian = motion.jacobian(touches[ok], normals[:, None, :])
    weights = 1.0 / expected[ok] ** 2
    return np.einsum("t,tai,taj->ij", weights, jacobian, jacobian), weights


def motions_missing(
    touches: TouchRegistration, feature_info: FloatArray, *, motion: RigidMotion
) -> list[str]:
    """The motions a traced feature needs fixed that the touches leave free.

    Parameters
    ----------
    touches : TouchRegistration
    feature_info : ndarray of shape (6, 6)
        What the trace's own registration to its feature would learn about each motion (its
        information matrix for twists of ``motion``): the motions it constrains are the ones that
        move the traced path relative to the feature, the ones the robot's path depends on.
    motion : RigidMotion
        The twists ``feature_info`` is expressed in (tracker frame).

    Returns
    -------
    list of str
        Each missing motion in words; empty when the touches fix everything the feature needs.
    """
    values, vectors = np.linalg.eigh(feature_info)
    needed = vectors[:, fixed_by_ratio(values)]
    if needed.shape[1] == 0 or touches.free_directions.shape[0] == 0:
        return []
    # Express the touches' free motions in the feature's twist coordinates: the same rigid
    # motion about another centre and scale.
    free = np.array([_rebase(v, touches.motion, motion) for v in touches.free_directions])
    free /= np.linalg.norm(free, axis=1)[:, None]
    missing = []
    for direction in free:
        share = np.linalg.norm(needed.T @ direction)
        if share > 0.3:  # the free motion moves the traced path against its feature
            missing.append(motion.describe(direction))
    return missing


def _rebase(twist: FloatArray, source: RigidMotion, target: RigidMotion) -> FloatArray:
    """The same small rigid motion as a twist of another centre and scale."""
    omega = twist[:3] / source.length_m
    # x -> x + omega x (x - c1) + t1 = x + omega x (x - c2) + t1 + omega x (c2 - c1)
    t2 = twist[3:] + np.cross(omega, target.centre_m - source.centre_m)
    return np.concatenate([omega * target.length_m, t2])
