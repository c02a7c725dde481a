"""Several demonstrations of one path fused: against ground truth, with directions mixed, with an
outlier, and with pieces missing."""

import numpy as np
import pytest

from recon import scenes
from recon.errors import DegenerateInputError
from recon.fusion import fuse_traces
from recon.inputs import Recording
from recon.metrics import score_path
from recon.reconstruct import reconstruct

MM = 1e-3


@pytest.mark.parametrize("name", ["box_corner", "cylinder_edge", "free_curve"])
def test_fused_traces_are_closer_to_the_truth_than_each_one(name):
    for seed in range(3):
        scene = scenes.ACCURACY_SCENES[name](seed)
        traces = [scene.recording, *scene.traces(2, seed)]
        fused = fuse_traces(traces, spacing_m=1e-3)
        assert all(t.used for t in fused.traces)
        assert [t.reversed for t in fused.traces] == [False, False, True]
        errors = [score_path(t.points_m, scene.truth_m).mean_m for t in traces]
        fused_error = score_path(fused.recording.points_m, scene.truth_m).mean_m
        # Independent drifts average: the mean of three is well below the typical one.
        assert fused_error < 0.8 * np.median(errors), (name, seed)
        # The fused trace runs the first demonstration's way.
        first = traces[0].points_m
        assert np.linalg.norm(fused.recording.points_m[0] - first[0]) < 5 * MM


def test_the_fused_variance_follows_the_spread_of_the_traces():
    """Analytic: three straight traces at constant offsets of 0, +a and -a across the path
    (no noise): the mean is the middle one and its variance (2 a^2 / 3) / 3 per point."""
    x = np.linspace(0, 0.1, 101)
    a = 0.6 * MM
    traces = [
        Recording(points_m=np.column_stack([x, np.full_like(x, offset), np.zeros_like(x)]))
        for offset in (0.0, a, -a)
    ]
    fused = fuse_traces(traces, spacing_m=1e-3)
    np.testing.assert_allclose(fused.recording.points_m[:, 1], 0.0, atol=1e-9)
    # Sample variance with n - 1 = 2: (a^2 + a^2) / 2 = a^2, of the mean: a^2 / 3.
    np.testing.assert_allclose(fused.variance_m2, a**2 / 3, rtol=0.05)


def test_an_outlier_demonstration_is_left_out_and_named():
    scene = scenes.box_corner(2)
    traces = [scene.recording, *scene.traces(3, 2)]
    wrong = traces[2].points_m + [0.0, 0.006, 0.0]  # 6 mm off: another edge
    traces[2] = Recording(points_m=wrong, t_s=traces[2].t_s)
    fused = fuse_traces(traces, spacing_m=1e-3)
    assert [t.used for t in fused.traces] == [True, True, False, True]
    assert "demonstration 3 left out" in " ".join(fused.notes)
    assert fused.traces[2].mean_offset_m > 3 * MM


def test_a_demonstration_with_a_gap_is_filled_by_the_others():
    scene = scenes.box_corner(0)
    traces = [scene.recording, *scene.traces(2, 0)]
    n = len(traces[1].points_m)
    piece = np.where(np.arange(n) < n // 2, 0, 1)
    kept = (np.arange(n) < n // 2 - 60) | (np.arange(n) >= n // 2)
    traces[1] = Recording(
        points_m=traces[1].points_m[kept], t_s=traces[1].t_s[kept], piece=piece[kept]
    )
    fused = fuse_traces(traces, spacing_m=1e-3)
    steps = np.linalg.norm(np.diff(fused.recording.points_m, axis=0), axis=1)
    assert steps.max() < 2 * MM  # continuous through the gap: no jump where one trace stops
    assert fused.coverage.min() >= 2
    # Where the gap was, the fused path is no worse than the worst demonstration there.
    gap = traces[1].points_m[n // 2 - 61]
    near = np.linalg.norm(fused.recording.points_m - gap, axis=1) < 0.03
    fused_error = score_path(fused.recording.points_m[near], scene.truth_m).max_m
    worst = max(score_path(t.points_m, scene.truth_m).max_m for t in traces)
    assert fused_error <= worst


def test_demonstrations_of_different_paths_are_refused():
    a = Recording(
        points_m=np.column_stack([np.linspace(0, 0.1, 100), np.zeros(100), np.zeros(100)])
    )
    b = Recording(
        points_m=np.column_stack([np.zeros(100), np.linspace(0.2, 0.3, 100), np.zeros(100)])
    )
    with pytest.raises(DegenerateInputError, match="same path"):
        fuse_traces([a, b], spacing_m=1e-3)
    with pytest.raises(ValueError):
        fuse_traces([a], spacing_m=1e-3)


@pytest.mark.slow
def test_three_fused_demonstrations_reconstruct_better_than_one():
    scene = scenes.cylinder_edge(1)
    traces = [scene.recording, *scene.traces(2, 1)]
    fused = reconstruct(traces, scene.scan)
    single = reconstruct(scene.recording, scene.scan)
    assert len(fused.demonstrations) == 3
    assert (
        score_path(fused.points_m, scene.truth_m).mean_m
        < score_path(single.points_m, scene.truth_m).mean_m
    )


def test_a_loop_traced_both_ways_is_fused_whole():
    """A closed path: its start and end coincide, so the ends cannot tell the direction nor
    where along the path a point belongs; the passes' directions and arc lengths do."""
    a = np.linspace(0, 2 * np.pi, 629)
    loop = np.column_stack([0.05 * np.cos(a), 0.05 * np.sin(a), np.zeros_like(a)])
    rng = np.random.default_rng(0)
    traces = [
        Recording(points_m=loop + 0.3 * MM * rng.standard_normal(loop.shape)) for _ in range(3)
    ]
    traces[2] = Recording(points_m=traces[2].points_m[::-1].copy())
    fused = fuse_traces(traces, spacing_m=1e-3)
    assert [(t.used, t.reversed) for t in fused.traces] == [
        (True, False),
        (True, False),
        (True, True),
    ]
    arc = np.sum(np.linalg.norm(np.diff(fused.recording.points_m, axis=0), axis=1))
    assert arc > 0.95 * 2 * np.pi * 0.05  # all the way round
    assert score_path(fused.recording.points_m, loop).max_m < 0.6 * MM


def test_a_demonstration_of_part_of_the_path_joins_where_it_belongs():
    scene = scenes.box_corner(0)
    traces = [scene.recording, *scene.traces(2, 0)]
    traces[1] = Recording(points_m=traces[1].points_m[: len(traces[1].points_m) // 2])
    fused = fuse_traces(traces, spacing_m=1e-3)
    assert all(t.used for t in fused.traces)
    full = score_path(fused.recording.points_m, scene.truth_m)
    assert np.isfinite(full.start_max_m) and np.isfinite(full.end_max_m)  # end to end
    assert full.max_m < max(score_path(t.points_m, scene.truth_m).max_m for t in traces)
