"""The accuracy suite: every scene of :data:`recon.scenes.ACCURACY_SCENES` over many seeds, for
every way of reconstructing, scored where the tool touches.

What a row says, errors in the tracker frame (what the robot gets) unless said otherwise:

* the mean, 99th percentile and largest error, each the median over the seeds, and the worst
  seed's largest error (one lucky draw proves nothing);
* the ends (the first and last 10 mm of the feature, :data:`recon.metrics.END_STRETCH_M`) apart;
* the mean error over the raw trace's (over the demonstrations' average, when several were
  fused), median and worst seed;
* the registered frame: the errors across the path to the feature where the registered scan puts
  it (what the method itself controls; the rest is the rigid part of the hand's drift, which
  registration cannot tell from a misplaced scanner);
* for a surface, the largest height above it (tracker frame), and the mean error in its plane
  (which only the trace defines; the Savitzky-Golay row is then the filter best in the plane).

The variants (:func:`suite_variants`): the raw trace, the best Savitzky-Golay filter in hindsight,
the paper's Eq. (4), the default with registration from the trace, from touches of the workpiece,
with a calibrated scanner, and three fused demonstrations (with the scanner registered from them,
and from touches).
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from recon.arrays import FloatArray
from recon.errors import ReconError
from recon.inputs import Recording
from recon.metrics import PathScore, best_savitzky_golay, score_path
from recon.recon_params import ReconParams
from recon.reconstruct import reconstruct
from recon.results import Reconstruction
from recon.scenes import Scene, touch_recording
from recon.touches import TouchRegistration, register_touches, touches_in
from recon.transforms import apply_transform, invert_transform

MM = 1e-3
#: The registered frame's errors are measured against the feature run on this far past its ends.
REGISTERED_EXTENSION_M = 0.03
#: Demonstrations fused in the "fused" variants.
N_FUSED = 3


@dataclass(frozen=True)
class SuiteVariant:
    """A way to reconstruct a scene.

    Attributes
    ----------
    label : str
    run : callable
        ``run(scene, seed)`` -> a Reconstruction, or an (N, 3) array for the baselines.
    needs_scan : bool
        Skipped on scenes without a scan.
    inputs : callable or None
        ``inputs(scene, seed)`` -> the recordings it started from, when not the scene's trace
        alone (several demonstrations): the raw error it is compared with is their mean.
    """

    label: str
    run: Callable[[Scene, int], Reconstruction | FloatArray]
    needs_scan: bool = False
    inputs: Callable[[Scene, int], list[Recording]] | None = None


def touches_for(scene: Scene, seed: int) -> TouchRegistration:
    """The scanner registered from a touch recording of the scene (6 touches)."""
    if scene.scan is None:
        raise ValueError(f"scene {scene.name} has no scan to register touches against")
    recording = touch_recording(scene, seed).recording
    found = touches_in(recording.points_m, recording.t_s)
    return register_touches(
        found.points_m,
        scene.scan.points_m,
        T_scan_tracker_init=np.eye(4),
        touch_sigma_m=found.sigma_m,
    )


def _params(scene: Scene, **changes: Any) -> ReconParams:
    # The defaults everywhere: without a scan the path's windows widen by themselves where the
    # path runs straight (see recon.methods.common.adaptive_smoothing).
    return replace(ReconParams(), **changes)


def suite_variants() -> list[SuiteVariant]:
    """The rows of the accuracy tables, in order."""

    def raw(scene: Scene, seed: int) -> FloatArray:
        return scene.recording.points_m

    def savgol(scene: Scene, seed: int) -> FloatArray:
        if scene.in_plane is not None:
            # On a surface, the filter best in the plane (the height is the scan's to fix).
            flat = best_savitzky_golay(
                scene.in_plane(scene.recording.points_m),
                scene.in_plane(scene.truth_m),
                spacing_m=1e-3,
            )
            return best_savitzky_golay(
                scene.recording.points_m,
                scene.truth_m,
                spacing_m=1e-3,
                windows_m=(flat.window_m,),
                orders=(flat.order,),
            ).points_m
        return best_savitzky_golay(scene.recording.points_m, scene.truth_m, spacing_m=1e-3).points_m

    def paper(scene: Scene, seed: int) -> Reconstruction:
        return reconstruct(scene.recording, scene.scan, params=_params(scene, method="paper"))

    def default(scene: Scene, seed: int) -> Reconstruction:
        return reconstruct(scene.recording, scene.scan, params=_params(scene))

    def touches(scene: Scene, seed: int) -> Reconstruction:
        return reconstruct(
            scene.recording, scene.scan, params=_params(scene), touches=touches_for(scene, seed)
        )

    def calibrated(scene: Scene, seed: int) -> Reconstruction:
        return reconstruct(
            scene.recording,
            scene.scan,
            params=_params(scene, register=False),
            T_scan_tracker_init=scene.T_scan_tracker,
        )

    def demonstrations(scene: Scene, seed: int) -> list[Recording]:
        return [scene.recording, *scene.traces(N_FUSED - 1, seed)]

    def fused(scene: Scene, seed: int) -> Reconstruction:
        return reconstruct(demonstrations(scene, seed), scene.scan, params=_params(scene))

    def fused_touches(scene: Scene, seed: int) -> Reconstruction:
        return reconstruct(
            demonstrations(scene, seed),
            scene.scan,
            params=_params(scene),
            touches=touches_for(scene, seed),
        )

    return [
        SuiteVariant("raw trace", raw),
        SuiteVariant("best Savitzky-Golay (hindsight)", savgol),
        SuiteVariant("paper, Eq. (4)", paper),
        SuiteVariant("default, registered from the trace", default),
        SuiteVariant("default, registered by touches", touches, needs_scan=True),
        SuiteVariant("default, calibrated scanner", calibrated, needs_scan=True),
        SuiteVariant(f"default, {N_FUSED} fused traces", fused, inputs=demonstrations),
        SuiteVariant(
            f"default, {N_FUSED} fused traces + touches",
            fused_touches,
            needs_scan=True,
            inputs=demonstrations,
        ),
    ]


@dataclass(frozen=True)
class SeedResult:
    """One variant on one seed of one scene."""

    tracker: PathScore
    raw: PathScore
    registered: PathScore | None
    height_max_m: float | None
    in_plane: PathScore | None = None
    raw_registered: PathScore | None = None


@dataclass(frozen=True)
class SuiteRow:
    """One variant on one scene over the seeds (see the module docstring).

    Attributes
    ----------
    scene, variant : str
    results : list of SeedResult
        Of the seeds it ran on.
    refused : list of (int, str)
        Seeds it was refused on, and why (touches that fix too little, say).
    """

    scene: str
    variant: str
    results: list[SeedResult]
    refused: list[tuple[int, str]]

    def median(self, value: Callable[[SeedResult], float | None]) -> float:
        """The median over seeds of ``value`` (every seed must have it)."""
        return statistics.median(self._values(value))

    def worst(self, value: Callable[[SeedResult], float | None]) -> float:
        """The largest over seeds of ``value`` (every seed must have it)."""
        return max(self._values(value))

    def _values(self, value: Callable[[SeedResult], float | None]) -> list[float]:
        values = [value(r) for r in self.results]
        present = [v for v in values if v is not None]
        if len(present) != len(values):
            raise ValueError(f"{self.variant}: a score is missing for some seeds of {self.scene}")
        return present


def _registered_mean_m(result: SeedResult) -> float | None:
    return None if result.registered is None else result.registered.mean_m


def _registered_max_m(result: SeedResult) -> float | None:
    return None if result.registered is None else result.registered.max_m


def _in_plane_mean_m(result: SeedResult) -> float | None:
    return None if result.in_plane is None else result.in_plane.mean_m


def run_variant(scene: Scene, seed: int, variant: SuiteVariant) -> SeedResult:
    """Run one variant on one scene and score it.

    Raises
    ------
    ReconError
        The variant refused the scene (kept as a refusal by :func:`run_suite`).
    """
    out = variant.run(scene, seed)
    recon = out if isinstance(out, Reconstruction) else None
    points = recon.points_m if recon is not None else np.asarray(out)
    registered = raw_registered = None
    if recon is not None and recon.T_scan_tracker is not None and scene.feature == "edge":
        error = invert_transform(recon.T_scan_tracker) @ scene.T_scan_tracker
        moved_truth = apply_transform(error, scene.truth_m)
        registered = score_path(points, moved_truth, extend_ends_m=REGISTERED_EXTENSION_M)
        raw_registered = score_path(
            scene.recording.points_m, moved_truth, extend_ends_m=REGISTERED_EXTENSION_M
        )
    height = None
    if scene.surface_height is not None:
        height = float(np.max(np.abs(scene.surface_height(points))))
    in_plane = None
    if scene.in_plane is not None:
        in_plane = score_path(scene.in_plane(points), scene.in_plane(scene.truth_m))
    inputs = [scene.recording] if variant.inputs is None else variant.inputs(scene, seed)
    raws = [score_path(r.points_m, scene.truth_m) for r in inputs]
    raw = PathScore(
        *(float(np.mean([getattr(r, f) for r in raws])) for f in PathScore.__annotations__)
    )
    return SeedResult(
        tracker=score_path(points, scene.truth_m),
        raw=raw,
        registered=registered,
        height_max_m=height,
        in_plane=in_plane,
        raw_registered=raw_registered,
    )


def run_suite(
    scenes: dict[str, Callable[[int], Scene]],
    seeds: range,
    variants: list[SuiteVariant] | None = None,
) -> list[SuiteRow]:
    """Every variant on every scene and seed.

    Returns
    -------
    list of SuiteRow
        Scene by scene, variants in order; variants that need a scan are left out of scenes
        without one.
    """
    variants = variants or suite_variants()
    rows = []
    for name, make in scenes.items():
        built = [make(seed) for seed in seeds]
        for variant in variants:
            if variant.needs_scan and built[0].scan is None:
                continue
            results, refused = [], []
            for seed, scene in zip(seeds, built, strict=True):
                try:
                    results.append(run_variant(scene, seed, variant))
                except ReconError as error:
                    refused.append((seed, str(error)))
            rows.append(SuiteRow(name, variant.label, results, refused))
    return rows


def format_suite(rows: list[SuiteRow]) -> str:
    """The rows as Markdown tables, one per scene; millimetres."""
    out = []
    scene = None
    for row in rows:
        if row.scene != scene:
            scene = row.scene
            out += [
                "",
                f"**{scene}** (median over seeds, worst seed after the slash)",
                "",
                "| variant | mean | p99 | max | first 10 mm max | last 10 mm max | mean / raw "
                "| registered: mean | max | height max | in-plane mean | refused |",
                "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
            ]
        if not row.results:
            out.append(
                f"| {row.variant} | - | - | - | - | - | - | - | - | - | - | {len(row.refused)} |"
            )
            continue
        reg = "- | -"
        if all(r.registered is not None for r in row.results):
            reg = (
                f"{row.median(_registered_mean_m) / MM:.3f} | "
                f"{row.median(_registered_max_m) / MM:.2f} / "
                f"{row.worst(_registered_max_m) / MM:.2f}"
            )
        height = "-"
        if row.results[0].height_max_m is not None:
            height = (
                f"{row.median(lambda r: r.height_max_m) / MM:.2f} / "
                f"{row.worst(lambda r: r.height_max_m) / MM:.2f}"
            )
        plane = "-"
        if row.results[0].in_plane is not None:
            plane = f"{row.median(_in_plane_mean_m) / MM:.3f}"
        out.append(
            f"| {row.variant} "
            f"| {row.median(lambda r: r.tracker.mean_m) / MM:.3f} "
            f"| {row.median(lambda r: r.tracker.p99_m) / MM:.2f} "
            f"| {row.median(lambda r: r.tracker.max_m) / MM:.2f} / "
            f"{row.worst(lambda r: r.tracker.max_m) / MM:.2f} "
            f"| {row.median(lambda r: r.tracker.start_max_m) / MM:.2f} / "
            f"{row.worst(lambda r: r.tracker.start_max_m) / MM:.2f} "
            f"| {row.median(lambda r: r.tracker.end_max_m) / MM:.2f} / "
            f"{row.worst(lambda r: r.tracker.end_max_m) / MM:.2f} "
            f"| {row.median(lambda r: r.tracker.mean_m / r.raw.mean_m):.2f} / "
            f"{row.worst(lambda r: r.tracker.mean_m / r.raw.mean_m):.2f} "
            f"| {reg} | {height} | {plane} | {len(row.refused)} |"
        )
    return "\n".join(out)
