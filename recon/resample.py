"""Resampling of a traced path to equidistant points (Algorithm 1, first step)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from recon.arrays import FloatArray
from recon.errors import DegenerateInputError


@dataclass(frozen=True)
class ResampledPath:
    """A path resampled at equal arc-length steps.

    Attributes
    ----------
    points_m : ndarray of shape (N, 3), metres
    arc_length_m : ndarray of shape (N,), metres
        Arc length of each point from the start of the path.
    spacing_m : float
        The actual step (at most the requested one; chosen so the last point is the path's end).
    t_s : ndarray of shape (N,), seconds, or None
        Sample times interpolated along the arc length.
    orientations_xyzw : ndarray of shape (N, 4), or None
        Pen orientations interpolated along the arc length (spherical linear interpolation),
        scalar-last quaternions.
    n_duplicates : int
        Input samples dropped because they repeated the previous position.
    """

    points_m: FloatArray
    arc_length_m: FloatArray
    spacing_m: float
    t_s: FloatArray | None
    n_duplicates: int
    orientations_xyzw: FloatArray | None = None


def resample_equidistant(
    points_m: FloatArray,
    *,
    spacing_m: float,
    t_s: FloatArray | None = None,
    orientations_xyzw: FloatArray | None = None,
) -> ResampledPath:
    """Resample a polyline at equal arc-length steps, dropping repeated samples first.

    The step is ``L / ceil(L / spacing_m)``, at most ``spacing_m``, so the first and last points
    of the input are kept exactly. Interpolation is linear along the polyline: a tracker samples
    far denser than the millimetre spacing used here, so nothing is gained by a spline, and a
    spline would overshoot at corners.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3), metres
    spacing_m : float
        Requested distance between points.
    t_s : ndarray of shape (N,), seconds, optional
    orientations_xyzw : ndarray of shape (N, 4), optional
        Unit quaternions, scalar last.

    Returns
    -------
    ResampledPath

    Raises
    ------
    ValueError
        Bad shapes or a non-positive spacing.
    DegenerateInputError
        Fewer than two distinct positions, or a path shorter than two steps.
    """
    points = np.asarray(points_m, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points_m must have shape (N, 3), got {points.shape}")
    if not spacing_m > 0:
        raise ValueError(f"spacing_m must be positive, got {spacing_m}")
    times = None if t_s is None else np.asarray(t_s, dtype=np.float64)
    if times is not None and times.shape != (len(points),):
        raise ValueError(f"t_s must have shape ({len(points)},), got {times.shape}")
    quats = None if orientations_xyzw is None else np.asarray(orientations_xyzw, np.float64)
    if quats is not None and quats.shape != (len(points), 4):
        raise ValueError(f"orientations_xyzw must have shape ({len(points)}, 4), got {quats.shape}")

    step = np.linalg.norm(np.diff(points, axis=0), axis=1)
    # A sample that does not move (the pen resting, or a repeated tracker frame) adds no geometry;
    # keeping it would make arc length non-increasing and the interpolation ill-defined.
    moved = np.concatenate(([True], step > 1e-9))
    n_duplicates = int(np.count_nonzero(~moved))
    points = points[moved]
    times = None if times is None else times[moved]
    quats = None if quats is None else quats[moved]
    if len(points) < 2:
        raise DegenerateInputError(
            "the path has fewer than two distinct positions; record a longer trace"
        )

    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))))
    length = float(arc[-1])
    n_steps = int(np.ceil(length / spacing_m - 1e-9))
    if n_steps < 2:
        raise DegenerateInputError(
            f"the path is {length * 1000:.2f} mm long, shorter than two resampling steps of "
            f"{spacing_m * 1000:.2f} mm; record a longer trace or reduce the spacing"
        )
    s_new = np.linspace(0.0, length, n_steps + 1)
    resampled = np.column_stack([np.interp(s_new, arc, points[:, k]) for k in range(3)])
    t_new = None if times is None else np.interp(s_new, arc, times)
    q_new = None
    if quats is not None:
        q_new = Slerp(arc, Rotation.from_quat(quats))(np.clip(s_new, arc[0], arc[-1])).as_quat()
    return ResampledPath(
        points_m=resampled,
        arc_length_m=s_new,
        spacing_m=length / n_steps,
        t_s=t_new,
        n_duplicates=n_duplicates,
        orientations_xyzw=q_new,
    )
