"""Scoring reconstructions of synthetic scenes against their ground truth.

Errors are reported in two frames, because a misplaced scanner makes them differ:

``tracker``
    Distance to the true feature in the tracker frame: what the robot gets.
``registered``
    Distance to the feature where the registered scan puts it, as in the paper's Fig. 4 (the
    noisy path was aligned to the scan by ICP and compared with the model). A slow drift of the
    trace that looks like a rigid motion is indistinguishable from a misplaced scanner, so
    registration absorbs it; this frame measures everything else. For surface scenes, where
    registration fixes only some motions, it is the height above the registered surface.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from recon.arrays import FloatArray
from recon.metrics import ErrorStats, best_savitzky_golay, error_stats
from recon.recon_params import ReconParams
from recon.reconstruct import reconstruct
from recon.results import Reconstruction
from recon.scenes import Scene
from recon.transforms import apply_transform, invert_transform


@dataclass(frozen=True)
class Variant:
    """A way to reconstruct: a label and the parameters (None for the baselines)."""

    label: str
    params: ReconParams | None


@dataclass(frozen=True)
class Row:
    """Accuracy of one variant on one scene.

    Attributes
    ----------
    label : str
    tracker : ErrorStats
        Distances to the true feature, tracker frame.
    tracker_ratio : float
        Mean error over the raw trace's, same frame.
    registered : ErrorStats or None
        Distances to the feature as registered (edge scenes); None where not defined.
    registered_ratio : float or None
    height_max_m : float or None
        Largest height above the registered surface (surface scenes).
    """

    label: str
    tracker: ErrorStats
    tracker_ratio: float
    registered: ErrorStats | None
    registered_ratio: float | None
    height_max_m: float | None


def default_variants(base: ReconParams | None = None) -> list[Variant]:
    """The variants of the issue's accuracy table: the paper's Eq. (4) and ours, several alphas."""
    base = base or ReconParams()
    variants = []
    for method in ("paper", "anchored"):
        for alpha in (1.0, 0.0, 0.5, "auto"):
            variants.append(
                Variant(f"{method} alpha={alpha}", replace(base, method=method, alpha=alpha))
            )
    return variants


def registered_truth(scene: Scene, recon: Reconstruction) -> FloatArray:
    """The true feature moved to where the registered scan shows it (tracker frame)."""
    if recon.registration is None:
        return scene.truth_m
    error = invert_transform(recon.registration.T_scan_tracker) @ scene.T_scan_tracker
    return apply_transform(error, scene.truth_m)


def height_above_registered(
    scene: Scene, recon: Reconstruction, points_m: FloatArray
) -> FloatArray:
    """Heights of points above the scene's surface as the registered scan shows it."""
    if scene.surface_height is None:
        raise ValueError(f"scene {scene.name} has no surface height")
    if recon.registration is None:
        return scene.surface_height(points_m)
    error = invert_transform(recon.registration.T_scan_tracker) @ scene.T_scan_tracker
    return scene.surface_height(apply_transform(invert_transform(error), points_m))


def evaluate(
    scene: Scene,
    variants: list[Variant],
    *,
    spacing_m: float = 0.001,
    T_scan_tracker_init: FloatArray | None = None,
) -> list[Row]:
    """Reconstruct ``scene`` with every variant and score it; raw and best Savitzky-Golay first.

    The registered frame of the raw trace and of the Savitzky-Golay baseline is the one of the
    first variant that registered (they do not register themselves).
    """
    raw_tracker = error_stats(scene.recording.points_m, scene.truth_m)
    results = [
        (
            v.label,
            reconstruct(
                scene.recording,
                scene.scan,
                params=v.params,
                T_scan_tracker_init=T_scan_tracker_init,
            ),
        )
        for v in variants
    ]
    reference = next((r for _, r in results if r.registration is not None), None)
    savgol = best_savitzky_golay(scene.recording.points_m, scene.truth_m, spacing_m=spacing_m)

    def row(label: str, points: FloatArray, recon: Reconstruction | None) -> Row:
        tracker = error_stats(points, scene.truth_m)
        frame = recon if recon is not None and recon.registration is not None else reference
        registered = registered_ratio = height = None
        if scene.feature == "edge" and frame is not None:
            truth = registered_truth(scene, frame)
            registered = error_stats(points, truth)
            registered_ratio = registered.ratio_to(error_stats(scene.recording.points_m, truth))
        if scene.surface_height is not None:
            height = float(
                np.max(height_above_registered(scene, frame, points))
                if frame is not None
                else np.max(scene.surface_height(points))
            )
        return Row(
            label, tracker, tracker.ratio_to(raw_tracker), registered, registered_ratio, height
        )

    rows = [row("raw trace", scene.recording.points_m, None)]
    rows.append(
        row(
            f"best Savitzky-Golay ({savgol.window_m * 1e3:.0f} mm, order {savgol.order})",
            savgol.points_m,
            None,
        )
    )
    rows += [row(label, recon.points_m, recon) for label, recon in results]
    return rows


def format_table(rows: list[Row], *, title: str = "") -> str:
    """The rows as a Markdown table, errors in millimetres."""
    mm = 1e3
    lines = [f"**{title}**", ""] if title else []
    lines += [
        "| method | mean mm | max mm | e/e_raw | registered: mean mm | max mm | e/e_raw "
        "| height max mm |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        reg = (
            (
                f"{r.registered.mean_m * mm:.3f} | {r.registered.max_m * mm:.3f} | "
                f"{r.registered_ratio:.2f}"
            )
            if r.registered is not None
            else "- | - | -"
        )
        height = f"{r.height_max_m * mm:.2f}" if r.height_max_m is not None else "-"
        lines.append(
            f"| {r.label} | {r.tracker.mean_m * mm:.3f} | {r.tracker.max_m * mm:.3f} | "
            f"{r.tracker_ratio:.2f} | {reg} | {height} |"
        )
    return "\n".join(lines)
