"""What every synthetic scene is made of: the scene itself, the faces a pen can touch, and the
scan's noise model."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from recon.arrays import FloatArray
from recon.inputs import Recording, Scan
from recon.scenes.noise import HandNoise, hand_trace
from recon.transforms import apply_transform

MM = 1e-3

#: ``curve(s)``: points of the true feature at arc lengths ``s`` (shape (N,) -> (N, 3), metres).
Curve = Callable[[FloatArray], FloatArray]


@dataclass(frozen=True)
class Face:
    """A face of the workpiece a pen tip can rest on, tracker frame.

    Attributes
    ----------
    name : str
    sample : callable
        ``sample(rng, n)`` -> ``(points, normals)``, each of shape (n, 3): points spread over the
        face (kept a few millimetres inside its borders) and the outward unit normals there.
    """

    name: str
    sample: Callable[[np.random.Generator, int], tuple[FloatArray, FloatArray]]


@dataclass(frozen=True)
class Scene:
    """A test case with ground truth.

    Attributes
    ----------
    name : str
    description : str
    truth_m : ndarray of shape (G, 3)
        The feature the operator meant to trace, densely sampled, tracker frame.
    recording : Recording
        The noisy trace, tracker frame.
    scan : Scan or None
        The workpiece scan in the scan frame.
    T_scan_tracker : ndarray of shape (4, 4)
        The true transform from tracker to scan frame (the misalignment to be recovered).
    feature : {"edge", "surface", "none"}
        What the scan defines along the path.
    surface_height : callable or None
        Height of a point above the true surface (tracker frame), for surface scenes.
    curve : callable or None
        The true feature by arc length (see :data:`Curve`), for more traces of it.
    length_m : float
        Arc length of the feature.
    noise : HandNoise
        The hand noise the trace was made with.
    extra_offset : callable or None
        A deliberate departure of the trace (a lift-off) by arc length, (N,) -> (N, 3).
    faces : tuple of Face
        Faces of the workpiece that can be touched to register the scanner.
    corners_m : ndarray of shape (C, 3)
        The true corners along the feature, tracker frame (empty for smooth features).
    in_plane : callable or None
        For surface scenes: points (N, 3) -> their coordinates in the surface's plane (N, 3,
        height zeroed), to score the position the scan does not define.
    """

    name: str
    description: str
    truth_m: FloatArray
    recording: Recording
    scan: Scan | None
    T_scan_tracker: FloatArray
    feature: str
    surface_height: Callable[[FloatArray], FloatArray] | None = None
    curve: Curve | None = None
    length_m: float = 0.0
    noise: HandNoise = HandNoise()
    extra_offset: Callable[[FloatArray], FloatArray] | None = None
    faces: tuple[Face, ...] = ()
    corners_m: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    in_plane: Callable[[FloatArray], FloatArray] | None = None

    def traces(self, n: int, seed: int) -> list[Recording]:
        """``n`` more traces of the same feature with independent noise, every other one traced
        in the opposite direction (operators do not always start at the same end).

        Parameters
        ----------
        n : int
        seed : int
            The traces are a deterministic function of it (and of nothing else).

        Returns
        -------
        list of Recording
        """
        if self.curve is None:
            raise ValueError(f"scene {self.name} has no curve to trace again")
        out = []
        for k in range(n):
            rng = np.random.default_rng([seed, 7919, k])
            recording, _ = hand_trace(
                self.curve, self.length_m, rng, noise=self.noise, extra_offset=self.extra_offset
            )
            if k % 2 == 1:
                t_s = recording.t_s
                recording = Recording(
                    points_m=recording.points_m[::-1].copy(),
                    t_s=None if t_s is None else t_s[-1] - t_s[::-1],
                )
            out.append(recording)
        return out


def scan_from_surface(
    points: FloatArray,
    normals: FloatArray,
    rng: np.random.Generator,
    *,
    sigma_m: float,
    outlier_fraction: float,
    T_scan_tracker: FloatArray,
) -> Scan:
    """Noise along the normals (how depth noise looks on a face-on surface), a few outliers."""
    noisy = points + normals * (sigma_m * rng.standard_normal(len(points)))[:, None]
    n_out = int(outlier_fraction * len(points))
    if n_out:
        lo, hi = points.min(axis=0) - 0.01, points.max(axis=0) + 0.01
        noisy = np.concatenate([noisy, rng.uniform(lo, hi, size=(n_out, 3))])
    return Scan(points_m=apply_transform(T_scan_tracker, noisy))


def sample_count(area_m2: float, density_per_mm2: float) -> int:
    """Points for a face of ``area_m2`` at ``density_per_mm2`` (at least 10)."""
    return max(int(area_m2 / MM**2 * density_per_mm2), 10)


def interpolated_curve(polyline_m: FloatArray) -> tuple[Curve, float]:
    """An arc-length parameterised curve through a dense polyline, and its length.

    Parameters
    ----------
    polyline_m : ndarray of shape (K, 3)
        Densely sampled (the curve is linear between samples).
    """
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(polyline_m, axis=0), axis=1))))

    def curve(s: FloatArray) -> FloatArray:
        return np.column_stack([np.interp(s, arc, polyline_m[:, k]) for k in range(3)])

    return curve, float(arc[-1])
