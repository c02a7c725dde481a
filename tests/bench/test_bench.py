"""Benchmarks: the paper's alpha variants, the Fig. 6 sweep and speed (``make bench``). They
print; they never fail on time.

The accuracy suite over 20 seeds (every scene, every way of registering) is
``test_bench_accuracy.py``; accuracy figures are asserted in ``tests/recon/test_accuracy.py``.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import replace
from functools import partial

import numpy as np
import pytest

from recon import reconstruct as R
from recon import scenes
from recon.classify import classify_segments
from recon.evaluation import default_variants, evaluate, format_table, registered_truth
from recon.methods.anchored import anchored_segment
from recon.metrics import error_stats
from recon.transforms import apply_transform
from recon.types import ReconParams
from tests.reference_loop import anchored_segment_loop

pytestmark = pytest.mark.bench

MM = 1e-3


def test_accuracy_tables():
    """The paper's Eq. (4) and ours at several alphas, seed 0 of the paper's scenes."""
    print("\n## Accuracy, seed 0, alpha variants (errors in mm; distances to the true feature)\n")
    for make in scenes.SCENES.values():
        scene = make(0)
        base, title = ReconParams(), scene.description
        if scene.scan is None:
            # Without a scan only the tremor can go: the large radius the paper suggests.
            base, title = replace(base, radius_m=0.032), f"{title} (r = 32 mm)"
        print(format_table(evaluate(scene, default_variants(base)), title=title))
        print()


def test_alpha_sweep_fig6():
    """The paper's Fig. 6: path and scan of varying quality, fixed alphas and auto."""
    print("\n## Fig. 6: alpha against path and scan quality (registered-frame mean error, mm)\n")
    alphas = (1.0, 0.75, 0.5, 0.25, 0.0, "auto")
    print(
        "| path noise | scan noise | "
        + " | ".join(f"alpha={a}" for a in alphas)
        + " | auto's median alpha |"
    )
    print("|---|---|" + "---:|" * (len(alphas) + 1))
    for path_scale in (0.5, 2.0):
        for scan_noise in (0.2 * MM, 1.5 * MM):
            scene = scenes.polynomial_ridge(0, path_noise_scale=path_scale, scan_noise_m=scan_noise)
            cells = []
            for alpha in alphas:
                recon = R.reconstruct(scene.recording, scene.scan, params=ReconParams(alpha=alpha))
                cells.append(error_stats(recon.points_m, registered_truth(scene, recon)).mean_m)
            print(
                f"| x{path_scale} | {scan_noise / MM:.1f} mm | "
                + " | ".join(f"{c / MM:.3f}" for c in cells)
                + f" | {np.median(recon.alpha):.2f} |"
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
