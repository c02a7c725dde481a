"""Splitting a resampled path at sharp corners (Algorithm 1, second step).

Each segment is reconstructed on its own, so a polynomial never has to bend around a corner and
corners stay sharp.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import find_peaks

from recon.types import FloatArray


def turning_angle_deg(points_m: FloatArray, *, half_window: int) -> FloatArray:
    """Turning angle at every point, measured between chords ``half_window`` points long.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3), metres
        Equidistant path points.
    half_window : int
        Chord length in points. Chords longer than the hand tremor's wavelength keep tremor
        from looking like corners.

    Returns
    -------
    ndarray of shape (N,), degrees
        0 for a straight path, 90 at a right-angle corner; 0 within ``half_window`` of the ends,
        where no chord fits on one side.
    """
    points = np.asarray(points_m, dtype=np.float64)
    n = len(points)
    k = int(half_window)
    if k < 1:
        raise ValueError(f"half_window must be >= 1, got {half_window}")
    angle = np.zeros(n)
    if n <= 2 * k:
        return angle
    incoming = points[k:-k] - points[: -2 * k]
    outgoing = points[2 * k :] - points[k:-k]
    cos = np.einsum("ij,ij->i", incoming, outgoing) / np.maximum(
        np.linalg.norm(incoming, axis=1) * np.linalg.norm(outgoing, axis=1), 1e-300
    )
    angle[k:-k] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return angle


def find_corners(
    points_m: FloatArray, *, spacing_m: float, angle_deg: float, scale_m: float
) -> np.ndarray:
    """Indices of corners: local maxima of the turning angle above ``angle_deg``.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3), metres
        Equidistant path points.
    spacing_m : float
        Their spacing.
    angle_deg : float
        Threshold on the turning angle.
    scale_m : float
        Chord length for the turning angle; also the smallest distance between two corners.

    Returns
    -------
    ndarray of int, sorted
    """
    k = max(1, int(round(scale_m / spacing_m)))
    angle = turning_angle_deg(points_m, half_window=k)
    # Two corners closer than a chord cannot be told apart; keep the sharper one.
    peaks, _ = find_peaks(angle, height=angle_deg, distance=2 * k)
    return peaks.astype(np.int64)


def split_at(n_points: int, corners: np.ndarray) -> list[tuple[int, int]]:
    """Segments ``[start, stop)`` between corners; neighbours share the corner point.

    Parameters
    ----------
    n_points : int
    corners : ndarray of int
        Sorted corner indices, each in ``(0, n_points - 1)``.

    Returns
    -------
    list of (start, stop)
    """
    bounds = [0, *[int(c) for c in corners if 0 < c < n_points - 1], n_points - 1]
    return [(a, b + 1) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
