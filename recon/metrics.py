"""Accuracy measures against ground truth, and the baselines the method is compared with."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import savgol_filter
from scipy.spatial import cKDTree

from recon.arrays import FloatArray
from recon.resample import resample_equidistant

#: Ground-truth curves are densified to this spacing before nearest-point queries, which bounds
#: the distance error of the polyline approximation at (spacing / 2)^2 / (2 R), far below 1 um.
TRUTH_SPACING_M = 2e-5


@dataclass(frozen=True)
class ErrorStats:
    """Distances of a path's points to the ground-truth curve, metres."""

    mean_m: float
    max_m: float
    rms_m: float
    p95_m: float
    n: int

    def ratio_to(self, reference: ErrorStats) -> float:
        """Mean-error ratio e / e_ref (the paper reports 13.0 / 21.9 = 0.59)."""
        return self.mean_m / reference.mean_m


def distance_to_curve(points_m: FloatArray, truth_m: FloatArray) -> FloatArray:
    """Distance of each point to the polyline ``truth_m`` (cross-track error).

    The paper's error (Eq. 5) pairs points of equal index, which needs the same sampling on both
    sides; the reconstruction resamples the path, so the error of a point is measured as its
    distance to the true curve instead, which is also what matters to the robot.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3)
    truth_m : ndarray of shape (G, 3)
        The true curve, ordered.

    Returns
    -------
    ndarray of shape (N,), metres
    """
    dense = resample_equidistant(truth_m, spacing_m=TRUTH_SPACING_M).points_m
    distance: FloatArray
    distance, _ = cKDTree(dense).query(points_m, workers=-1)
    return distance


def error_stats(points_m: FloatArray, truth_m: FloatArray) -> ErrorStats:
    """Mean, max, RMS and 95th percentile of :func:`distance_to_curve`."""
    d = distance_to_curve(points_m, truth_m)
    return ErrorStats(
        mean_m=float(d.mean()),
        max_m=float(d.max()),
        rms_m=float(np.sqrt(np.mean(d**2))),
        p95_m=float(np.percentile(d, 95)),
        n=len(d),
    )


#: The stretch at each end of a path whose errors are reported apart (where a tool meets the
#: workpiece first and leaves it last).
END_STRETCH_M = 0.010


@dataclass(frozen=True)
class PathScore:
    """Errors of a path against ground truth, with its two ends apart, metres.

    Attributes
    ----------
    mean_m, p99_m, max_m : float
        Over every point.
    start_max_m, end_max_m : float
        Largest error of the points whose nearest true point lies within :data:`END_STRETCH_M` of
        the start (end) of the true curve; NaN when none does.
    """

    mean_m: float
    p99_m: float
    max_m: float
    start_max_m: float
    end_max_m: float

    @property
    def ends_max_m(self) -> float:
        """The larger of the two ends' maxima."""
        return float(np.nanmax([self.start_max_m, self.end_max_m]))


def score_path(
    points_m: FloatArray,
    truth_m: FloatArray,
    *,
    ends_m: float = END_STRETCH_M,
    extend_ends_m: float = 0.0,
) -> PathScore:
    """:class:`PathScore` of ``points_m`` against the true curve ``truth_m`` (both ordered).

    A point beyond an end of the true curve is as far off as it is from that end: a tool that
    runs on past where the feature ends has an error there too. (Unless ``extend_ends_m``.)

    Parameters
    ----------
    points_m : ndarray of shape (N, 3)
    truth_m : ndarray of shape (G, 3)
    ends_m : float
        Length of each end's stretch, along the true curve.
    extend_ends_m : float
        Run the true curve on straight past both ends by this much first: errors across the
        path only. For the registered frame, where the truth's ends move along the path with
        whatever the registration could not fix (sliding along a straight edge).

    Returns
    -------
    PathScore
    """
    dense = resample_equidistant(truth_m, spacing_m=TRUTH_SPACING_M)
    length = dense.arc_length_m[-1]
    points, arcs = dense.points_m, dense.arc_length_m
    if extend_ends_m > 0:
        steps = np.arange(1, int(extend_ends_m / TRUTH_SPACING_M) + 1) * TRUTH_SPACING_M
        head = points[1] - points[0]
        tail = points[-1] - points[-2]
        head, tail = head / np.linalg.norm(head), tail / np.linalg.norm(tail)
        points = np.concatenate(
            [points[0] - np.outer(steps[::-1], head), points, points[-1] + np.outer(steps, tail)]
        )
        arcs = np.concatenate([-steps[::-1], arcs, length + steps])
    distance, index = cKDTree(points).query(points_m, workers=-1)
    arc = arcs[index]

    def end_max(mask: NDArray[np.bool_]) -> float:
        return float(distance[mask].max()) if np.any(mask) else float("nan")

    return PathScore(
        mean_m=float(distance.mean()),
        p99_m=float(np.percentile(distance, 99)),
        max_m=float(distance.max()),
        start_max_m=end_max(arc <= ends_m),
        end_max_m=end_max(arc >= length - ends_m),
    )


def savitzky_golay(points_m: FloatArray, *, window_points: int, order: int = 2) -> FloatArray:
    """Per-axis Savitzky-Golay smoothing of an equidistant path (the classic baseline).

    Parameters
    ----------
    points_m : ndarray of shape (N, 3)
    window_points : int
        Odd window length, at most N.
    order : int
    """
    window = min(window_points, len(points_m) - (1 - len(points_m) % 2))
    smoothed: FloatArray = savgol_filter(
        points_m, window_length=window, polyorder=order, axis=0, mode="interp"
    )
    return smoothed


@dataclass(frozen=True)
class SavgolResult:
    """The best Savitzky-Golay filter found: its error, window, order and output."""

    stats: ErrorStats
    window_m: float
    order: int
    points_m: FloatArray


def best_savitzky_golay(
    points_m: FloatArray,
    truth_m: FloatArray,
    *,
    spacing_m: float,
    windows_m: tuple[float, ...] = (0.004, 0.008, 0.016, 0.032, 0.064, 0.128),
    orders: tuple[int, ...] = (2, 3),
) -> SavgolResult:
    """The best per-axis Savitzky-Golay filter in hindsight (window and order chosen with the
    ground truth), on the path resampled at ``spacing_m``: a baseline no real user could beat.

    Raises
    ------
    ValueError
        The path is shorter than every window.
    """
    resampled = resample_equidistant(points_m, spacing_m=spacing_m).points_m
    best = None
    for window_m in windows_m:
        window = 2 * int(round(window_m / spacing_m / 2)) + 1
        for order in orders:
            if window <= order or window > len(resampled):
                continue
            smoothed = savitzky_golay(resampled, window_points=window, order=order)
            stats = error_stats(smoothed, truth_m)
            if best is None or stats.mean_m < best.stats.mean_m:
                best = SavgolResult(stats, window_m, order, smoothed)
    if best is None:
        raise ValueError("the path is too short for any of the Savitzky-Golay windows")
    return best
