"""The real-parts benchmark: the corpus's CAD parts scanned by a simulated hand-held depth camera,
hand traces along their true feature curves, every way of reconstructing scored against the truth.

Shared by the benchmark (``tests/bench/test_bench_real_parts.py``, every part, tables) and the
``make test`` subset (``tests/recon/test_real_parts.py``, a few curves, the bars asserted).

Errors are distances to the true curve in the tracker frame (what the robot gets), in metres:
the mean over the raw trace's, the largest, and the ends (the first and last 10 mm).
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cache

import numpy as np
from scipy.spatial import cKDTree

from recon.errors import ReconError
from recon.icp import register_icp
from recon.metrics import best_savitzky_golay, distance_to_curve, score_path
from recon.recon_params import ReconParams
from recon.reconstruct import reconstruct
from recon.resample import resample_equidistant
from recon.results import PointMode, PointReason, Reconstruction
from recon.scenes import Scene, touch_recording
from recon.scenes.cad import CaseChoice, CurveCase, cad_scene, traceable_cases
from recon.touches import register_touches, touches_in
from recon.transforms import apply_transform, invert_transform
from tests.corpus import load_part, part_names

MM = 1e-3
#: A point this far from the truth must be flagged (fallen back, or path only): the bar.
FLAG_DISTANCE_M = 2 * MM


@cache
def benchmark_choices(names: tuple[str, ...] | None = None) -> tuple[CaseChoice, ...]:
    """The traceable curves of every part (or of the named ones), in corpus order, with how
    much of each the scan shows from both sides."""
    choices = []
    for name in names or tuple(part_names()):
        choices += traceable_cases(load_part(name))
    return tuple(choices)


def benchmark_cases(names: tuple[str, ...] | None = None) -> tuple[CurveCase, ...]:
    """The traceable curves of every part (or of the named ones), in corpus order."""
    return tuple(choice.case for choice in benchmark_choices(names))


@cache
def scene_of(case: CurveCase, seed: int, kind: str) -> Scene:
    return cad_scene(case, seed, kind=kind)


@dataclass(frozen=True)
class Variant:
    """A way to reconstruct a scene: ``run(scene, seed)`` -> Reconstruction or (N, 3) array."""

    label: str
    run: Callable[[Scene, int], Reconstruction | np.ndarray]


class NoRoomToTouch(Exception):
    """The part has no three faces with room for a touch away from their borders: the touches
    variant cannot be staged on it (a limit of the bench's scene, not a refusal of the method)."""


def _touches(scene: Scene, seed: int):
    try:
        recording = touch_recording(scene, seed, n_touches=7).recording
    except ValueError as error:
        if "no room" not in str(error):
            raise
        raise NoRoomToTouch(f"no touches staged: {error}") from None
    found = touches_in(recording.points_m, recording.t_s)
    return register_touches(
        found.points_m,
        scene.scan.points_m,
        T_scan_tracker_init=np.eye(4),
        touch_sigma_m=found.sigma_m,
    )


def registered_to_truth(scene: Scene, seed: int) -> np.ndarray:
    """The truth carried into the trace's frame by the trace's own best rigid fit to it: what a
    registration from the trace leaves in the tracker frame at best (the rigid part of the
    hand's drift, which no registration can tell from a misplaced scanner). A floor for the
    "registered from the trace" bar, not a method."""
    truth = resample_equidistant(scene.truth_m, spacing_m=0.2 * MM).points_m
    directions = np.gradient(truth, axis=0)
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    fit = register_icp(
        scene.recording.points_m,
        truth,
        init_T_target_source=np.eye(4),
        max_distance_m=10 * MM,
        target_directions=directions,
        target_label="edge",
        target_tree=cKDTree(truth),
    )
    return apply_transform(invert_transform(fit.T_scan_tracker), truth)


VARIANTS = {
    "trace": Variant("registered from the trace", lambda s, seed: reconstruct(s.recording, s.scan)),
    "known": Variant(
        "scanner pose known",
        lambda s, seed: reconstruct(
            s.recording,
            s.scan,
            params=replace(ReconParams(), register=False),
            T_scan_tracker_init=s.T_scan_tracker,
        ),
    ),
    "touches": Variant(
        "registered by touches",
        lambda s, seed: reconstruct(s.recording, s.scan, touches=_touches(s, seed)),
    ),
    "path": Variant("path only (no scan)", lambda s, seed: reconstruct(s.recording, None)),
    "oracle": Variant("trace's best rigid fit to the truth (a floor)", registered_to_truth),
}


@dataclass(frozen=True)
class CurveScore:
    """One variant on one scene.

    Attributes
    ----------
    scene : str
    variant : str
    mean_m, max_m, start_max_m, end_max_m : float
        Tracker frame.
    raw_mean_m, raw_max_m : float
        The raw trace's.
    savgol_mean_m : float
        The best Savitzky-Golay filter's in hindsight.
    fallback_fraction : float
        Share of points left to the path alone although a scan was given.
    unflagged_far : int
        Points farther than :data:`FLAG_DISTANCE_M` from the truth and not flagged.
    covered_2sigma : float
        Share of points whose error is within twice their stated uncertainty (NaN without one).
    n_points : int
        Points of the output (to pool the coverage over scenes).
    refused : str
        Why the variant refused the scene ("" when it did not).
    """

    scene: str
    variant: str
    mean_m: float
    max_m: float
    start_max_m: float
    end_max_m: float
    raw_mean_m: float
    raw_max_m: float
    savgol_mean_m: float
    fallback_fraction: float
    unflagged_far: int
    covered_2sigma: float
    n_points: int = 0
    refused: str = ""

    @property
    def ratio(self) -> float:
        return self.mean_m / self.raw_mean_m

    @property
    def savgol_ratio(self) -> float:
        return self.mean_m / self.savgol_mean_m


def flagged(recon: Reconstruction) -> np.ndarray:
    """Per point: the output says the scan was not used there (path only or unchanged, or a
    reason that says it fell back)."""
    fell = [int(r) for r in PointReason if r.fallen_back]
    return np.isin(recon.mode, [int(PointMode.PATH), int(PointMode.UNCHANGED)]) | (
        recon.reason is not None and np.isin(recon.reason, fell)
    )


def score(scene: Scene, variant: str, seed: int) -> CurveScore:
    """Run one variant on one scene and score it (a refusal is kept, with its reason)."""
    raw = score_path(scene.recording.points_m, scene.truth_m)
    savgol = best_savitzky_golay(scene.recording.points_m, scene.truth_m, spacing_m=1e-3)
    nan = float("nan")
    try:
        out = VARIANTS[variant].run(scene, seed)
    except (ReconError, NoRoomToTouch) as error:
        return CurveScore(
            scene.name, variant, nan, nan, nan, nan, raw.mean_m, raw.max_m,
            savgol.stats.mean_m, nan, 0, nan, 0, refused=str(error),
        )  # fmt: skip
    if isinstance(out, np.ndarray):  # points only: nothing flagged, no uncertainty
        points, mark, uncertainty = out, np.zeros(len(out), dtype=bool), None
    else:
        points, mark, uncertainty = out.points_m, flagged(out), out.uncertainty_m
    result = score_path(points, scene.truth_m)
    error = distance_to_curve(points, scene.truth_m)
    covered = nan
    if uncertainty is not None:
        covered = float(np.mean(error <= 2.0 * uncertainty))
    return CurveScore(
        scene=scene.name,
        variant=variant,
        mean_m=result.mean_m,
        max_m=result.max_m,
        start_max_m=result.start_max_m,
        end_max_m=result.end_max_m,
        raw_mean_m=raw.mean_m,
        raw_max_m=raw.max_m,
        savgol_mean_m=savgol.stats.mean_m,
        # Falling back means something only where a scan was used.
        fallback_fraction=float(np.mean(mark)) if variant not in ("path", "oracle") else nan,
        unflagged_far=int(np.count_nonzero((error > FLAG_DISTANCE_M) & ~mark)),
        covered_2sigma=covered,
        n_points=len(points),
    )


def run(
    cases, seeds, kinds=("edge",), variants=("trace", "known", "path"), skipped=None
) -> list[CurveScore]:
    """Every variant on every case, seed and trace kind.

    A face trace needs a flat stretch of face beside the curve; where a part has none, the case
    is left out of that kind and ``(case name, reason)`` appended to ``skipped`` (if given).
    """
    out = []
    for case in cases:
        for kind in kinds:
            if kind == "past_ends" and case.closed:
                continue  # a loop's stretch has no feature ends to run past
            for seed in seeds:
                try:
                    scene = scene_of(case, seed, kind)
                except ValueError as error:
                    if kind != "face":
                        raise
                    if skipped is not None:
                        skipped.append((case.name, str(error)))
                    break  # the face is the same for every seed
                for variant in variants:
                    out.append(replace(score(scene, variant, seed), scene=f"{scene.name}/{seed}"))
    return out


def _mm(value: float) -> str:
    return "-" if not np.isfinite(value) else f"{value / MM:.2f}"


def _percent(share: float, digits: int) -> str:
    return "-" if not np.isfinite(share) else f"{share * 100:.{digits}f} %"


def per_curve_table(scores: list[CurveScore]) -> str:
    """One row per scene and seed, one column group per variant (mm)."""
    variants = list(dict.fromkeys(s.variant for s in scores))
    scenes = list(dict.fromkeys(s.scene for s in scores))
    by = {(s.scene, s.variant): s for s in scores}
    head = "| scene | raw mean | raw max |"
    rule = "|---|---:|---:|"
    for v in variants:
        head += f" {v}: mean/raw | max | first 10 | last 10 | fallen back |"
        rule += "---:|---:|---:|---:|---:|"
    lines = [head, rule]
    for name in scenes:
        first = by[(name, variants[0])]
        row = f"| {name} | {_mm(first.raw_mean_m)} | {_mm(first.raw_max_m)} |"
        for v in variants:
            s = by.get((name, v))
            if s is None:
                row += " | | | | |"
            elif s.refused:
                row += " refused | | | | |"
            else:
                ratio = s.ratio if v != "path" else s.savgol_ratio
                mark = "" if v != "path" else " (SG)"
                row += (
                    f" {ratio:.2f}{mark} | {_mm(s.max_m)} | {_mm(s.start_max_m)} | "
                    f"{_mm(s.end_max_m)} | {_percent(s.fallback_fraction, 0)} |"
                )
        lines.append(row)
    return "\n".join(lines)


def summary_table(scores: list[CurveScore]) -> str:
    """One row per variant over every scene: the bars' figures (mm)."""
    lines = [
        "| variant | scenes | refused | mean/raw median | worst | worse than raw | "
        "max median | worst max | max <= 1 mm | ends max median | fallen back | "
        "unflagged > 2 mm | 2-sigma coverage (pooled) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for variant in dict.fromkeys(s.variant for s in scores):
        rows = [s for s in scores if s.variant == variant]
        done = [s for s in rows if not s.refused]
        if not done:
            lines.append(f"| {VARIANTS[variant].label} | {len(rows)} | {len(rows)} |" + " - |" * 10)
            continue
        ratios = [s.ratio if variant != "path" else s.savgol_ratio for s in done]
        ends = [np.nanmax([s.start_max_m, s.end_max_m]) for s in done]
        covered = [s for s in done if np.isfinite(s.covered_2sigma)]
        pooled = (
            sum(s.covered_2sigma * s.n_points for s in covered) / sum(s.n_points for s in covered)
            if covered
            else float("nan")
        )
        fallen = [s.fallback_fraction for s in done if np.isfinite(s.fallback_fraction)]
        label = VARIANTS[variant].label + (" (ratio to best SG)" if variant == "path" else "")
        lines.append(
            f"| {label} | {len(rows)} | {len(rows) - len(done)} "
            f"| {statistics.median(ratios):.2f} | {max(ratios):.2f} "
            f"| {sum(r >= 1.0 for r in ratios)} "
            f"| {_mm(statistics.median(s.max_m for s in done))} "
            f"| {_mm(max(s.max_m for s in done))} "
            f"| {sum(s.max_m <= 1.0 * MM for s in done) / len(done) * 100:.0f} % "
            f"| {_mm(statistics.median(ends))} "
            f"| {_percent(statistics.mean(fallen) if fallen else float('nan'), 1)} "
            f"| {sum(s.unflagged_far for s in done)} "
            f"| {_percent(pooled, 0)} |"
        )
    return "\n".join(lines)
