"""Calibrations from measurements: the pen's tip offset, and tracker-to-robot transforms.

* **Pivot calibration.** The operator keeps the pen's tip on one point and pivots the pen. Every
  rigid-body pose (R_i, p_i) then maps the unknown tip offset t (rigid-body frame) onto the same
  unknown point c (tracker frame): ``R_i t + p_i = c``. Stacked, ``[R_i  -I] [t; c] = -p_i`` is
  linear least squares in six unknowns; it is well posed only if the pen turned about at least
  two different axes, which the singular values of the stacked matrix tell.
* **Point pairs.** The robot touches N points with a tracked tip (or carries a tracked marker to
  N poses): the same physical points in two frames give ``T_a_b`` by the Kabsch/Umeyama least
  squares (no scale). Each pair's leave-one-out residual (the pair's error under the transform
  fitted to all the others) singles out a bad pair, which the plain residual hides because the
  fit bends towards it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from recon.arrays import FloatArray
from recon.errors import DegenerateInputError
from recon.transforms import apply_transform

#: The pen must turn through at least this much (about two different axes) for a pivot fit.
MIN_PIVOT_ROTATION_DEG = 15.0
#: Point pairs whose spread across their second principal axis is below this are collinear.
MIN_PAIR_SPREAD_M = 1e-3
#: Pairs are touched in one robot cell: a coordinate beyond this is a unit mix-up (m).
MAX_PAIR_COORDINATE_M = 50.0
#: A hand-held pen's tip lies within this of its rigid body (m).
MAX_TIP_OFFSET_M = 0.5
#: A pivot whose tip wandered more than this (RMS, m) did not pivot at all: no override stores it
#: (``accept_poor_fit`` widens the tolerance up to here, never beyond).
MAX_PIVOT_RMS_M = 0.01


@dataclass(frozen=True)
class PivotCalibration:
    """The result of a pivot calibration.

    Attributes
    ----------
    tip_offset_m : ndarray of shape (3,), metres
        The tip in the rigid-body frame: ``tip = R @ tip_offset_m + p``.
    pivot_point_m : ndarray of shape (3,), metres
        The point the tip stayed on, tracker frame.
    residuals_m : ndarray of shape (N,), metres
        Distance of each sample's computed tip from the pivot point.
    residual_rms_m, residual_max_m : float
    rotation_spread_deg : float
        How far the pen turned about its second-best-excited axis (for a pen stirred around a
        cone, the cone's half-angle): small values leave the offset poorly determined.
    n_used, n_rejected : int
        Samples in the final fit, and samples dropped as outliers (a slipping tip).
    """

    tip_offset_m: FloatArray
    pivot_point_m: FloatArray
    residuals_m: FloatArray
    residual_rms_m: float
    residual_max_m: float
    rotation_spread_deg: float
    n_used: int
    n_rejected: int

    def poor_fit(self, tolerance_m: float) -> str | None:
        """Why this pivot is not to be trusted at ``tolerance_m`` (RMS), or None."""
        return pivot_fit_problem(self.tip_offset_m, self.residual_rms_m, tolerance_m)


def pivot_fit_impossible(tip_offset_m: FloatArray, residual_rms_m: float) -> str | None:
    """Why a pivot with this tip offset (3,) and RMS residual (m) is physically no pen's (and is
    never stored, whatever the override), or None."""
    length_m = float(np.linalg.norm(tip_offset_m))
    if not np.isfinite(length_m) or length_m > MAX_TIP_OFFSET_M:
        return (
            f"the tip is {length_m * 1e3:.0f} mm from the rigid body, more than a pen's "
            f"{MAX_TIP_OFFSET_M * 1e3:.0f} mm: the tip slipped, or the units are wrong"
        )
    if not np.isfinite(residual_rms_m) or residual_rms_m > MAX_PIVOT_RMS_M:
        return (
            f"the tip wandered {residual_rms_m * 1e3:.1f} mm RMS, more than the "
            f"{MAX_PIVOT_RMS_M * 1e3:.0f} mm of any pivot: the tip was not held on one point"
        )
    return None


def pivot_fit_problem(
    tip_offset_m: FloatArray, residual_rms_m: float, tolerance_m: float
) -> str | None:
    """Why a pivot with this tip offset (3,) and RMS residual (m) is not to be trusted at
    ``tolerance_m``, or None."""
    impossible = pivot_fit_impossible(tip_offset_m, residual_rms_m)
    if impossible is not None:
        return impossible
    if residual_rms_m > tolerance_m:
        return (
            f"the tip stayed within {residual_rms_m * 1e3:.2f} mm RMS of one point, worse than "
            f"the {tolerance_m * 1e3:.2f} mm tolerance: hold the tip still in a dimple and "
            "pivot again"
        )
    return None


def pivot_calibration(
    position_m: FloatArray,
    orientation_xyzw: FloatArray,
    *,
    reject_factor: float = 4.0,
) -> PivotCalibration:
    """Tip offset of a tracked pen from a pivoting recording.

    Parameters
    ----------
    position_m : ndarray of shape (N, 3), metres
        Rigid-body positions (tracker frame).
    orientation_xyzw : ndarray of shape (N, 4)
        Rigid-body orientations, unit quaternions, scalar last.
    reject_factor : float
        After a first fit, samples whose residual exceeds this many times the median residual
        (and 0.5 mm) are dropped once and the fit repeated: the tip slipping for a moment should
        not pull the result.

    Returns
    -------
    PivotCalibration

    Raises
    ------
    ValueError
        Shapes, NaN, or quaternions that are not unit length.
    DegenerateInputError
        Fewer than 10 samples, or the pen did not pivot enough about two axes.
    """
    p = np.asarray(position_m, dtype=np.float64)
    q = np.asarray(orientation_xyzw, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or q.shape != (len(p), 4):
        raise ValueError(
            f"position_m must be (N, 3) and orientation_xyzw (N, 4), got {p.shape}, {q.shape}"
        )
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise ValueError("pivot samples contain NaN or infinite values; drop lost frames first")
    if np.any(np.abs(np.linalg.norm(q, axis=1) - 1.0) > 1e-3):
        raise ValueError("orientation_xyzw must be unit quaternions (x, y, z, w)")
    if len(p) < 10:
        raise DegenerateInputError(
            f"a pivot calibration needs at least 10 samples, got {len(p)}; record a few seconds "
            "of pivoting"
        )
    R = Rotation.from_quat(q).as_matrix()
    spread = _rotation_spread_deg(R)
    if spread < MIN_PIVOT_ROTATION_DEG:
        raise DegenerateInputError(
            f"the pen turned only {spread:.1f} deg about its second axis (at least "
            f"{MIN_PIVOT_ROTATION_DEG:.0f} needed): keep the tip on the point and tilt the pen "
            "in several directions, like stirring a cone"
        )
    keep = np.ones(len(p), dtype=bool)
    tip, centre, residuals = _pivot_fit(R, p, keep)
    median = float(np.median(residuals))
    outliers = residuals > max(reject_factor * median, 5e-4)
    if np.any(outliers) and np.count_nonzero(~outliers) >= 10:
        keep = ~outliers
        tip, centre, _ = _pivot_fit(R, p, keep)
        residuals = np.linalg.norm(R @ tip + p - centre, axis=1)
    used = residuals[keep]
    return PivotCalibration(
        tip_offset_m=tip,
        pivot_point_m=centre,
        residuals_m=residuals,
        residual_rms_m=float(np.sqrt(np.mean(used**2))),
        residual_max_m=float(used.max()),
        rotation_spread_deg=spread,
        n_used=int(np.count_nonzero(keep)),
        n_rejected=int(np.count_nonzero(~keep)),
    )


def _pivot_fit(
    R: FloatArray, p: FloatArray, keep: np.ndarray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    n = int(np.count_nonzero(keep))
    A = np.zeros((n, 3, 6))
    A[:, :, :3] = R[keep]
    A[:, :, 3:] = -np.eye(3)
    solution, *_ = np.linalg.lstsq(A.reshape(-1, 6), -p[keep].reshape(-1), rcond=None)
    tip, centre = solution[:3], solution[3:]
    residuals = np.linalg.norm(R @ tip + p - centre, axis=1)
    return tip, centre, residuals


def _rotation_spread_deg(R: FloatArray) -> float:
    """The second-largest spread of the rotations about their mean (degrees).

    A pen turning about one axis only leaves the offset along that axis undetermined; the
    second principal spread of the rotation vectors (relative to the mean rotation) measures
    the excitation that matters. Scaled by sqrt(2) so that a pen stirred evenly around a cone
    gives the cone's half-angle.
    """
    rotations = Rotation.from_matrix(R)
    mean = rotations.mean()
    rotvec = (mean.inv() * rotations).as_rotvec()
    singular = np.linalg.svd(rotvec - rotvec.mean(axis=0), compute_uv=False)
    return float(np.degrees(np.sqrt(2.0) * singular[1] / np.sqrt(len(R))))


@dataclass(frozen=True)
class PointPairCalibration:
    """A rigid transform fitted to point pairs.

    Attributes
    ----------
    T_a_b : ndarray of shape (4, 4)
        Maps points of frame b into frame a (metres).
    residuals_m : ndarray of shape (N,), metres
        ``|T_a_b b_i - a_i|`` for every pair.
    leave_one_out_m : ndarray of shape (N,), metres
        Each pair's error under the transform fitted to the other pairs (NaN with 3 pairs).
    residual_rms_m : float
        Over the pairs used.
    suspect : ndarray of shape (N,), bool
        Pairs whose leave-one-out error exceeds the tolerance: re-measure them.
    used : ndarray of shape (N,), bool
        Pairs the transform was fitted to: all but the suspects that had to be left out for the
        others to agree (at least 4 stay in).
    tolerance_m : float
    """

    T_a_b: FloatArray
    residuals_m: FloatArray
    leave_one_out_m: FloatArray
    residual_rms_m: float
    suspect: np.ndarray
    used: np.ndarray
    tolerance_m: float

    def poor_fit(self) -> str | None:
        """Why this fit is worse than its tolerance, or None: a pair it used disagrees with the
        others by more than the tolerance, or its RMS residual exceeds it."""
        used_suspects = np.flatnonzero(self.suspect & self.used)
        if self.residual_rms_m > self.tolerance_m:
            return (
                f"the pairs agree to {self.residual_rms_m * 1e3:.2f} mm RMS, worse than the "
                f"{self.tolerance_m * 1e3:.2f} mm tolerance"
            )
        if len(used_suspects):
            pairs = ", ".join(str(i + 1) for i in used_suspects)
            return (
                f"pair(s) {pairs} disagree with the others by more than the "
                f"{self.tolerance_m * 1e3:.2f} mm tolerance and could not be left out"
            )
        return None

    def lines(self) -> list[str]:
        """A short report for a terminal."""
        used = self.residuals_m[self.used]
        out = [
            f"{len(used)} of {len(self.residuals_m)} point pairs used, residual rms "
            f"{self.residual_rms_m * 1e3:.3f} mm, max {used.max() * 1e3:.3f} mm"
        ]
        for i in np.flatnonzero(self.suspect):
            what = "used" if self.used[i] else "left out"
            out.append(
                f"pair {i + 1} ({what}): {self.leave_one_out_m[i] * 1e3:.2f} mm off the fit of "
                f"the others (tolerance {self.tolerance_m * 1e3:.2f} mm): re-measure it"
            )
        return out


#: A pair is left out of the fit when its leave-one-out error is this many times the median
#: of the others' (fitted without it) and above the tolerance: one bad touch among good ones,
#: not general noise.
OUTLIER_RATIO = 3.0


def fit_point_pairs(
    points_a_m: FloatArray, points_b_m: FloatArray, *, tolerance_m: float = 1e-3
) -> PointPairCalibration:
    """The rigid transform ``T_a_b`` with ``a_i ~ T_a_b b_i``, by least squares.

    Parameters
    ----------
    points_a_m, points_b_m : ndarray of shape (N, 3), metres
        The same N physical points in frames a (e.g. the robot base) and b (e.g. the tracker).
    tolerance_m : float
        Pairs whose leave-one-out error exceeds this are reported as suspect. The worst is left
        out of the fit, one at a time, while it exceeds the tolerance *and* stands out from the
        rest (more than ``OUTLIER_RATIO`` times the median of theirs, fitted without it):
        uniform noise near the tolerance is reported, not stripped away. At most a fifth of the
        pairs are left out, and at least 4 stay in.

    Raises
    ------
    ValueError
        Shapes, NaN, a tolerance that is not positive.
    DegenerateInputError
        Fewer than 3 pairs, or points that are (nearly) collinear in either frame, which leave
        the rotation about their line undetermined.
    """
    a = np.asarray(points_a_m, dtype=np.float64)
    b = np.asarray(points_b_m, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape != b.shape:
        raise ValueError(f"point pairs must be two (N, 3) arrays, got {a.shape} and {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("point pairs contain NaN or infinite values")
    for name, pts in (("first", a), ("second", b)):
        farthest = float(np.abs(pts).max()) if pts.size else 0.0
        if farthest > MAX_PAIR_COORDINATE_M:
            raise ValueError(
                f"a point of the {name} frame lies {farthest:.3g} m from its origin, beyond "
                f"{MAX_PAIR_COORDINATE_M:.0f} m: check the units (m or mm) of the pairs"
            )
    if not tolerance_m > 0:
        raise ValueError(f"tolerance_m must be positive, got {tolerance_m}")
    if len(a) < 3:
        raise DegenerateInputError(
            f"a rigid transform needs at least 3 non-collinear point pairs, got {len(a)}"
        )
    for name, pts in (("first", a), ("second", b)):
        spread = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
        if spread[1] / np.sqrt(len(pts)) < MIN_PAIR_SPREAD_M:
            raise DegenerateInputError(
                f"the points of the {name} frame lie (nearly) on a line: touch at least 3 "
                "points that form a wide triangle, better 4 or more spread over the work area"
            )
    # Leave-one-out errors, removing the worst pair while it breaks the tolerance: one bad
    # pair inflates every other pair's error too, so pairs are judged after it is gone.
    loo = np.full(len(a), np.nan)
    max_removed = len(a) // 5
    idx = np.arange(len(a))  # the pairs in the fit
    loo_idx = _leave_one_out_errors(a[idx], b[idx]) if len(idx) >= 4 else None
    while loo_idx is not None and len(idx) > 4 and len(a) - len(idx) < max_removed:
        at = int(np.argmax(loo_idx))
        if loo_idx[at] <= tolerance_m:
            break
        # Judge the worst against the others as they fit without it: one bad pair inflates
        # every other pair's error while it is in.
        rest = np.delete(idx, at)
        loo_rest = _leave_one_out_errors(a[rest], b[rest])
        if loo_idx[at] <= OUTLIER_RATIO * float(np.median(loo_rest)):
            break
        loo[idx[at]] = loo_idx[at]
        idx, loo_idx = rest, loo_rest
    if loo_idx is not None:
        loo[idx] = loo_idx
    inlier = np.zeros(len(a), dtype=bool)
    inlier[idx] = True
    T = _kabsch(a[inlier], b[inlier])
    residuals = _pair_errors(T, a, b)
    # Excluded pairs are judged against the final fit; with 3 pairs there is no redundancy and
    # the plain residual is all there is.
    loo[~inlier] = residuals[~inlier]
    check = np.where(np.isnan(loo), residuals, loo)
    return PointPairCalibration(
        T_a_b=T,
        residuals_m=residuals,
        leave_one_out_m=loo,
        residual_rms_m=float(np.sqrt(np.mean(residuals[inlier] ** 2))),
        suspect=(check > tolerance_m) | ~inlier,
        used=inlier,
        tolerance_m=float(tolerance_m),
    )


def _leave_one_out_errors(a: FloatArray, b: FloatArray) -> FloatArray:
    """Each pair's distance from the transform fitted to all the other pairs, shape (N,)."""
    errors = np.empty(len(a))
    for k in range(len(a)):
        others = np.arange(len(a)) != k
        T = _kabsch(a[others], b[others])
        errors[k] = _pair_errors(T, a[k : k + 1], b[k : k + 1])[0]
    return errors


def _kabsch(a: FloatArray, b: FloatArray) -> FloatArray:
    """``T_a_b`` minimising sum |R b + t - a|^2 (SciPy's align_vectors on centred points)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    rotation, _ = Rotation.align_vectors(a - ca, b - cb)
    T = np.eye(4)
    T[:3, :3] = rotation.as_matrix()
    T[:3, 3] = ca - T[:3, :3] @ cb
    return T


def _pair_errors(T: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    errors: FloatArray = np.linalg.norm(apply_transform(T, b) - a, axis=1)
    return errors
