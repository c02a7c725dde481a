"""Benchmarks: the Fig. 6 alpha sweep (``make bench``). They print; they never fail.

Speed, as a user times it (whole commands), is ``test_bench_speed.py``.

The accuracy suite over 20 seeds (every scene, every way of registering) is
``test_bench_accuracy.py``; accuracy figures are asserted in ``tests/recon/test_accuracy.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

from recon import reconstruct as R
from recon import scenes
from recon.evaluation import registered_truth
from recon.metrics import score_path
from recon.recon_params import ReconParams

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
