"""Hand-trace noise and scanner misplacement for the synthetic scenes.

Noise follows what real traces look like (paper, Sec. VI: max error 2-5 mm, std 0.5-1 mm): hand
tremor correlated over a few centimetres, plus a slow drift off the feature correlated over tens of
centimetres, plus a little white tracker noise. A local smoother removes the tremor but not the
drift; only the scan (or touches of the workpiece) can remove the drift.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import convolve1d
from scipy.spatial.transform import Rotation

from recon.arrays import FloatArray
from recon.inputs import Recording

MM = 1e-3


@dataclass(frozen=True)
class HandNoise:
    """Coloured noise of a hand trace, in metres (std per axis) and metres of arc length.

    The defaults give a 3-D error of about 1 mm on average and 2.5-3.5 mm at most, the paper's
    measured operator error (std 0.5-1 mm, max 2-5 mm). The drift's kernel of 40 mm correlates
    it over wavelengths of 15-25 cm, far beyond any reconstruction window.
    """

    tremor_sigma_m: float = 0.3 * MM
    tremor_length_m: float = 8 * MM
    drift_sigma_m: float = 0.6 * MM
    drift_length_m: float = 40 * MM
    white_sigma_m: float = 0.05 * MM


def coloured_noise(
    arc_m: FloatArray, rng: np.random.Generator, *, sigma_m: float, length_m: float
) -> FloatArray:
    """Gaussian-correlated noise along arc length, three independent axes.

    Parameters
    ----------
    arc_m : ndarray of shape (N,)
        Equally spaced arc-length samples.
    sigma_m : float
        Standard deviation per axis (over realisations).
    length_m : float
        Standard deviation of the Gaussian correlation kernel.

    Returns
    -------
    ndarray of shape (N, 3)
    """
    if sigma_m == 0:
        return np.zeros((len(arc_m), 3))
    ds = float(arc_m[1] - arc_m[0])
    sigma_samples = max(length_m / ds, 1e-6)
    half = int(np.ceil(4 * sigma_samples))
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma_samples) ** 2)
    kernel /= np.sqrt(np.sum(kernel**2))  # unit variance of the filtered white noise
    pad = len(kernel)
    white = rng.standard_normal((len(arc_m) + 2 * pad, 3))
    filtered: FloatArray = convolve1d(white, kernel, axis=0, mode="constant")[pad:-pad]
    return sigma_m * filtered


def cross_track_frame(
    points: FloatArray, up: FloatArray | None = None
) -> tuple[FloatArray, FloatArray]:
    """Two unit directions across a curve at each sample: sideways and (mostly) up.

    Parameters
    ----------
    points : ndarray of shape (N, 3)
        Densely sampled curve; without ``up``, nowhere vertical.
    up : ndarray of shape (N, 3), optional
        What "up" is at each sample (e.g. the outward bisector of the faces at an edge: the
        hand drifts off the edge across it and away from the part). World z when not given.

    Returns
    -------
    across, up : ndarrays of shape (N, 3)
    """
    tangent = np.gradient(points, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1)[:, None]
    reference = np.broadcast_to([0.0, 0.0, 1.0], points.shape) if up is None else up
    across = np.cross(tangent, reference)
    # Where "up" runs along the curve it says nothing across it: any other direction will do.
    spare = np.where(np.abs(tangent[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    degenerate = np.linalg.norm(across, axis=1) < 1e-6
    across[degenerate] = np.cross(tangent[degenerate], spare[degenerate])
    across /= np.linalg.norm(across, axis=1)[:, None]
    return across, np.cross(across, tangent)


def hand_trace(
    curve: Callable[[FloatArray], FloatArray],
    length_m: float,
    rng: np.random.Generator,
    *,
    noise: HandNoise,
    sample_spacing_m: float = 0.25 * MM,
    speed_m_s: float = 0.04,
    extra_offset: Callable[[FloatArray], FloatArray] | None = None,
    up: Callable[[FloatArray], FloatArray] | None = None,
) -> tuple[Recording, FloatArray]:
    """Trace ``curve(s)`` (arc-length parameterised) by a shaky hand.

    ``up(s)`` (shape (N,) -> (N, 3)), when given, says what is "up" across the curve at arc
    length ``s`` (see :func:`cross_track_frame`); world z otherwise.

    Returns
    -------
    recording : Recording
        Noisy samples with times (speed varies by +-20 % like a hand's).
    truth : ndarray of shape (G, 3)
        The curve sampled densely (0.05 mm), as ground truth.
    """
    s = np.arange(0.0, length_m + 1e-12, sample_spacing_m)
    ideal = curve(s)
    # The drift is off the feature: across it, in the curve's own frame. (In world axes a
    # constant drift would be a rigid shift that registration absorbs; across a curved feature
    # it is not.) Tremor shakes in every direction.
    across, up_dir = cross_track_frame(ideal, None if up is None else up(s))
    drift = coloured_noise(s, rng, sigma_m=noise.drift_sigma_m, length_m=noise.drift_length_m)
    offset = (
        coloured_noise(s, rng, sigma_m=noise.tremor_sigma_m, length_m=noise.tremor_length_m)
        + drift[:, :1] * across
        + drift[:, 1:2] * up_dir
        + noise.white_sigma_m * rng.standard_normal((len(s), 3))
    )
    if extra_offset is not None:
        offset = offset + extra_offset(s)
    speed = speed_m_s * (1.0 + 0.2 * np.sin(2 * np.pi * s / max(length_m / 3, 1e-9)))
    t = np.concatenate(([0.0], np.cumsum(np.diff(s) / speed[1:])))
    truth = curve(np.arange(0.0, length_m + 1e-12, 0.05 * MM))
    return Recording(points_m=ideal + offset, t_s=t), truth


def misalignment(rng: np.random.Generator, *, shift_m: float, angle_deg: float) -> FloatArray:
    """A rigid transform with a translation of ``shift_m`` and a rotation of ``angle_deg``.

    Returns
    -------
    ndarray of shape (4, 4)
    """
    axis = rng.standard_normal(3)
    direction = rng.standard_normal(3)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(
        np.radians(angle_deg) * axis / np.linalg.norm(axis)
    ).as_matrix()
    T[:3, 3] = shift_m * direction / np.linalg.norm(direction)
    return T
