"""The accuracy suite (``make bench``): every scene of ``recon.scenes.ACCURACY_SCENES`` over 20
seeds, every variant, tracker frame first, ends apart, median and worst seed (see
:mod:`recon.accuracy`). It prints; targets are asserted on seeded scenes in
``tests/recon/test_accuracy.py``."""

from __future__ import annotations

import os
import time

import pytest

from recon import scenes
from recon.accuracy import format_suite, run_suite

pytestmark = pytest.mark.bench

#: Seeds per scene (TEACHPATH_BENCH_SEEDS overrides it for a quick look).
SEEDS = int(os.environ.get("TEACHPATH_BENCH_SEEDS", "20"))


@pytest.mark.timeout(3600)
def test_accuracy_suite():
    start = time.perf_counter()
    rows = run_suite(scenes.ACCURACY_SCENES, range(SEEDS))
    print(
        f"\n## Accuracy over {SEEDS} seeds per scene (mm; tracker frame unless said; "
        "median / worst seed)\n"
    )
    print(format_suite(rows))
    refused = [(r.scene, r.variant, seed, why) for r in rows for seed, why in r.refused]
    if refused:
        print("\nRefused (the variant said why, nothing was made):\n")
        for scene, variant, seed, why in refused:
            print(f"- {scene}, {variant}, seed {seed}: {why}")
    print(f"\n({time.perf_counter() - start:.0f} s)")
