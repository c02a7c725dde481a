"""Benchmarks: the Fig. 6 alpha sweep and speed (``make bench``). They print; they never fail
on time.

The accuracy suite over 20 seeds (every scene, every way of registering) is
``test_bench_accuracy.py``; accuracy figures are asserted in ``tests/recon/test_accuracy.py``.
"""

from __future__ import annotations

import statistics
import time
from functools import partial

import numpy as np
import pytest

from recon import reconstruct as R
from recon import scenes
from recon.classify import classify_segments
from recon.evaluation import registered_truth
from recon.methods.anchored import anchored_segment
from recon.metrics import score_path
from recon.transforms import apply_transform
from recon.types import ReconParams
from tests.reference_loop import anchored_segment_loop

pytestmark = pytest.mark.bench

MM = 1e-3


#: Seeds of the Fig. 6 sweep (every accuracy table is over 20 seeds: median and worst).
FIG6_SEEDS = 20


@pytest.mark.timeout(1800)
def test_alpha_sweep_fig6():
    """The paper's Fig. 6: path and scan of varying quality, fixed alphas and auto, over seeds."""
    print(
        f"\n## Fig. 6: alpha against path and scan quality (registered-frame mean error, mm; "
        f"median / worst of {FIG6_SEEDS} seeds)\n"
    )
    alphas = (1.0, 0.75, 0.5, 0.25, 0.0, "auto")
    print(
        "| path noise | scan noise | "
        + " | ".join(f"alpha={a}" for a in alphas)
        + " | auto's median alpha |"
    )
    print("|---|---|" + "---:|" * (len(alphas) + 1))
    for path_scale in (0.5, 2.0):
        for scan_noise in (0.2 * MM, 1.5 * MM):
            errors = {alpha: [] for alpha in alphas}
            auto_alpha = []
            for seed in range(FIG6_SEEDS):
                scene = scenes.polynomial_ridge(
                    seed, path_noise_scale=path_scale, scan_noise_m=scan_noise
                )
                for alpha in alphas:
                    recon = R.reconstruct(
                        scene.recording, scene.scan, params=ReconParams(alpha=alpha)
                    )
                    truth = registered_truth(scene, recon)
                    # Across the path, as the accuracy suite's registered frame.
                    score = score_path(recon.points_m, truth, extend_ends_m=0.03)
                    errors[alpha].append(score.mean_m)
                auto_alpha.append(float(np.median(recon.alpha)))
            print(
                f"| x{path_scale} | {scan_noise / MM:.1f} mm | "
                + " | ".join(
                    f"{np.median(errors[a]) / MM:.3f} / {max(errors[a]) / MM:.3f}" for a in alphas
                )
                + f" | {np.median(auto_alpha):.2f} |"
            )


def _median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


#: The per-point loop is timed on at most this many points and scaled linearly.
LOOP_POINTS = 3000


def test_speed_table():
    print("\n## Speed (seconds, median of repeats on this machine)\n")
    print(
        "| path points | scan points | whole reconstruction | per-point stage, vectorised "
        "| per-point stage, loop | loop / vectorised |"
    )
    print("|---:|---:|---:|---:|---:|---:|")
    for n_path in (1_000, 10_000, 100_000):
        for n_scan in (100_000, 1_000_000):
            scene = scenes.long_edge(n_path, n_scan)
            params = ReconParams()
            repeats = 3 if n_path * n_scan <= 10_000 * 1_000_000 else 1
            total = _median_time(
                partial(R.reconstruct, scene.recording, scene.scan, params=params), repeats
            )
            # The per-point stage on its own, vectorised and looped, on the same scan model.
            plan = R.plan_segments(scene.recording, params)
            points, bounds, half = plan.resampled.points_m, plan.bounds, plan.half_width
            prepared = R.prepare_scan_model(points, scene.scan, bounds, params)
            model, T = prepared.model, prepared.T_scan_tracker
            work = apply_transform(T, points)
            kind = classify_segments(work, bounds, model, params)[0].kind
            start, stop = bounds[0]
            seg = work[start:stop]
            vector = _median_time(
                partial(anchored_segment, seg, kind, model, params, half), repeats
            )
            sub = seg[:LOOP_POINTS]
            loop = (
                _median_time(partial(anchored_segment_loop, sub, kind, model, params, half), 1)
                * len(seg)
                / len(sub)
            )
            scaled = "*" if len(seg) > LOOP_POINTS else ""
            print(
                f"| {n_path:,} | {n_scan:,} | {total:.2f} | {vector:.3f} | {loop:.1f}{scaled} "
                f"| {loop / vector:.0f}x |"
            )
    print(f"\n\\* loop timed on {LOOP_POINTS} points and scaled to the path's length.")
