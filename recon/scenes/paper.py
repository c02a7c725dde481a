"""The paper's test cases (Figs. 4, 6, 7 and 8), a box corner, and long paths for timing."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from recon.arrays import FloatArray
from recon.inputs import Scan
from recon.scenes.base import (
    MM,
    Face,
    Scene,
    sample_count,
    scan_from_surface,
)
from recon.scenes.noise import HandNoise, hand_trace, misalignment
from recon.transforms import apply_transform


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

    def curve(s: FloatArray) -> FloatArray:
        a = s / R
        return np.column_stack([R * np.cos(a), R * np.sin(a), np.full_like(a, H)])

    recording, truth = hand_trace(curve, length, rng, noise=noise)
    n_top = sample_count(np.pi * R**2, scan_density_per_mm2)
    r = R * np.sqrt(rng.uniform(0, 1, n_top))
    a = rng.uniform(0, 2 * np.pi, n_top)
    top = np.column_stack([r * np.cos(a), r * np.sin(a), np.full(n_top, H)])
    n_side = sample_count(2 * np.pi * R * H, scan_density_per_mm2)
    a = rng.uniform(0, 2 * np.pi, n_side)
    side = np.column_stack([R * np.cos(a), R * np.sin(a), rng.uniform(0, H, n_side)])
    side_normals = np.column_stack([np.cos(a), np.sin(a), np.zeros(n_side)])
    T = misalignment(rng, shift_m=shift_m, angle_deg=angle_deg)
    scan = scan_from_surface(
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
        curve=curve,
        length_m=length,
        noise=noise,
        faces=_cylinder_faces(R, H),
    )


def _cylinder_faces(R: float, H: float) -> tuple[Face, ...]:
    """The cylinder's top (kept 5 mm inside the rim) and its side wall."""

    def top(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        r = (R - 5 * MM) * np.sqrt(rng.uniform(0.05, 1, n))
        a = rng.uniform(0, 2 * np.pi, n)
        points = np.column_stack([r * np.cos(a), r * np.sin(a), np.full(n, H)])
        return points, np.tile([0.0, 0.0, 1.0], (n, 1))

    def side(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        a = rng.uniform(0, 2 * np.pi, n)
        normals = np.column_stack([np.cos(a), np.sin(a), np.zeros(n)])
        points = R * normals + np.outer(rng.uniform(5 * MM, H - 5 * MM, n), [0.0, 0.0, 1.0])
        return points, normals

    return (Face("top", top), Face("side", side))


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

    def curve(s: FloatArray) -> FloatArray:
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
    length = float(arc[-1])
    width = 20 * MM
    n = sample_count((2 * half_length_m + 20 * MM) * 2 * width * np.sqrt(2), 1.0)
    x = rng.uniform(-half_length_m - 10 * MM, half_length_m + 10 * MM, n)
    d = rng.uniform(-width, width, n)  # offset across the crest, in y
    pts = np.column_stack([x, 0.5 * c * x**2 + d, -np.abs(d)])
    # Face normals of z = -|y - c x^2 / 2|: gradient (c x sgn, -sgn, -1) up to sign.
    sgn = np.sign(d)
    normals = np.column_stack([c * x * sgn, -sgn, -np.ones(n)])
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    T = misalignment(rng, shift_m=shift_m, angle_deg=angle_deg)
    scan = scan_from_surface(
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
        curve=curve,
        length_m=length,
        noise=noise,
        faces=_ridge_faces(c, half_length_m, width),
    )


def _ridge_faces(c: float, half_length_m: float, width_m: float) -> tuple[Face, ...]:
    """The ridge's two 45-degree faces, kept 3 mm off the crest and the far borders."""

    def face(sign: float) -> Callable[[np.random.Generator, int], tuple[FloatArray, FloatArray]]:
        def sample(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
            x = rng.uniform(-half_length_m, half_length_m, n)
            d = sign * rng.uniform(3 * MM, width_m - 3 * MM, n)
            points = np.column_stack([x, 0.5 * c * x**2 + d, -np.abs(d)])
            # The face is z = -sign (y - c x^2 / 2); its upward normal is the gradient of
            # z + sign (y - c x^2 / 2).
            normals = np.column_stack([-c * x * sign, np.full(n, sign), np.ones(n)])
            return points, normals / np.linalg.norm(normals, axis=1)[:, None]

        return sample

    return (Face("face +y", face(1.0)), Face("face -y", face(-1.0)))


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

    def curve(s: FloatArray) -> FloatArray:
        return np.column_stack([np.interp(s, arc, line[:, k]) for k in range(3)])

    def lift(s: FloatArray) -> FloatArray:
        bump = lift_m * np.exp(-0.5 * ((s - 0.55 * length) / lift_width_m) ** 2)
        return np.column_stack([np.zeros_like(s), np.zeros_like(s), bump])

    noise = HandNoise()
    recording, truth = hand_trace(curve, length, rng, noise=noise, extra_offset=lift)
    n = sample_count(200 * MM * 80 * MM, 1.0)
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
        curve=curve,
        length_m=length,
        noise=noise,
        extra_offset=lift,
        faces=(Face("plate", _plate_top),),
        in_plane=lambda p: p * [1.0, 1.0, 0.0],
    )


def _plate_top(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
    """Points on the plate (z = 0), kept 10 mm inside its borders."""
    points = np.column_stack(
        [rng.uniform(-90 * MM, 90 * MM, n), rng.uniform(-30 * MM, 30 * MM, n), np.zeros(n)]
    )
    return points, np.tile([0.0, 0.0, 1.0], (n, 1))


def free_curve(seed: int = 0) -> Scene:
    """The paper's Fig. 8: a curved path with no surface at all (path-only reconstruction)."""
    rng = np.random.default_rng(seed)
    xs = np.linspace(0, 1, 20001)
    ang = 2.2 * np.pi * xs
    line = np.column_stack(
        [60 * MM * np.cos(ang), 40 * MM * np.sin(ang), 25 * MM * np.sin(0.5 * ang)]
    )
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))))

    def curve(s: FloatArray) -> FloatArray:
        return np.column_stack([np.interp(s, arc, line[:, k]) for k in range(3)])

    recording, truth = hand_trace(curve, float(arc[-1]), rng, noise=HandNoise())
    return Scene(
        curve=curve,
        length_m=float(arc[-1]),
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

    def curve(s: FloatArray) -> FloatArray:
        s = np.asarray(s)
        first = corner + np.outer(np.minimum(s, leg_a) - leg_a, [1.0, 0.0, 0.0])
        second = np.outer(np.clip(s - leg_a, 0.0, None), [0.0, 1.0, 0.0])
        points: FloatArray = first + second
        return points

    recording, truth = hand_trace(curve, leg_a + leg_b, rng, noise=HandNoise())
    X, Y, Z = 100 * MM, 80 * MM, 40 * MM
    n_top, n_front, n_right = (sample_count(a, 1.0) for a in (X * Y, X * Z, Y * Z))
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
    scan = scan_from_surface(
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
        curve=curve,
        length_m=leg_a + leg_b,
        faces=_box_faces(X, Y, Z),
        corners_m=corner[None, :],
    )


def _box_faces(X: float, Y: float, Z: float) -> tuple[Face, ...]:
    """The box's top, front (y = 0) and right (x = X) faces, kept 5 mm inside their borders."""
    inset = 5 * MM

    def top(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        points = np.column_stack(
            [rng.uniform(inset, X - inset, n), rng.uniform(inset, Y - inset, n), np.zeros(n)]
        )
        return points, np.tile([0.0, 0.0, 1.0], (n, 1))

    def front(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        points = np.column_stack(
            [rng.uniform(inset, X - inset, n), np.zeros(n), rng.uniform(inset - Z, -inset, n)]
        )
        return points, np.tile([0.0, -1.0, 0.0], (n, 1))

    def right(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        points = np.column_stack(
            [np.full(n, X), rng.uniform(inset, Y - inset, n), rng.uniform(inset - Z, -inset, n)]
        )
        return points, np.tile([1.0, 0.0, 0.0], (n, 1))

    return (Face("top", top), Face("front", front), Face("right", right))


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

    def curve(s: FloatArray) -> FloatArray:
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


def serpentine_plate(
    n_path_points: int,
    n_scan_points: int,
    seed: int = 0,
    *,
    spacing_m: float = 1 * MM,
    row_length_m: float = 0.3,
    pitch_m: float = 20 * MM,
    near_x_m: float = 0.35,
    height_m: float = 0.1,
    scan_noise_m: float = 0.5 * MM,
) -> Scene:
    """A long path on a plate within a UR10e's reach (up to about 12k points at the defaults:
    longer paths add rows beyond it), for timing planning.

    The path runs in rows ``row_length_m`` long along y, ``pitch_m`` apart in x from
    ``near_x_m`` outwards, joined by half circles, ``n_path_points * spacing_m`` long in all, on
    the plate z = ``height_m`` of the tracker frame (the base frame of an arm at its origin, on
    a table below the plate). The scan has ``n_scan_points`` on the plate, 10 mm past the path
    all round.
    """
    rng = np.random.default_rng(seed)
    length = n_path_points * spacing_m
    turn = np.pi * pitch_m / 2
    rows = int(np.ceil(length / (row_length_m + turn))) + 1
    pieces = []
    for row in range(rows):
        x = near_x_m + row * pitch_m
        y0, y1 = (-0.5, 0.5) if row % 2 == 0 else (0.5, -0.5)
        ys = np.linspace(y0 * row_length_m, y1 * row_length_m, 2001)
        pieces.append(np.column_stack([np.full_like(ys, x), ys, np.full_like(ys, height_m)]))
        # Half a circle to the next row, on the side the row ended.
        angle = np.linspace(np.pi, 0.0, 200)[1:-1]
        centre = (x + pitch_m / 2, y1 * row_length_m)
        side = 1.0 if y1 > 0 else -1.0
        pieces.append(
            np.column_stack(
                [
                    centre[0] + pitch_m / 2 * np.cos(angle),
                    centre[1] + side * pitch_m / 2 * np.sin(angle),
                    np.full_like(angle, height_m),
                ]
            )
        )
    line = np.concatenate(pieces)
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))))

    def curve(s: FloatArray) -> FloatArray:
        return np.column_stack([np.interp(s, arc, line[:, k]) for k in range(3)])

    recording, truth = hand_trace(
        curve, length, rng, noise=HandNoise(), sample_spacing_m=spacing_m / 2
    )
    lo, hi = truth.min(axis=0) - 10 * MM, truth.max(axis=0) + 10 * MM
    points = np.column_stack(
        [
            rng.uniform(lo[0], hi[0], n_scan_points),
            rng.uniform(lo[1], hi[1], n_scan_points),
            height_m + scan_noise_m * rng.standard_normal(n_scan_points),
        ]
    )
    return Scene(
        name=f"serpentine_plate_{n_path_points}",
        description=f"{length:.0f} m in rows on a plate, {n_scan_points} scan points",
        truth_m=truth,
        recording=recording,
        scan=Scan(points_m=points),
        T_scan_tracker=np.eye(4),
        feature="surface",
        surface_height=lambda p: p[:, 2] - height_m,
    )
