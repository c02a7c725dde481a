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
   touch's foot, re-fitted as the transform moves), solved for the motions the touches pin through
   their planes' normals; the motions only the planes' noisy tilts would pin keep the initial
   guess. Touches that stay far off the surface are left out and named.
3. :func:`touch_uncertainty` and :meth:`TouchUncertainty.check`: the one rule by which touches are
   accepted, for a reconstruction and for a calibration alike. The 1-sigma position error the
   touches leave *at the path* (across its features; over the scanned workpiece near the touches
   when there is no path), in millimetres, per poorly pinned motion and overall, is held against a
   tolerance; a refusal names each motion with its millimetres and what to touch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from recon.arrays import FloatArray
from recon.classify import SegmentKind, classify_segments
from recon.errors import DegenerateInputError, RegistrationError, TouchesInsufficientError
from recon.fitting import fit_linear, quadric_design, weighted_pca
from recon.icp import RigidMotion, _across
from recon.recon_params import ReconParams
from recon.transforms import apply_transform, check_rigid, invert_transform

if TYPE_CHECKING:
    from recon.scan_model import ScanModel

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
#: How far the planes' normals may be tilted (1 sigma): the quadric's tangent plane of a
#: millimetre-noise scan within :data:`PLANE_RADIUS_M`, and a touch near a face's border whose
#: patch reaches round the edge, are off by a degree or two.
PLANE_TILT_RAD = np.radians(2.0)
#: What the initial guess of a registration by touches is taken to be off by, by default (1 sigma,
#: as a twist at the touches' extent, in every motion): a stored calibration, a millimetre or so.
#: (The accuracy scenes' scanner, misplaced by 2 mm and half a degree, is such a guess in turning:
#: about 1 mm at the touches' extent; its shift the touches always pin.) The motions the touches
#: pin worse than their initial guess keep it, and are judged at this sigma.
INITIAL_GUESS_SIGMA_M = 1e-3
#: ... and when the guess is rougher: the trace registered to the scan, off by the rigid part of
#: the hand's drift (the hand's error is 0.8 mm, and a registration to a trace keeps its slow
#: drift, see recon.reconstruct.registration_sigma_m), or the frames as given. Measured: on a box
#: traced along two edges, a turning the touches pinned to 1 mm came out 0.8 mm off at the path
#: when left to the trace's registration, 0.35 mm when taken from the touches.
ROUGH_GUESS_SIGMA_M = 2e-3
#: A motion is solved for (the touches move it; the others keep the initial guess) when it moves
#: the touches along their planes' normals at least this many times more (in information: the
#: square of the ratio of weighted RMS movements) than a tilt of those planes by
#: :data:`PLANE_TILT_RAD` could feign, and the touches pin it better than the initial guess is
#: taken to be (each motion is taken from whichever knows it better; on the accuracy scenes,
#: solving a ridge's turning that the touches pinned to 1.2-2.4 mm made its path worse than the
#: 1 mm guess). Sliding on a plate and turning about its normal are pinned only through the
#: normals' tilts: a ratio of 0.1-1 on touches of one plate or one face of a box (measured,
#: recon.scenes), where a 3-2-1 set on a box pins every motion with a ratio of 30 or more; the
#: sigma of a motion pinned only by tilts means nothing (1.3-40 mm on plates). Whether what is
#: solved is good enough is not for these thresholds to say but for :func:`touch_uncertainty`,
#: at the path.
MIN_NORMAL_TO_TILT = 4.0
#: Touches are judged at most at this many points (evenly taken from the path or the scan): the
#: largest error over more points differs by a few percent.
MAX_JUDGED_POINTS = 4000
#: Without a path, touches are judged over the scan within this of their bounding box (tracker
#: frame): where a path on the touched workpiece will be.
NEAR_TOUCHES_M = 10e-3
#: A refusal names every motion leaving more than this share of the tolerance at the path (a
#: quarter of the variance the tolerance allows), and always the worst.
NAMED_SHARE = 0.5
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
        return float(self.spread_m / np.sqrt(3.0 * max(self.n_samples, 1)))


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
        How many of the six rigid motions the touches solve for (see
        :data:`MIN_NORMAL_TO_TILT`): how well each is pinned, and whether that is enough, is
        :func:`touch_uncertainty`'s to say.
    free_motions : tuple of str
        The others, in words ("sliding along (1.00, 0.00, 0.00)"): they keep the initial guess.
    free_directions : ndarray of shape (F, 6)
        Those motions as orthonormal unit twists of ``motion``.
    motion : RigidMotion
        The twists' centre and scale.
    covariance : ndarray of shape (6, 6)
        Of the solved motions' twist (zero along the free ones), from the touches' expected
        errors.
    notes : tuple of str
    judgement : TouchUncertainty, optional
        What the touches leave at the path they were checked for (set by the callers that judge
        them: :func:`recon.reconstruct.touches_for_trace`, a calibration).
    initial_sigma_m : float
        What the initial guess was taken to be off by: the free motions keep it, and are judged
        at it.
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
    judgement: TouchUncertainty | None = None
    initial_sigma_m: float = INITIAL_GUESS_SIGMA_M

    def point_sigma_m(self, points_tracker_m: FloatArray) -> FloatArray:
        """1-sigma position error that the transform's uncertainty gives points (tracker frame).

        Parameters
        ----------
        points_tracker_m : ndarray of shape (N, 3)

        Returns
        -------
        ndarray of shape (N,), metres
            Zero from the free motions (the touches do not know them; see ``free_motions`` and
            :func:`touch_uncertainty`, which counts them).
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
    initial_sigma_m: float = INITIAL_GUESS_SIGMA_M,
) -> TouchRegistration:
    """Register touches of the workpiece (tracker frame) to its scan (scan frame), point to plane.

    Each iteration maps the touches into the scan frame, fits a quadric to the scan points within
    :data:`PLANE_RADIUS_M` of each (its tangent plane at the touch's foot is the touch's plane),
    and takes one Gauss-Newton step on the touches' distances to their planes, in the motions
    the planes' normals pin better than the initial guess (:data:`MIN_NORMAL_TO_TILT`,
    ``initial_sigma_m``; the others keep the initial guess). A touch whose distance stays large
    (more than :data:`OUTLIER_FACTOR` times what is expected of it) is left out and the fit
    repeated.

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
    initial_sigma_m : float
        What ``T_scan_tracker_init`` is taken to be off by (1 sigma, as a twist at the touches'
        extent): :data:`INITIAL_GUESS_SIGMA_M`, or :data:`ROUGH_GUESS_SIGMA_M` when it is the
        trace registered to the scan or the frames as given. The motions the touches pin worse
        keep it.

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
    if not initial_sigma_m > 0:
        raise ValueError(f"initial_sigma_m must be positive, got {initial_sigma_m}")
    if len(touches) < MIN_TOUCHES:
        raise RegistrationError(
            f"{len(touches)} touches were found; at least {MIN_TOUCHES} are needed on two or "
            "three faces of the workpiece: rest the tip for half a second on each"
        )
    motion = RigidMotion.around(touches)
    used = np.ones(len(touches), dtype=bool)
    notes: list[str] = []
    while True:
        T, planes = _match(touches, used, own, scan, tree, T, motion, initial_sigma_m)
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
        with np.errstate(invalid="ignore"):  # no plane: inf / inf, the first to go
            excess = np.where(bad, np.abs(np.nan_to_num(residual, nan=np.inf)) / bound, -1.0)
        excess = np.nan_to_num(excess, nan=np.inf)
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
    info, tilt = _information(touches, used, planes, expected, T, motion)
    split = _split(info, tilt, initial_sigma_m)
    free = split.free.T
    return TouchRegistration(
        T_scan_tracker=T,
        touches_m=touches,
        residual_m=residual,
        used=used,
        plane_points=planes.count,
        fixed_motions=split.n_solved,
        free_motions=tuple(motion.describe(v) for v in free),
        free_directions=free,
        motion=motion,
        covariance=split.covariance,
        notes=tuple(notes),
        initial_sigma_m=float(initial_sigma_m),
    )


@dataclass(frozen=True)
class _Planes:
    centre: FloatArray  # (T, 3), scan frame
    normal: FloatArray  # (T, 3)
    count: NDArray[np.int64]  # (T,)
    variance: FloatArray  # (T,): of the plane's offset at the touch, m^2


def _planes(points_scan_m: FloatArray, scan: FloatArray, tree: cKDTree) -> _Planes:
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


def _match(
    touches: FloatArray,
    used: NDArray[np.bool_],
    own: FloatArray,
    scan: FloatArray,
    tree: cKDTree,
    T: FloatArray,
    motion: RigidMotion,
    initial_sigma_m: float,
) -> tuple[FloatArray, _Planes]:
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
        weight = 1.0 / expected[ok] ** 2
        info, tilt = _normal_and_tilt(mapped[ok], planes.normal[ok], weight, step_motion)
        jacobian = step_motion.jacobian(mapped[ok], planes.normal[ok][:, None, :])[:, 0]
        residual = np.einsum("ti,ti->t", mapped[ok] - planes.centre[ok], planes.normal[ok])
        gradient = np.einsum("t,ti,t->i", weight, jacobian, residual)
        twist = -_split(info, tilt, initial_sigma_m).covariance @ gradient
        T = step_motion.transform(twist) @ T
        if np.linalg.norm(twist) < CONVERGED_M:
            break
    return T, _planes(apply_transform(T, touches), scan, tree)


@dataclass(frozen=True)
class _Split:
    """The motions the touches pin and the ones they leave to the initial guess.

    ``solved`` (6, S) and ``free`` (6, F) are orthonormal twists, together a basis. Orthogonal, so
    that a step in the solved ones moves nothing along the free ones: steps along directions
    merely independent of them would drag the free motions along, iteration after iteration.
    """

    solved: FloatArray  # (6, S), columns
    values: FloatArray  # (S,): the information along each
    free: FloatArray  # (6, F), columns

    @property
    def n_solved(self) -> int:
        return int(self.solved.shape[1])

    @property
    def covariance(self) -> FloatArray:
        """Of the solved motions' twist, (6, 6); zero along the free ones."""
        return (self.solved / self.values) @ self.solved.T


def _split(info: FloatArray, tilt: FloatArray, initial_sigma_m: float) -> _Split:
    """Which motions the touches pin through their planes' normals (see
    :data:`MIN_NORMAL_TO_TILT`), better than the initial guess knows them (``initial_sigma_m``, 1
    sigma as a twist)."""
    # First the motions the touches see only through their planes' tilts: the generalized
    # eigenvectors of (information, tilt information) with a small ratio. A motion that moves
    # every touch straight along its normal has no tilt information at all: a floor keeps the
    # problem definite (and that motion's ratio large).
    floor = 1e-9 * max(float(np.trace(tilt)), float(np.trace(info)) * 1e-6, 1e-300)
    ratio, directions = scipy.linalg.eigh(info, tilt + floor * np.eye(6))
    tilt_only = directions[:, ratio <= MIN_NORMAL_TO_TILT]
    if tilt_only.shape[1]:
        tilt_only, _ = np.linalg.qr(tilt_only)
    # Then, in the motions orthogonal to those, the touches' information's own axes, solved for
    # where they pin them well enough.
    basis, _, _ = np.linalg.svd(np.eye(6) - tilt_only @ tilt_only.T)
    rest = basis[:, : 6 - tilt_only.shape[1]]
    values, axes = np.linalg.eigh(rest.T @ info @ rest)
    axes = rest @ axes
    pinned = values > 1.0 / initial_sigma_m**2
    return _Split(axes[:, pinned], values[pinned], np.hstack([tilt_only, axes[:, ~pinned]]))


def _normal_and_tilt(
    points: FloatArray, normals: FloatArray, weights: FloatArray, motion: RigidMotion
) -> tuple[FloatArray, FloatArray]:
    """The touches' information about a twist of ``motion`` through their planes' normals, and
    what tilts of those planes by :data:`PLANE_TILT_RAD` would feign, both (6, 6).

    A tilt turns part of a touch's movement along its plane into movement along the normal, so
    the information a motion gets from tilts alone is the weighted square of its movement along
    the planes times the tilt's variance.
    """
    full = motion.jacobian(points, np.broadcast_to(np.eye(3), (len(points), 3, 3)))  # (T, 3, 6)
    along_normal = np.einsum("ti,tij->tj", normals, full)
    info = np.einsum("t,ti,tj->ij", weights, along_normal, along_normal)
    in_plane = full - normals[:, :, None] * along_normal[:, None, :]
    tilt = PLANE_TILT_RAD**2 * np.einsum("t,tai,taj->ij", weights, in_plane, in_plane)
    return info, tilt


def _information(
    touches: FloatArray,
    used: NDArray[np.bool_],
    planes: _Planes,
    expected: FloatArray,
    T: FloatArray,
    motion: RigidMotion,
) -> tuple[FloatArray, FloatArray]:
    """The touches' information about the twist of ``motion`` (tracker frame), and the tilts'
    (see :func:`_normal_and_tilt`), 6x6 each."""
    ok = used & (planes.count >= MIN_PLANE_POINTS)
    # The planes' normals back in the tracker frame, where the twist is expressed.
    normals = planes.normal[ok] @ T[:3, :3]
    return _normal_and_tilt(touches[ok], normals, 1.0 / expected[ok] ** 2, motion)


# -- the one rule: what the touches leave at the path ------------------------------------------


@dataclass(frozen=True)
class MotionUncertainty:
    """One motion as the touches leave it, and the error it leaves at the path.

    Attributes
    ----------
    motion : str
        In words ("turning about (0.00, 0.00, 1.00)"; the axis passes through the touches'
        centre).
    twist_m : ndarray of shape (6,)
        Its 1-sigma twist of :attr:`TouchRegistration.motion`, metres.
    at_path_m : float
        The largest 1-sigma displacement it gives a judged point, in the directions that matter
        there, metres.
    solved : bool
        False for a motion the touches pin worse than the initial guess, or through their
        planes' tilts only: it keeps the initial guess, taken to be off by
        :attr:`TouchRegistration.initial_sigma_m`.
    """

    motion: str
    twist_m: FloatArray
    at_path_m: float
    solved: bool


@dataclass(frozen=True)
class TouchUncertainty:
    """What the touches' uncertainty leaves at the path (see :func:`touch_uncertainty`).

    Attributes
    ----------
    points_m : ndarray of shape (N, 3)
        The points judged, tracker frame.
    sigma_m : ndarray of shape (N,)
        Each one's 1-sigma position error from the touches, in the directions that matter there
        (RMS over them), metres.
    motions : tuple of MotionUncertainty
        Its principal parts, worst first: their variances add up to ``sigma_m ** 2`` at every
        point.
    where : str
        Where and in which directions it was judged, for messages ("at the traced path, across
        its features").
    guess_sigma_m : float
        What the motions the touches did not solve for were taken to be off by.
    """

    points_m: FloatArray
    sigma_m: FloatArray
    motions: tuple[MotionUncertainty, ...]
    where: str
    guess_sigma_m: float

    @property
    def worst_m(self) -> float:
        """The largest 1-sigma error at a judged point, metres."""
        return float(self.sigma_m.max()) if len(self.sigma_m) else 0.0

    def summary(self) -> str:
        """One line: the largest error and the motion that leaves most of it."""
        text = f"{_mm(self.worst_m)} (1 sigma, at most) {self.where}"
        if self.motions and self.motions[0].at_path_m > 0.0:
            worst = self.motions[0]
            text += f"; most from {worst.motion} ({_mm(worst.at_path_m)})"
            if not worst.solved:
                text += ", which the touches pin too little to solve for"
        return text

    def problem(self, tolerance_m: float) -> str | None:
        """Why these touches are not good enough at ``tolerance_m`` (1 sigma), or None."""
        if not tolerance_m > 0:
            raise ValueError(f"tolerance_m must be positive, got {tolerance_m}")
        if self.worst_m <= tolerance_m:
            return None
        named = [m for m in self.motions if m.at_path_m > NAMED_SHARE * tolerance_m]
        parts = []
        for m in named or self.motions[:1]:
            text = f"{m.motion} leaves {_mm(m.at_path_m)}"
            if not m.solved:
                text += (
                    " (the touches pin it too little to solve for it: it keeps the initial "
                    f"guess, taken to be {self.guess_sigma_m * 1e3:.0f} mm off)"
                )
            parts.append(f"{text}: {touch_advice(m.motion, solved=m.solved)}")
        return (
            f"the touches leave the scan's placement uncertain by up to {_mm(self.worst_m)} "
            f"(1 sigma) {self.where}, more than the {_mm(tolerance_m)} tolerance: "
            + "; ".join(parts)
        )

    def check(self, tolerance_m: float, *, remedy: str = "") -> None:
        """Refuse touches that leave more than ``tolerance_m`` (1 sigma) at the path.

        Parameters
        ----------
        tolerance_m : float
        remedy : str
            What else can be done, appended to the message ("or reconstruct without the
            touches").

        Raises
        ------
        TouchesInsufficientError
            Naming each poorly pinned motion with the millimetres it leaves and what to touch.
        """
        problem = self.problem(tolerance_m)
        if problem is not None:
            raise TouchesInsufficientError(problem + (f"; {remedy}" if remedy else ""))


def touch_uncertainty(
    touches: TouchRegistration,
    points_tracker_m: FloatArray,
    *,
    axes: FloatArray | None = None,
    where: str,
) -> TouchUncertainty:
    """The 1-sigma position error the touches leave at points, in the directions that matter.

    The rule by which touches are accepted, wherever they are used: each motion contributes its
    uncertainty, the motions the touches solve for with their covariance (from the touches'
    expected errors), the others with the initial guess's sigma (they keep the initial guess,
    :attr:`TouchRegistration.initial_sigma_m`). A motion the touches pin poorly is as good as the
    error it leaves where it matters: turning about an axis near the path moves the path little,
    sliding along a straight edge not at all.

    Parameters
    ----------
    touches : TouchRegistration
    points_tracker_m : ndarray of shape (N, 3), metres
        Where to judge: the path's points, or where a path will be. At most
        :data:`MAX_JUDGED_POINTS` of them, evenly taken, are used.
    axes : ndarray of shape (N, A, 3), optional
        The directions that matter at each point (tracker frame; unit or zero rows), e.g. the two
        across an edge the path follows, or a surface's normal (see :func:`path_axes`). All three
        (the full displacement) when not given.
    where : str
        Where that is, for messages.

    Returns
    -------
    TouchUncertainty
    """
    points = np.asarray(points_tracker_m, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError("points_tracker_m must have shape (N, 3) with N >= 1")
    if axes is None:
        axes = np.broadcast_to(np.eye(3), (len(points), 3, 3))
    axes = np.asarray(axes, dtype=np.float64)
    if axes.ndim != 3 or axes.shape[0] != len(points) or axes.shape[2] != 3:
        raise ValueError("axes must have shape (N, A, 3) for N points")
    step = max(1, -(-len(points) // MAX_JUDGED_POINTS))
    points, axes = points[::step], axes[::step]
    full = touches.motion.jacobian(points, np.broadcast_to(np.eye(3), (len(points), 3, 3)))
    moves = np.einsum("nab,nbi->nai", axes, full)  # (N, A, 6): twist -> what matters
    free = touches.free_directions.T  # (6, F), orthonormal
    parts = [(touches.covariance, True), (touches.initial_sigma_m**2 * free @ free.T, False)]
    motions, variance = [], np.zeros(len(points))
    for covariance, solved in parts:
        variance += np.einsum("nai,ij,naj->n", moves, covariance, moves)
        for twist in _principal_motions(covariance, moves):
            at_path = float(np.linalg.norm(moves @ twist, axis=1).max())
            words = touches.motion.describe(twist)
            motions.append(MotionUncertainty(words, twist, at_path, solved))
    motions.sort(key=lambda m: -m.at_path_m)
    return TouchUncertainty(
        points_m=points,
        sigma_m=np.sqrt(np.maximum(variance, 0.0)),
        motions=tuple(motions),
        where=where,
        guess_sigma_m=touches.initial_sigma_m,
    )


def _principal_motions(covariance: FloatArray, moves: FloatArray) -> list[FloatArray]:
    """A twist covariance as a sum of 1-sigma twists ``c_k c_k^T``, ordered by how much they
    move the points on average (most first): the motions that leave most at the path, rather
    than the covariance's own axes, whose twists mix metres and radians by the touches' extent.

    Parameters
    ----------
    covariance : ndarray of shape (6, 6)
    moves : ndarray of shape (N, A, 6)
        What each twist component moves each point by, in the directions that matter.

    Returns
    -------
    list of ndarray of shape (6,)
    """
    values, vectors = np.linalg.eigh(covariance)
    keep = values > 1e-12 * max(float(values.max()), 1e-300)
    if not keep.any():
        return []
    root = vectors[:, keep] * np.sqrt(values[keep])  # covariance = root @ root.T
    metric = np.einsum("nai,naj->ij", moves, moves) / len(moves)
    _, rotate = np.linalg.eigh(root.T @ metric @ root)
    twists = root @ rotate[:, ::-1]  # still root-like: twists @ twists.T = covariance
    return [twists[:, k] for k in range(twists.shape[1])]


def path_axes(
    points_tracker_m: FloatArray,
    model: ScanModel,
    bounds: list[tuple[int, int]],
    params: ReconParams,
    *,
    T_scan_tracker: FloatArray,
) -> FloatArray:
    """The directions in which a registration error moves each point of a path off its result:
    across the edge where a segment follows an edge, along the normal where it follows a
    surface (the reconstruction puts the point on the feature there, so an error along the
    feature changes nothing), every direction where it follows nothing of the scan (the tool's
    orientation and the collision checks still use the scan there). As in
    :func:`recon.registration.feature_information`, whose information is the sum of these.

    Parameters
    ----------
    points_tracker_m : ndarray of shape (N, 3)
        The resampled path, tracker frame.
    model : ScanModel
    bounds : list of (start, stop)
    params : ReconParams
    T_scan_tracker : ndarray of shape (4, 4)

    Returns
    -------
    ndarray of shape (N, 3, 3)
        Unit rows (tracker frame), zero rows where fewer than three directions matter.
    """
    points = np.asarray(points_tracker_m, dtype=np.float64)
    in_scan = apply_transform(T_scan_tracker, points)
    R = np.asarray(T_scan_tracker, dtype=np.float64)[:3, :3]
    axes = np.tile(np.eye(3), (len(points), 1, 1))
    classes = classify_segments(in_scan, bounds, model, params)
    for (start, stop), segment_class in zip(bounds, classes, strict=True):
        here = in_scan[start:stop]
        if segment_class.kind == SegmentKind.EDGE and model.edge_tree is not None:
            _, index = model.edge_tree.query(here, workers=-1)
            axes[start:stop] = 0.0
            axes[start:stop, :2] = _across(model.edges.directions[index]) @ R
        elif segment_class.kind == SegmentKind.SURFACE:
            _, index = model.coarse_tree.query(here, workers=-1)
            axes[start:stop] = 0.0
            axes[start:stop, 0] = model.features.normals[index] @ R
    return axes


def judge_at_path(
    touches: TouchRegistration,
    points_tracker_m: FloatArray,
    model: ScanModel,
    bounds: list[tuple[int, int]],
    params: ReconParams,
) -> TouchUncertainty:
    """What the touches leave at a traced path, across its features (see :func:`path_axes`).

    Parameters
    ----------
    touches : TouchRegistration
    points_tracker_m : ndarray of shape (N, 3)
        The resampled path, tracker frame.
    model : ScanModel
        Built around the path placed by the touches.
    bounds : list of (start, stop)
    params : ReconParams
    """
    axes = path_axes(points_tracker_m, model, bounds, params, T_scan_tracker=touches.T_scan_tracker)
    return touch_uncertainty(
        touches, points_tracker_m, axes=axes, where="at the traced path, across its features"
    )


def judge_near_touches(touches: TouchRegistration, scan_points_m: FloatArray) -> TouchUncertainty:
    """What the touches leave where a path on the touched workpiece will be, when there is no
    path to judge them by: over the scan within :data:`NEAR_TOUCHES_M` of the touches' bounding
    box, in every direction.

    Parameters
    ----------
    touches : TouchRegistration
    scan_points_m : ndarray of shape (M, 3)
        The scan, scan frame.
    """
    used = touches.touches_m[touches.used]
    low, high = used.min(axis=0) - NEAR_TOUCHES_M, used.max(axis=0) + NEAR_TOUCHES_M
    scan = apply_transform(invert_transform(touches.T_scan_tracker), scan_points_m)
    near = scan[np.all((scan >= low) & (scan <= high), axis=1)]
    if len(near) == 0:  # cannot be: every used touch has scan points under it
        return touch_uncertainty(touches, used, where="at the touches (no path given)")
    return touch_uncertainty(
        touches,
        near,
        where=(
            "over the scanned workpiece around the touches (no path given, so every direction "
            f"counts; the scan within {NEAR_TOUCHES_M * 1e3:.0f} mm of the touches' extent)"
        ),
    )


def touch_advice(motion: str, *, solved: bool = False) -> str:
    """What to touch to pin a motion better.

    Parameters
    ----------
    motion : str
        In words, as :meth:`recon.icp.RigidMotion.describe` gives it.
    solved : bool
        Whether the touches pin it at all (then: more of the same, farther apart), or not (then:
        another face).
    """
    if motion.startswith("sliding along"):
        towards = motion.removeprefix("sliding ")
        if solved:
            return f"touch more points on the faces that face {towards}"
        return f"touch a face that faces {towards}"
    axis = motion.removeprefix("turning about ")
    if solved:
        return f"touch points farther apart across the axis {axis}"
    return f"touch a face that does not face along the axis {axis}, away from it"


def _mm(value_m: float) -> str:
    return f"{value_m * 1e3:.2f} mm"
