"""Paths along the top edge of a plate whose outline turns: a sharp corner of any angle, or a
rounded bend of a given radius (with or without a scan).

The plate's top is z = 0 with the workpiece on the left of the direction of travel (a convex
outline, traced anticlockwise seen from above); its wall runs 25 mm down. The outline and the
scan continue 15 mm past both ends of the path, as a workpiece's edge does past where an operator
starts and stops, so the ends of the path are scored where the scan still defines the edge.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from recon.arrays import FloatArray
from recon.scenes.base import (
    MM,
    Face,
    Scene,
    interpolated_curve,
    sample_count,
    scan_from_surface,
)
from recon.scenes.noise import HandNoise, hand_trace, misalignment

#: How far the plate's edge (and the scan) runs on past each end of the path.
EXTENSION_M = 15 * MM
#: Depth of the plate's top that is scanned, inwards from the edge.
TOP_DEPTH_M = 40 * MM
#: Height of the plate's wall.
WALL_HEIGHT_M = 25 * MM


def _heading(angle_rad: FloatArray) -> FloatArray:
    return np.column_stack([np.cos(angle_rad), np.sin(angle_rad), np.zeros_like(angle_rad)])


def outline(
    s_m: FloatArray, *, leg_a_m: float, leg_b_m: float, turn_deg: float, bend_radius_m: float
) -> tuple[FloatArray, FloatArray]:
    """Points and unit headings of the outline at arc lengths ``s_m`` (any real values; beyond
    ``[0, length]`` the legs run on straight).

    Leg A runs along +x from the origin; then the outline turns left by ``turn_deg``, sharply
    (``bend_radius_m`` = 0) or on a circular arc of that radius; then leg B.

    Returns
    -------
    points, headings : ndarrays of shape (N, 3)
    """
    s = np.asarray(s_m, dtype=np.float64)
    turn = np.radians(turn_deg)
    arc_len = bend_radius_m * turn
    # Where the arc starts (the sharp corner's vertex when the radius is 0).
    start_arc = np.array([leg_a_m, 0.0, 0.0])
    centre = start_arc + np.array([0.0, bend_radius_m, 0.0])
    end_arc = centre + bend_radius_m * np.array([np.sin(turn), -np.cos(turn), 0.0])
    on_a = s <= leg_a_m
    on_arc = (s > leg_a_m) & (s < leg_a_m + arc_len)
    on_b = ~on_a & ~on_arc
    angle = np.where(on_a, 0.0, np.where(on_arc, (s - leg_a_m) / max(bend_radius_m, 1e-300), turn))
    heading = _heading(angle)
    points = np.empty((len(s), 3))
    points[on_a] = np.outer(s[on_a], [1.0, 0.0, 0.0])
    a = angle[on_arc]
    points[on_arc] = centre + bend_radius_m * np.column_stack(
        [np.sin(a), -np.cos(a), np.zeros_like(a)]
    )
    heading_b = _heading(np.array([turn]))[0]
    points[on_b] = end_arc + np.outer(s[on_b] - leg_a_m - arc_len, heading_b)
    return points, heading


def _left(heading: FloatArray) -> FloatArray:
    """The horizontal direction to the left of each heading (into the plate)."""
    return np.column_stack([-heading[:, 1], heading[:, 0], np.zeros(len(heading))])


def _inside(points_xy: FloatArray, polygon_xy: FloatArray) -> np.ndarray:
    """Even-odd point-in-polygon test (ray to +x), vectorised over the points."""
    x, y = points_xy[:, 0], points_xy[:, 1]
    inside = np.zeros(len(points_xy), dtype=bool)
    xa, ya = polygon_xy[:, 0], polygon_xy[:, 1]
    xb, yb = np.roll(xa, -1), np.roll(ya, -1)
    for x0, y0, x1, y1 in zip(xa, ya, xb, yb, strict=True):
        crosses = (y0 > y) != (y1 > y)
        x_cross = x0 + (y - y0) * (x1 - x0) / np.where(y1 != y0, y1 - y0, 1.0)
        inside ^= crosses & (x < x_cross)
    return inside


def turning_edge(
    seed: int = 0,
    *,
    turn_deg: float = 90.0,
    bend_radius_m: float = 0.0,
    leg_a_m: float = 60 * MM,
    leg_b_m: float = 50 * MM,
    with_scan: bool = True,
    scan_noise_m: float = 0.5 * MM,
    shift_m: float = 2 * MM,
    angle_deg: float = 1.0,
    noise: HandNoise | None = None,
) -> Scene:
    """A path along the top edge of a plate that turns by ``turn_deg``: at a sharp corner
    (``bend_radius_m`` = 0) or on a rounded bend of that radius.

    A sharp turn of 60-120 degrees is a corner of 120-60 degrees between the two edges. With
    ``with_scan`` False there is no scan (the path alone must keep a rounded bend round).
    """
    rng = np.random.default_rng(seed)
    noise = noise or HandNoise()
    geometry = {
        "leg_a_m": leg_a_m,
        "leg_b_m": leg_b_m,
        "turn_deg": turn_deg,
        "bend_radius_m": bend_radius_m,
    }
    length = leg_a_m + bend_radius_m * np.radians(turn_deg) + leg_b_m
    dense_s = np.arange(-EXTENSION_M, length + EXTENSION_M + 1e-12, 0.05 * MM)
    dense, headings = outline(dense_s, **geometry)
    inner = (dense_s >= 0) & (dense_s <= length)
    curve, _ = interpolated_curve(dense[inner])
    recording, truth = hand_trace(curve, length, rng, noise=noise)

    polygon = np.concatenate(
        [
            dense[:, :2],
            (dense[-1] + TOP_DEPTH_M * _left(headings[-1:])[0])[None, :2],
            (dense[0] + TOP_DEPTH_M * _left(headings[:1])[0])[None, :2],
        ]
    )
    shape = "sharp" if bend_radius_m == 0 else f"rounded (radius {bend_radius_m / MM:.0f} mm)"
    description = f"plate edge turning {turn_deg:g} deg, {shape}"
    T = np.eye(4)
    scan = None
    if with_scan:
        lo, hi = polygon.min(axis=0), polygon.max(axis=0)
        n_box = sample_count(float(np.prod(hi - lo)), 1.0)
        xy = rng.uniform(lo, hi, size=(n_box, 2))
        xy = xy[_inside(xy, polygon)]
        top = np.column_stack([xy, np.zeros(len(xy))])
        wall_length = length + 2 * EXTENSION_M
        n_wall = sample_count(wall_length * WALL_HEIGHT_M, 1.0)
        ws = rng.uniform(-EXTENSION_M, length + EXTENSION_M, n_wall)
        wall_points, wall_headings = outline(ws, **geometry)
        wall_points[:, 2] = rng.uniform(-WALL_HEIGHT_M, 0.0, n_wall)
        T = misalignment(rng, shift_m=shift_m, angle_deg=angle_deg)
        scan = scan_from_surface(
            np.concatenate([top, wall_points]),
            np.concatenate([np.tile([0.0, 0.0, 1.0], (len(top), 1)), -_left(wall_headings)]),
            rng,
            sigma_m=scan_noise_m,
            outlier_fraction=0.003,
            T_scan_tracker=T,
        )
        description += (
            f", scan noise {scan_noise_m / MM:.1f} mm, off by {shift_m / MM:.0f} mm / "
            f"{angle_deg:g} deg"
        )
    else:
        description += ", no scan"
    corners = (
        outline(np.array([leg_a_m]), **geometry)[0] if bend_radius_m == 0 else np.zeros((0, 3))
    )
    return Scene(
        name=("corner" if bend_radius_m == 0 else "bend") + ("" if with_scan else "_no_scan"),
        description=description,
        truth_m=truth,
        recording=recording,
        scan=scan,
        T_scan_tracker=T,
        feature="edge" if with_scan else "none",
        curve=curve,
        length_m=length,
        noise=noise,
        faces=_plate_faces(polygon, geometry, length) if with_scan else (),
        corners_m=corners,
    )


def _plate_faces(
    polygon: FloatArray, geometry: dict[str, float], length: float
) -> tuple[Face, ...]:
    """The plate's top (5 mm inside its outline) and the walls below its two legs."""
    inset = 5 * MM

    def top(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        lo, hi = polygon.min(axis=0), polygon.max(axis=0)
        found = np.zeros((0, 2))
        while len(found) < n:
            xy = rng.uniform(lo, hi, size=(4 * n, 2))
            keep = _inside(xy, polygon)
            # Keep off the edge: the point moved inset towards every side stays inside.
            for d in ((inset, 0), (-inset, 0), (0, inset), (0, -inset)):
                keep &= _inside(xy + np.asarray(d), polygon)
            found = np.concatenate([found, xy[keep]])
        points = np.column_stack([found[:n], np.zeros(n)])
        return points, np.tile([0.0, 0.0, 1.0], (n, 1))

    def wall(
        lo_m: float, hi_m: float
    ) -> Callable[[np.random.Generator, int], tuple[FloatArray, FloatArray]]:
        def sample(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
            points, headings = outline(rng.uniform(lo_m, hi_m, n), **geometry)
            points[:, 2] = rng.uniform(inset - WALL_HEIGHT_M, -inset, n)
            return points, -_left(headings)

        return sample

    leg_b_start = length - geometry["leg_b_m"]
    return (
        Face("top", top),
        Face("wall of the first leg", wall(inset, geometry["leg_a_m"] - inset)),
        Face("wall of the second leg", wall(leg_b_start + inset, length - inset)),
    )
