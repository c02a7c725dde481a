"""Synthetic scenes with known ground truth: the paper's test cases and a few of our own.

Each scene holds the true feature curve, a noisy hand trace of it in the tracker frame and,
where the case has one, a noisy scan of the workpiece in a slightly misplaced scan frame.

Noise follows what real traces look like (paper, Sec. VI: max error 2-5 mm, std 0.5-1 mm): hand
tremor correlated over a few centimetres, plus a slow drift off the feature correlated over tens of
centimetres, plus a little white tracker noise. A local smoother removes the tremor but not the
drift; only the scan can remove the drift.

Used by the tests, the benchmarks and the demo; deterministic for a given seed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import convolve1d
from scipy.spatial.transform import Rotation

from recon.transforms import apply_transform
from recon.types import FloatArray, Recording, Scan

MM = 1e-3


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
    """

    name: str
    description: str
    truth_m: FloatArray
    recording: Recording
    scan: Scan | None
    T_scan_tracker: FloatArray
    feature: str
    surface_height: Callable[[FloatArray], FloatArray] | None = None


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
    return sigma_m * convolve1d(white, kernel, axis=0, mode="constant")[pad:-pad]


def _cross_track_frame(points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit directions across a curve at each sample: horizontal and (mostly) vertical.

    Parameters
    ----------
    points : ndarray of shape (N, 3)
        Densely sampled curve that is nowhere vertical.

    Returns
    -------
    across, up : ndarrays of shape (N, 3)
    """
    tangent = np.gradient(points, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1)[:, None]
    across = np.cross(tangent, [0.0, 0.0, 1.0])
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
) -> tuple[Recording, FloatArray]:
    """Trace ``curve(s)`` (arc-length parameterised) by a shaky hand.

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
    across, up = _cross_track_frame(ideal)
    drift = coloured_noise(s, rng, sigma_m=noise.drift_sigma_m, length_m=noise.drift_length_m)
    offset = (
        coloured_noise(s, rng, sigma_m=noise.tremor_sigma_m, length_m=noise.tremor_length_m)
        + drift[:, :1] * across
        + drift[:, 1:2] * up
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


def _scan_from_surface(
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


def _sample_count(area_m2: float, density_per_mm2: float) -> int:
    return max(int(area_m2 / MM**2 * density_per_mm2), 10)


def cylinder_edge(
    seed: int = 0,
    *,
    radius_m: float = 50 * MM,
    height_m: float = 30 * MM,
    sweep_deg: float = 340.0,
    scan_noise_fraction: float = 0.02,
    scan_density_per_mm2: float = 1.0,
    noise: HandNoise | None = None,
    shift_m: float = 3 * MM,
    angle_deg: float = 1.0,
) -> Scene:
    """The paper's Fig. 4: a path along the circular top edge of a cylinder.

    The scan's noise is ``scan_noise_fraction`` of the model scale (the radius): 2 % of 50 mm is
    1 mm, the Kinect-class noise of the paper. The scan is misplaced by ``shift_m`` and
    ``angle_deg``.
    """
    rng = np.random.default_rng(seed)
    noise = noise or HandNoise()
    R, H = radius_m, height_m
    length = np.radians(sweep_deg) * R

    def curve(s):
        a = s / R
        return np.column_stack([R * np.cos(a), R * np.sin(a), np.full_like(a, H)])

    recording, truth = hand_trace(curve, length, rng, noise=noise)
    n_top = _sample_count(np.pi * R**2, scan_density_per_mm2)
    r = R * np.sqrt(rng.uniform(0, 1, n_top))
    a = rng.uniform(0, 2 * np.pi, n_top)
    top = np.column_stack([r * np.cos(a), r * np.sin(a), np.full(n_top, H)])
    n_side = _sample_count(2 * np.pi * R * H, scan_density_per_mm2)
    a = rng.uniform(0, 2 * np.pi, n_side)
    side = np.column_stack([R * np.cos(a), R * np.sin(a), rng.uniform(0, H, n_side)])
    side_normals = np.column_stack([np.cos(a), np.sin(a), np.zeros(n_side)])
    T = misalignment(rng, shift_m=shift_m, angle_deg=angle_deg)
    scan = _scan_from_surface(
        np.concatenate([top, side]),
        np.concatenate([np.tile([0.0, 0.0, 1.0], (n_top, 1)), side_normals]),
        rng,
        sigma_m=scan_noise_fraction * R,
        outlier_fraction=0.005,
        T_scan_tracker=T,
    )
    return Scene(
        name="cylinder_edge",
        description=f"Fig. 4: circular edge of a cylinder (R {R / MM:.0f} mm), scan noise "
        f"{scan_noise_fraction * 100:.0f} % of R, "
        f"scan off by {shift_m / MM:.1f} mm / {angle_deg:g} deg",
        truth_m=truth,
        recording=recording,
        scan=scan,
        T_scan_tracker=T,
        feature="edge",
    )


def polynomial_ridge(
    seed: int = 0,
    *,
    path_noise_scale: float = 1.0,
    scan_noise_m: float = 0.5 * MM,
    curvature_per_m: float = 1.0 / (150 * MM),
    half_length_m: float = 60 * MM,
    shift_m: float = 2 * MM,
    angle_deg: float = 0.5,
) -> Scene:
    """The paper's Fig. 6: a feature shaped by a second-order polynomial, of varying quality.

    A ridge (two 45-degree faces) whose crest follows ``y = c x^2 / 2`` in the plane z = 0;
    the path traces the crest. ``path_noise_scale`` scales the default hand noise and
    ``scan_noise_m`` sets the scan's noise, so the case can be run at several qualities.
    """
    rng = np.random.default_rng(seed)
    c = curvature_per_m
    xs = np.linspace(-half_length_m, half_length_m, 20001)
    crest = np.column_stack([xs, 0.5 * c * xs**2, np.zeros_like(xs)])
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(crest, axis=0), axis=1))))

    def curve(s):
        return np.column_stack([np.interp(s, arc, crest[:, k]) for k in range(3)])

    base = HandNoise()
    noise = HandNoise(
        tremor_sigma_m=base.tremor_sigma_m * path_noise_scale,
        tremor_length_m=base.tremor_length_m,
        drift_sigma_m=base.drift_sigma_m * path_noise_scale,
        drift_length_m=base.drift_length_m,
        white_sigma_m=base.white_sigma_m,
    )
    recording, truth = hand_trace(curve, float(arc[-1]), rng, noise=noise)
    width = 20 * MM
    n = _sample_count((2 * half_length_m + 20 * MM) * 2 * width * np.sqrt(2), 1.0)
    x = rng.uniform(-half_length_m - 10 * MM, half_length_m + 10 * MM, n)
    d = rng.uniform(-width, width, n)  # offset across the crest, in y
    pts = np.column_stack([x, 0.5 * c * x**2 + d, -np.abs(d)])
    # Face normals of z = -|y - c x^2 / 2|: gradient (c x sgn, -sgn, -1) up to sign.
    sgn = np.sign(d)
    normals = np.column_stack([c * x * sgn, -sgn, -np.ones(n)])
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    T = misalignment(rng, shift_m=shift_m, angle_deg=angle_deg)
    scan = _scan_from_surface(
        pts, normals, rng, sigma_m=scan_noise_m, outlier_fraction=0.002, T_scan_tracker=T
    )
    return Scene(
        name="polynomial_ridge",
        description=f"Fig. 6: ridge along a parabola; path noise x{path_noise_scale:g}, "
        f"scan noise {scan_noise_m / MM:.1f} mm",
        truth_m=truth,
        recording=recording,
        scan=scan,
        T_scan_tracker=T,
        feature="edge",
    )


def flat_liftoff(
    seed: int = 0,
    *,
    lift_m: float = 6 * MM,
    lift_width_m: float = 12 * MM,
    scan_noise_m: float = 0.5 * MM,
    shift_m: float = 2 * MM,
    angle_deg: float = 0.5,
) -> Scene:
    """The paper's Fig. 7: a path on a flat plate; mid-way the trace lifts off by ``lift_m``.

    The plate is z = 0 in the tracker frame; the scan's noise is depth-camera-like, correlated
    over centimetres plus white, 0.5 mm in all by default (a close-range RealSense-class camera;
    the paper's Kinect had about 1 mm, which caps how flat any reconstruction can be).
    """
    rng = np.random.default_rng(seed)
    half = 80 * MM

    xs = np.linspace(-half, half, 20001)
    line = np.column_stack([xs, 10 * MM * np.sin(xs / (40 * MM)), np.zeros_like(xs)])
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))))
    length = float(arc[-1])

    def curve(s):
        return np.column_stack([np.interp(s, arc, line[:, k]) for k in range(3)])

    def lift(s):
        bump = lift_m * np.exp(-0.5 * ((s - 0.55 * length) / lift_width_m) ** 2)
        return np.column_stack([np.zeros_like(s), np.zeros_like(s), bump])

    recording, truth = hand_trace(curve, length, rng, noise=HandNoise(), extra_offset=lift)
    n = _sample_count(200 * MM * 80 * MM, 1.0)
    pts = np.column_stack(
        [rng.uniform(-100 * MM, 100 * MM, n), rng.uniform(-40 * MM, 40 * MM, n), np.zeros(n)]
    )
    # Depth-camera noise is spatially correlated: a smooth field plus white noise.
    k = rng.standard_normal((6, 3))
    field = sum(
        np.sin(pts[:, 0] * k[i, 0] / (4 * MM) + pts[:, 1] * k[i, 1] / (4 * MM) + k[i, 2])
        for i in range(6)
    ) / np.sqrt(3.0)
    noisy = pts.copy()
    noisy[:, 2] += scan_noise_m * (0.6 * field + 0.8 * rng.standard_normal(n))
    T = misalignment(rng, shift_m=shift_m, angle_deg=angle_deg)
    scan = Scan(points_m=apply_transform(T, noisy))
    return Scene(
        name="flat_liftoff",
        description=f"Fig. 7: flat plate, trace lifts off by {lift_m / MM:.0f} mm mid-way, "
        f"scan noise {scan_noise_m / MM:.1f} mm",
        truth_m=truth,
        recording=recording,
        scan=scan,
        T_scan_tracker=T,
        feature="surface",
        surface_height=lambda p: p[:, 2],
    )


def free_curve(seed: int = 0) -> Scene:
    """The paper's Fig. 8: a curved path with no surface at all (path-only reconstruction)."""
    rng = np.random.default_rng(seed)
    xs = np.linspace(0, 1, 20001)
    ang = 2.2 * np.pi * xs
    line = np.column_stack(
        [60 * MM * np.cos(ang), 40 * MM * np.sin(ang), 25 * MM * np.sin(0.5 * ang)]
    )
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))))

    def curve(s):
        return np.column_stack([np.interp(s, arc, line[:, k]) for k in range(3)])

    recording, truth = hand_trace(curve, float(arc[-1]), rng, noise=HandNoise())
    return Scene(
        name="free_curve",
        description="Fig. 8: a 3-D curve traced in the air, no scan",
        truth_m=truth,
        recording=recording,
        scan=None,
        T_scan_tracker=np.eye(4),
        feature="none",
    )


def box_corner(
    seed: int = 0,
    *,
    scan_noise_m: float = 0.5 * MM,
    shift_m: float = 2 * MM,
    angle_deg: float = 0.5,
) -> Scene:
    """A path along two top edges of a box, around a 90-degree corner.

    The box spans x in [0, 100] mm, y in [0, 80] mm, z in [-40, 0] mm; the path runs along y = 0
    from x = 20 mm to the corner at (100, 0, 0) mm and then along x = 100 mm to y = 60 mm.
    """
    rng = np.random.default_rng(seed)
    corner = np.array([100 * MM, 0.0, 0.0])
    leg_a, leg_b = 80 * MM, 60 * MM

    def curve(s):
        s = np.asarray(s)
        first = corner + np.outer(np.minimum(s, leg_a) - leg_a, [1.0, 0.0, 0.0])
        second = np.outer(np.clip(s - leg_a, 0.0, None), [0.0, 1.0, 0.0])
        return first + second

    recording, truth = hand_trace(curve, leg_a + leg_b, rng, noise=HandNoise())
    X, Y, Z = 100 * MM, 80 * MM, 40 * MM
    n_top, n_front, n_right = (_sample_count(a, 1.0) for a in (X * Y, X * Z, Y * Z))
    top = np.column_stack([rng.uniform(0, X, n_top), rng.uniform(0, Y, n_top), np.zeros(n_top)])
    front = np.column_stack(
        [rng.uniform(0, X, n_front), np.zeros(n_front), rng.uniform(-Z, 0, n_front)]
    )
    right = np.column_stack(
        [np.full(n_right, X), rng.uniform(0, Y, n_right), rng.uniform(-Z, 0, n_right)]
    )
    normals = np.concatenate(
        [
            np.tile([0.0, 0.0, 1.0], (n_top, 1)),
            np.tile([0.0, -1.0, 0.0], (n_front, 1)),
            np.tile([1.0, 0.0, 0.0], (n_right, 1)),
        ]
    )
    T = misalignment(rng, shift_m=shift_m, angle_deg=angle_deg)
    scan = _scan_from_surface(
        np.concatenate([top, front, right]),
        normals,
        rng,
        sigma_m=scan_noise_m,
        outlier_fraction=0.003,
        T_scan_tracker=T,
    )
    return Scene(
        name="box_corner",
        description="a path around a 90-degree box corner along two top edges",
        truth_m=truth,
        recording=recording,
        scan=scan,
        T_scan_tracker=T,
        feature="edge",
    )


def long_edge(
    n_path_points: int,
    n_scan_points: int,
    seed: int = 0,
    *,
    spacing_m: float = 1 * MM,
    scan_noise_m: float = 0.5 * MM,
) -> Scene:
    """A long step edge wound into a spiral, for timing.

    The edge is ``n_path_points * spacing_m`` long on an Archimedean spiral with 80 mm between
    turns (so 100 m of edge fit in about 3 m), with a 30 mm wide top face outside it and a 30 mm
    high wall below it; ``n_scan_points`` are spread over both.
    """
    rng = np.random.default_rng(seed)
    length = n_path_points * spacing_m
    pitch, r0 = 80 * MM, 0.3
    # Arc length of r = r0 + b theta is about the integral of r dtheta for a tight pitch.
    b = pitch / (2 * np.pi)
    theta_end = (np.sqrt(r0**2 + 2 * b * length) - r0) / b
    theta = np.linspace(0.0, theta_end * 1.02, max(200_001, 8 * n_path_points))
    radius = r0 + b * theta
    line = np.column_stack([radius * np.cos(theta), radius * np.sin(theta), np.zeros_like(theta)])
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))))

    def curve(s):
        return np.column_stack([np.interp(s, arc, line[:, k]) for k in range(3)])

    recording, truth = hand_trace(
        curve, length, rng, noise=HandNoise(), sample_spacing_m=spacing_m / 2
    )
    half = n_scan_points // 2
    top_s = rng.uniform(0, length, half)
    wall_s = rng.uniform(0, length, n_scan_points - half)
    top_theta, wall_theta = np.interp(top_s, arc, theta), np.interp(wall_s, arc, theta)
    outward = rng.uniform(0, 30 * MM, half)
    top_r = r0 + b * top_theta + outward
    top = np.column_stack([top_r * np.cos(top_theta), top_r * np.sin(top_theta), np.zeros(half)])
    wall_r = r0 + b * wall_theta
    wall = np.column_stack(
        [
            wall_r * np.cos(wall_theta),
            wall_r * np.sin(wall_theta),
            rng.uniform(-30 * MM, 0, len(wall_s)),
        ]
    )
    pts = np.concatenate([top, wall])
    pts += scan_noise_m * rng.standard_normal(pts.shape)
    return Scene(
        name=f"long_edge_{n_path_points}",
        description=f"{length:.0f} m spiral step edge, {n_scan_points} scan points",
        truth_m=truth,
        recording=recording,
        scan=Scan(points_m=pts),
        T_scan_tracker=np.eye(4),
        feature="edge",
    )


#: The accuracy scenes, by name, with their default arguments.
SCENES: dict[str, Callable[..., Scene]] = {
    "cylinder_edge": cylinder_edge,
    "polynomial_ridge": polynomial_ridge,
    "flat_liftoff": flat_liftoff,
    "free_curve": free_curve,
    "box_corner": box_corner,
}
