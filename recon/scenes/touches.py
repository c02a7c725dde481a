"""Touch recordings: the pen's tip held still on several faces of a scene's workpiece.

What the operator records to register the scanner by touching (see :mod:`recon.touches`): the tip
rests for a while on each of several points, on two or three faces, and moves between them
through the air. The tracker's tip position carries white noise and the pivot calibration's error
(a fixed offset in the pen's frame, so its direction in the world changes with the pen's tilt).
:func:`touch_recording` picks the points as an operator is told to (spread over the faces);
:func:`touches_at` touches given ones (a layout to test, such as a 3-2-1 set on a box).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from recon.arrays import FloatArray
from recon.inputs import Recording
from recon.scenes.base import MM, Scene


@dataclass(frozen=True)
class Touches:
    """A touch recording with its ground truth.

    Attributes
    ----------
    recording : Recording
        Tip positions, tracker frame, with times.
    points_m : ndarray of shape (T, 3)
        Where the tip truly rested, tracker frame.
    normals : ndarray of shape (T, 3)
        The faces' outward normals there.
    faces : tuple of str
        The face of each touch.
    """

    recording: Recording
    points_m: FloatArray
    normals: FloatArray
    faces: tuple[str, ...]


def touch_recording(
    scene: Scene,
    seed: int,
    *,
    n_touches: int = 6,
    n_faces: int | None = None,
    tip_noise_m: float = 0.07 * MM,
    pivot_error_m: float = 0.1 * MM,
    dwell_s: tuple[float, float] = (0.5, 1.0),
    rate_hz: float = 120.0,
    lift_m: float = 20 * MM,
    speed_m_s: float = 0.15,
) -> Touches:
    """Touch ``n_touches`` points spread over the scene's faces (the first ``n_faces`` of them).

    Parameters
    ----------
    scene : Scene
        With ``faces``.
    seed : int
    n_touches : int
        Touches: three on the first face (it is the largest), the rest dealt to the others in
        turn.
    n_faces : int, optional
        How many of the scene's faces to touch (all by default).
    tip_noise_m : float
        Standard deviation per axis of the tracker's tip position while resting.
    pivot_error_m : float
        Length of the pivot calibration's error (tip offset in the pen's frame).
    dwell_s : (float, float)
        Range of the time the tip rests on each point.
    rate_hz : float
        Tracker rate.
    lift_m : float
        The pen leaves each point along the face's normal by this much before moving on.
    speed_m_s : float
        Speed through the air between touches.

    Returns
    -------
    Touches
    """
    faces = scene.faces[: n_faces or len(scene.faces)]
    if not faces:
        raise ValueError(f"scene {scene.name} has no faces to touch")
    rng = np.random.default_rng([seed, 104729])
    pivot_error = rng.standard_normal(3)
    pivot_error *= pivot_error_m / np.linalg.norm(pivot_error)
    # As an operator is told: three touches spread over the first (largest) face, which fix its
    # tilt, then the others in turn.
    if len(faces) == 1:
        order = [faces[0]] * n_touches
    else:
        order = [faces[0]] * min(3, n_touches)
        order += [faces[1 + k % (len(faces) - 1)] for k in range(n_touches - len(order))]
    points: list[FloatArray] = []
    normals: list[FloatArray] = []
    names: list[str] = []
    for face in order:
        # Spread out, as an operator is told to: of a few candidates, the one farthest from the
        # touches already made on this face.
        candidates, candidate_normals = face.sample(rng, 32)
        mine = [p for p, name in zip(points, names, strict=True) if name == face.name]
        if mine:
            gaps = np.linalg.norm(candidates[:, None] - np.asarray(mine)[None], axis=2).min(1)
            pick = int(np.argmax(gaps))
        else:
            pick = 0
        points.append(candidates[pick])
        normals.append(candidate_normals[pick])
        names.append(face.name)
    return _record(
        np.asarray(points),
        np.asarray(normals),
        tuple(names),
        rng,
        pivot_error=pivot_error,
        tip_noise_m=tip_noise_m,
        dwell_s=dwell_s,
        rate_hz=rate_hz,
        lift_m=lift_m,
        speed_m_s=speed_m_s,
    )


def touches_at(
    points_m: FloatArray,
    normals: FloatArray,
    seed: int,
    *,
    touch_error_m: float = 0.1 * MM,
    tip_noise_m: float = 0.07 * MM,
    dwell_s: tuple[float, float] = (0.5, 1.0),
    rate_hz: float = 120.0,
    lift_m: float = 20 * MM,
    speed_m_s: float = 0.15,
) -> Touches:
    """Touch given points (a layout an operator was told, such as a 3-2-1 set on a box).

    Parameters
    ----------
    points_m : ndarray of shape (T, 3)
        Where the tip is meant to rest, tracker frame, on the workpiece's faces.
    normals : ndarray of shape (T, 3)
        The faces' outward normals there (the pen comes and goes along them).
    seed : int
    touch_error_m : float
        Standard deviation per axis of each rest's error (the pivot calibration, the tip's seat):
        one draw per touch, which no averaging over the rest removes.
    tip_noise_m : float
        Standard deviation per axis of the tracker's tip position while resting.
    dwell_s, rate_hz, lift_m, speed_m_s
        As :func:`touch_recording`'s.

    Returns
    -------
    Touches
        ``points_m`` are the points as given; the recording rests off them by the touch error.
    """
    points = np.asarray(points_m, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError("points_m and normals must both have shape (T, 3)")
    rng = np.random.default_rng([seed, 7919])
    errors = touch_error_m * rng.standard_normal(points.shape)
    return _record(
        points,
        normals,
        ("given",) * len(points),
        rng,
        rest_error=errors,
        tip_noise_m=tip_noise_m,
        dwell_s=dwell_s,
        rate_hz=rate_hz,
        lift_m=lift_m,
        speed_m_s=speed_m_s,
    )


def _record(
    points: FloatArray,
    normals: FloatArray,
    names: tuple[str, ...],
    rng: np.random.Generator,
    *,
    pivot_error: FloatArray | None = None,
    rest_error: FloatArray | None = None,
    tip_noise_m: float,
    dwell_s: tuple[float, float],
    rate_hz: float,
    lift_m: float,
    speed_m_s: float,
) -> Touches:
    """Rest on each point in turn (off it by the pivot error turned with the pen, or by
    ``rest_error``), moving between them through the air."""
    dt = 1.0 / rate_hz
    samples: list[FloatArray] = []
    for k, (p, n) in enumerate(zip(points, normals, strict=True)):
        if rest_error is None:
            # The pen leans 10-30 degrees off the face's normal, about a random horizontal axis.
            tilt = Rotation.from_rotvec(
                np.radians(rng.uniform(10, 30)) * _unit(np.cross(n, rng.standard_normal(3)))
            )
            rest = p + tilt.apply(pivot_error)
        else:
            rest = p + rest_error[k]
        count = int(rng.uniform(*dwell_s) * rate_hz)
        samples.append(rest + tip_noise_m * rng.standard_normal((count, 3)))
        if k + 1 < len(points):
            samples.append(_move(rest, n, points[k + 1], normals[k + 1], lift_m, speed_m_s * dt))
    positions = np.concatenate(samples)
    return Touches(
        recording=Recording(
            points_m=positions, t_s=np.arange(len(positions), dtype=np.float64) * dt
        ),
        points_m=np.asarray(points),
        normals=np.asarray(normals),
        faces=tuple(names),
    )


def _unit(v: FloatArray) -> FloatArray:
    return v / np.linalg.norm(v)


def _move(
    a: FloatArray,
    normal_a: FloatArray,
    b: FloatArray,
    normal_b: FloatArray,
    lift_m: float,
    step_m: float,
) -> FloatArray:
    """Up from ``a`` along its normal, across, down onto ``b`` along its normal (excluding both
    ends), in steps of about ``step_m``."""
    waypoints = [a, a + lift_m * normal_a, b + lift_m * normal_b, b]
    out = []
    for p, q in itertools.pairwise(waypoints):
        n = max(2, int(np.ceil(np.linalg.norm(q - p) / step_m)))
        # Smooth in and out of each leg (a hand slows down where it turns).
        u = 0.5 - 0.5 * np.cos(np.pi * np.linspace(0.0, 1.0, n, endpoint=False)[1:])
        out.append(p + u[:, None] * (q - p))
    return np.concatenate(out)
