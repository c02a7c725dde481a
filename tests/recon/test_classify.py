"""Segment kinds: a string enum, so stored segments read and compare as plain strings."""

import json
from dataclasses import asdict

import pytest

from recon import scenes
from recon.classify import SegmentKind, classify_segments
from recon.recon_params import ReconParams
from recon.reconstruct import plan_segments, prepare_scan_model
from recon.results import Segment
from recon.transforms import apply_transform


def test_segment_json_keeps_the_plain_strings():
    segments = [Segment(0, 10, kind, 0.5) for kind in SegmentKind]
    text = json.dumps([asdict(s) for s in segments])
    assert [s["kind"] for s in json.loads(text)] == ["edge", "surface", "path"]
    assert json.dumps(SegmentKind.EDGE) == '"edge"' and str(SegmentKind.PATH) == "path"


def test_kinds_compare_equal_to_their_strings_and_are_read_back_from_them():
    assert SegmentKind.EDGE == "edge" and SegmentKind.SURFACE != "edge"
    read_back = Segment(**json.loads(json.dumps(asdict(Segment(3, 9, SegmentKind.SURFACE, 0.1)))))
    assert read_back.kind is SegmentKind.SURFACE
    assert read_back == Segment(3, 9, SegmentKind.SURFACE, 0.1)
    with pytest.raises(ValueError, match="'ridge' is not a valid SegmentKind"):
        Segment(0, 4, "ridge", 0.0)


def test_the_box_corner_segments_follow_edges_and_the_trace_without_a_scan_nothing():
    scene = scenes.box_corner(0)
    params = ReconParams()
    plan = plan_segments(scene.recording, params)
    points = plan.resampled.points_m
    prepared = prepare_scan_model(points, scene.scan, plan.bounds, params)
    model, T = prepared.model, prepared.T_scan_tracker
    classes = classify_segments(apply_transform(T, points), plan.bounds, model, params)
    assert [c.kind for c in classes] == [SegmentKind.EDGE, SegmentKind.EDGE]
    assert all(c.edge_fraction > 0.9 for c in classes)
    far = apply_transform(T, points) + [0.0, 0.0, 0.5]  # half a metre above the workpiece
    assert [c.kind for c in classify_segments(far, plan.bounds, model, params)] == [
        SegmentKind.PATH,
        SegmentKind.PATH,
    ]


def _viterbi_step_by_step(ids, offsets, distances):
    """The corner chosen at each point by the plain Viterbi pass, one step at a time (the
    classifier's pass before it computed its transitions in blocks)."""
    import numpy as np

    from recon import classify as c_

    n, c = ids.shape
    emit = np.concatenate(
        [
            np.where(np.isfinite(distances), (distances / c_.FOLLOW_SIGMA_M) ** 2, np.inf),
            np.full((n, 1), (c_.NO_CORNER_COST_M / c_.FOLLOW_SIGMA_M) ** 2),
        ],
        axis=1,
    )
    cost, back = emit[0].copy(), np.zeros((n, c + 1), np.int64)
    for i in range(1, n):
        step = offsets[i][None, :, :] - offsets[i - 1][:, None, :]
        trans = np.full((c + 1, c + 1), c_.ENTER_COST)
        trans[:c, :c] = np.einsum("abk,abk->ab", step, step) / c_.OFFSET_STEP_SIGMA_M**2
        trans[c, c] = 0.0
        total = cost[:, None] + trans
        back[i] = np.argmin(total, axis=0)
        cost = total[back[i], np.arange(c + 1)] + emit[i]
    state = np.empty(n, np.int64)
    state[-1] = int(np.argmin(cost))
    for i in range(n - 1, 0, -1):
        state[i - 1] = back[i, state[i]]
    return state


@pytest.mark.parametrize("block", [1, 3, 4096])
def test_the_edge_choice_is_the_plain_viterbi_pass_whatever_its_blocks(block, monkeypatch):
    """Transitions computed a block at a time (any block, across its boundaries) choose the same
    corners, with the same margins to the next candidate, as a step-by-step pass."""
    import numpy as np

    from recon import classify as c_

    rng = np.random.default_rng(4)
    n, c = 40, c_.CANDIDATES
    ids = np.tile(np.arange(c), (n, 1))
    # Two corners 1.5 mm apart that the trace hops between, the rest far or missing.
    offsets = rng.normal(0.0, 0.3e-3, (n, c, 3))
    offsets[:, 1] += [1.5e-3, 0.0, 0.0]
    offsets[:, 2:] += [5e-3, 0.0, 0.0]
    distances = np.linalg.norm(offsets, axis=2)
    distances[rng.random((n, c)) < 0.3] = np.inf
    monkeypatch.setattr(c_, "VITERBI_BLOCK", block)
    choice = c_._choose_edge((ids, offsets, distances), slice(0, n), n)
    state = _viterbi_step_by_step(ids, offsets, distances)
    on = state != c
    assert choice is not None and on.any()
    assert choice.corners == tuple(sorted({int(x) for x in ids[on, state[on]]}))
    assert choice.coverage == pytest.approx(np.count_nonzero(on) / n)
    rows = np.flatnonzero(on)
    assert choice.rms_m == float(np.median(distances[rows, state[rows]]))
    margins = []
    for row in rows:
        rest = [j for j in range(c) if j != state[row] and np.isfinite(distances[row, j])]
        if rest:
            gaps = np.linalg.norm(offsets[row, rest] - offsets[row, state[row]], axis=1)
            margins.append(float(gaps.min()))
    assert choice.next_m == (float(np.median(margins)) if margins else float("inf"))
