"""The real-parts benchmark (``make bench``): every traceable curve of the corpus's CAD parts,
scanned by the simulated hand-held depth camera and traced by hand, every way of reconstructing,
scored against the true curve in the tracker frame. Prints the tables of ``docs/real-parts.md``.

Three kinds of trace (``recon.scenes.cad``): along the edge, past the edge's ends (1.5 mm), on a
face 4 mm beside it. Variants: the scanner registered from the trace, its pose known, registered
by 7 touches, no scan (path only, against the best Savitzky-Golay filter in hindsight), and the
trace's best rigid fit to the truth (what any registration from the trace leaves at best).
Curves are grouped by whether the scan shows both faces of the edge along most of it (where the
scan defines the edge) or one.

``TEACHPATH_BENCH_SEEDS`` (default 2) and ``TEACHPATH_BENCH_KINDS`` (default all three) narrow
it for a quick look. Without the corpus it skips, saying so.
"""

from __future__ import annotations

import os
import time
from collections import defaultdict

import pytest

from tests.corpus import require_corpus

pytestmark = pytest.mark.bench

SEEDS = int(os.environ.get("TEACHPATH_BENCH_SEEDS", "2"))
KINDS = tuple(os.environ.get("TEACHPATH_BENCH_KINDS", "edge,past_ends,face").split(","))
VARIANTS = ("trace", "known", "touches", "path", "oracle")


@pytest.mark.timeout(4 * 3600)
def test_real_parts():
    require_corpus()
    from tests.realparts import benchmark_choices, per_curve_table, run, summary_table

    start = time.perf_counter()
    choices = benchmark_choices()
    defined = {c.case.name for c in choices if c.scan_defines_edge}
    print(
        f"\n## Real parts: {len(choices)} curves of {len({c.case.part.name for c in choices})} "
        f"parts, {SEEDS} seeds, traces {', '.join(KINDS)} (mm, tracker frame)\n"
    )
    print("| curve | edge | dihedral | length | both faces seen |")
    print("|---|---|---:|---:|---:|")
    for c in choices:
        profile = c.case.profile
        print(
            f"| {c.case.name} | {'concave' if profile.concave else 'convex'} "
            f"| {profile.dihedral_deg:.0f} deg | {c.case.length_m * 1e3:.0f} mm "
            f"| {c.defined * 100:.0f} % |"
        )
    skipped: list[tuple[str, str]] = []
    scores = run(
        [c.case for c in choices], range(SEEDS), kinds=KINDS, variants=VARIANTS, skipped=skipped
    )
    if skipped:
        print("\nNo face trace (no flat stretch of face beside the curve):\n")
        for _name, reason in skipped:
            print(f"- {reason}")

    def curve_of(score):
        return score.scene.split(":")[0]

    def kind_of(score):
        return score.scene.split(":")[1].split("/")[0]

    for kind in KINDS:
        of_kind = [s for s in scores if kind_of(s) == kind]
        if not of_kind:
            continue
        print(f"\n### Traced {kind}: every curve\n")
        print(summary_table(of_kind))
        for label, group in (
            ("the scan shows both faces (defines the edge)", True),
            ("the scan shows one face along much of it", False),
        ):
            rows = [s for s in of_kind if (curve_of(s) in defined) == group]
            if rows:
                print(f"\n### Traced {kind}: {label}\n")
                print(summary_table(rows))
    print("\n### Per part (all kinds)\n")
    by_part = defaultdict(list)
    for s in scores:
        by_part[curve_of(s).split("#")[0]].append(s)
    for part, rows in by_part.items():
        print(f"\n#### {part}\n")
        print(summary_table(rows))
    print("\n### Per curve and seed (traced along the edge)\n")
    print(per_curve_table([s for s in scores if kind_of(s) == "edge"]))
    refused = [s for s in scores if s.refused]
    if refused:
        print("\nRefused (the variant said why, nothing was made):\n")
        for s in refused:
            print(f"- {s.scene}, {s.variant}: {s.refused}")
    print(f"\n({time.perf_counter() - start:.0f} s)")
