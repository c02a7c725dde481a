"""Synthetic scenes with known ground truth: the paper's test cases and our own.

Each scene holds the true feature curve, a noisy hand trace of it in the tracker frame and,
where the case has one, a noisy scan of the workpiece in a slightly misplaced scan frame; the
faces of the workpiece that can be touched (:mod:`recon.scenes.touches`), and the curve itself, so
that more traces of it can be drawn (:meth:`Scene.traces`).

Used by the tests, the benchmarks and the demo; deterministic for a given seed.

Modules: :mod:`~recon.scenes.noise` (hand noise, scanner misplacement), :mod:`~recon.scenes.base`
(the scene, faces, scan noise), :mod:`~recon.scenes.paper` (the paper's figures, a box corner, a
long edge for timing), :mod:`~recon.scenes.outlines` (corners of any angle, rounded bends, with or
without a scan), :mod:`~recon.scenes.touches` (touch recordings).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

from recon.scenes.base import MM, Face, Scene
from recon.scenes.noise import HandNoise, coloured_noise, hand_trace, misalignment
from recon.scenes.outlines import turning_edge
from recon.scenes.paper import (
    box_corner,
    cylinder_edge,
    flat_liftoff,
    free_curve,
    long_edge,
    polynomial_ridge,
    serpentine_plate,
)
from recon.scenes.touches import Touches, touch_recording

__all__ = [
    "ACCURACY_SCENES",
    "MM",
    "SCENES",
    "Face",
    "HandNoise",
    "Scene",
    "Touches",
    "box_corner",
    "coloured_noise",
    "cylinder_edge",
    "flat_liftoff",
    "free_curve",
    "hand_trace",
    "long_edge",
    "misalignment",
    "polynomial_ridge",
    "serpentine_plate",
    "touch_recording",
    "turning_edge",
]

#: The paper's scenes and the box corner, by name, with their default arguments.
SCENES: dict[str, Callable[..., Scene]] = {
    "cylinder_edge": cylinder_edge,
    "polynomial_ridge": polynomial_ridge,
    "flat_liftoff": flat_liftoff,
    "free_curve": free_curve,
    "box_corner": box_corner,
}


def _named(name: str, make: Callable[..., Scene], **kwargs: Any) -> Callable[[int], Scene]:
    def scene(seed: int = 0) -> Scene:
        return replace(make(seed, **kwargs), name=name)

    scene.__name__ = name
    return scene


#: The accuracy suite: every kind of place where a tool meets the workpiece. Edges that are
#: circular, parabolic and straight; corners of 60, 90 and 120 degrees of turn; rounded bends
#: of 15 and 40 mm radius with and without a scan; a plate with a lift-off; a curve in the air.
ACCURACY_SCENES: dict[str, Callable[[int], Scene]] = {
    "cylinder_edge": cylinder_edge,
    "polynomial_ridge": polynomial_ridge,
    "box_corner": box_corner,
    "corner_60": _named("corner_60", turning_edge, turn_deg=60.0),
    "corner_120": _named("corner_120", turning_edge, turn_deg=120.0),
    "bend_15": _named("bend_15", turning_edge, bend_radius_m=15 * MM),
    "bend_40": _named("bend_40", turning_edge, bend_radius_m=40 * MM),
    "bend_15_no_scan": _named(
        "bend_15_no_scan", turning_edge, bend_radius_m=15 * MM, with_scan=False
    ),
    "bend_40_no_scan": _named(
        "bend_40_no_scan", turning_edge, bend_radius_m=40 * MM, with_scan=False
    ),
    "flat_liftoff": flat_liftoff,
    "free_curve": free_curve,
}
