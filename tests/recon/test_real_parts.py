"""The real-parts bars on a few curves of the corpus's CAD parts (``make test``'s share of the
real-parts benchmark, ``tests/bench/test_bench_real_parts.py``).

Each scene is a part of ``../shared/corpus/groundtruth`` scanned by the simulated hand-held depth
camera (:mod:`recon.scenes.depth_camera`) and a hand trace along one of its true feature curves
(:func:`recon.scenes.cad.cad_scene`). Errors are to the true curve, in the tracker frame (what the
robot gets). The curves are ones whose scan shows both faces of the edge, where the bars apply
in full; the benchmark has the one-sided ones too. Without the corpus these tests skip, saying so.
"""

from __future__ import annotations

import numpy as np
import pytest

from recon.metrics import distance_to_curve
from recon.results import PointReason
from tests.corpus import corpus_dir, require_corpus

MM = 1e-3

#: (part, curve index, seed): a fan's sharp convex edge, a block's edge, a casting's rim.
CURVES = [("fandisk", 1, 0), ("block", 5, 1), ("casting", 18, 0)]


def _case(part: str, index: int):
    from tests.realparts import benchmark_cases

    require_corpus()
    (case,) = [c for c in benchmark_cases((part,)) if c.index == index]
    return case


@pytest.fixture(scope="module", params=CURVES, ids=lambda c: f"{c[0]}#{c[1]}/{c[2]}")
def scored(request):
    """Every variant on one curve: {variant: CurveScore}."""
    from tests.realparts import scene_of, score

    part, index, seed = request.param
    scene = scene_of(_case(part, index), seed, "edge")
    return {v: score(scene, v, seed) for v in ("known", "trace", "path")}


@pytest.mark.slow
def test_the_curves_are_ones_the_scan_defines():
    """The chosen curves are traceable and the simulated scan shows both faces of each (what
    the bars below are for); the benchmark reports the others apart."""
    from recon.scenes.cad import traceable_cases
    from tests.corpus import load_part

    require_corpus()
    for part, index, _ in CURVES:
        (choice,) = [c for c in traceable_cases(load_part(part)) if c.case.index == index]
        assert choice.scan_defines_edge, (part, index, choice.defined)


@pytest.mark.slow
def test_with_the_scanner_pose_known_the_path_is_within_a_millimetre(scored):
    known = scored["known"]
    assert not known.refused, known.refused
    assert known.ratio <= 0.35, known  # the bar's median, held by each of these curves
    assert known.max_m <= 1.0 * MM, known
    assert max(known.start_max_m, known.end_max_m) <= 1.0 * MM, known
    assert known.unflagged_far == 0, known
    assert known.covered_2sigma >= 0.90, known


@pytest.mark.slow
def test_registered_from_the_trace_never_worse_than_the_trace(scored):
    trace = scored["trace"]
    assert not trace.refused, trace.refused
    assert trace.ratio < 1.0, trace
    assert trace.unflagged_far == 0, trace
    assert trace.covered_2sigma >= 0.90, trace


@pytest.mark.slow
def test_path_only_is_no_worse_than_the_trace(scored):
    path = scored["path"]
    assert path.ratio < 1.0, path


# -- a trace that runs past the feature's ends, a trace on a face -----------------------------


@pytest.fixture(scope="module")
def past_ends():
    """A fan's convex edge traced from 1.5 mm before its start to 1.5 mm past its end, the
    scanner's pose known."""
    from dataclasses import replace

    from recon.recon_params import ReconParams
    from recon.reconstruct import reconstruct
    from tests.realparts import scene_of

    scene = scene_of(_case("fandisk", 15), 0, "past_ends")
    out = reconstruct(
        scene.recording,
        scene.scan,
        params=replace(ReconParams(), register=False),
        T_scan_tracker_init=scene.T_scan_tracker,
    )
    return scene, out


@pytest.mark.slow
def test_past_the_feature_s_ends_no_jog_and_the_summary_says_what_was_done(past_ends):
    """Where the trace runs on past the edge's end, the end is continued along the edge's line
    (a bounded length) or left to the trace, never pulled sideways, and the summary names which
    and how many points."""
    scene, out = past_ends
    # The truth runs on along the edge's line as far as the trace does.
    error = distance_to_curve(out.points_m, scene.truth_m)
    beyond = np.isin(out.reason, [int(PointReason.CONTINUED), int(PointReason.PAST_END)])
    assert np.any(beyond)
    assert error.max() <= 1.0 * MM
    assert max(error[:10].max(), error[-10:].max()) <= 1.0 * MM
    # No jog: consecutive output points are never farther apart than the trace's own steps
    # allow, plus the hand's error.
    steps = np.linalg.norm(np.diff(out.points_m, axis=0), axis=1)
    trace_steps = np.linalg.norm(np.diff(out.input_points_m, axis=0), axis=1)
    assert steps.max() <= trace_steps.max() + 0.8 * MM
    said = [note for note in out.notes if "runs on past the scan's edge" in note]
    assert said and all("continued along the scan's edge line" in note for note in said), said


def test_a_trace_on_a_face_beside_an_edge_stays_on_that_face():
    """A trace on one face a few millimetres from an edge: its height comes from that face,
    never from a fit across the edge."""
    from dataclasses import replace

    from recon.recon_params import ReconParams
    from recon.reconstruct import reconstruct
    from tests.realparts import scene_of

    scene = scene_of(_case("block", 5), 0, "face")
    out = reconstruct(
        scene.recording,
        scene.scan,
        params=replace(ReconParams(), register=False),
        T_scan_tracker_init=scene.T_scan_tracker,
    )
    height = np.abs(scene.surface_height(out.points_m))
    raw = np.abs(scene.surface_height(scene.recording.points_m))
    assert np.median(height) < 0.5 * np.median(raw)
    assert height.max() <= 1.0 * MM


def test_the_corpus_location_is_reported_when_absent(monkeypatch, tmp_path):
    """Without the corpus the tests above skip with a message that says where it was looked
    for (CI has it beside the checkout)."""
    import tests.corpus as corpus

    monkeypatch.setenv(corpus.CORPUS_ENV, str(tmp_path))
    monkeypatch.setattr(corpus, "ROOT", tmp_path / "nowhere" / "checkout")
    assert corpus_dir() is None
    with pytest.raises(pytest.skip.Exception, match="the external corpus is absent"):
        require_corpus()
