"""Corners: candidates from the trace, judged by sharpness without a scan and by the scan's edges
with one; segments meet on one point."""

import numpy as np
import pytest
from scipy.signal import find_peaks

from recon import scenes
from recon.corners import (
    Candidate,
    find_candidates,
    judge_without_scan,
    local_peaks,
    turning_angle_deg,
)
from recon.metrics import score_path
from recon.recon_params import ReconParams
from recon.reconstruct import reconstruct
from recon.transforms import apply_transform

MM = 1e-3


def _polyline_turn(turn_deg: float, *, bend_radius_m: float = 0.0, n_leg: int = 60):
    """Two 60 mm legs at 1 mm spacing turning left by ``turn_deg``, sharply or on an arc."""
    from recon.scenes.outlines import outline

    length = 2 * n_leg * MM + bend_radius_m * np.radians(turn_deg)
    s = np.arange(0.0, length + 1e-12, MM)
    points, _ = outline(
        s,
        leg_a_m=n_leg * MM,
        leg_b_m=n_leg * MM,
        turn_deg=turn_deg,
        bend_radius_m=bend_radius_m,
    )
    return points


def test_turning_angle_of_a_right_angle_is_ninety_degrees():
    points = _polyline_turn(90.0)
    angle = turning_angle_deg(points, half_window=4)
    assert angle.max() == pytest.approx(90.0, abs=1e-6)
    assert np.argmax(angle) == 60


@pytest.mark.parametrize("turn", [60.0, 90.0, 120.0])
def test_a_sharp_turn_is_one_sharp_candidate_that_splits_without_a_scan(turn):
    (candidate,) = find_candidates(
        _polyline_turn(turn), spacing_m=MM, angle_deg=50.0, scale_m=4 * MM
    )
    assert candidate.index == 60
    assert candidate.sharp
    assert candidate.long_angle_deg == pytest.approx(turn, abs=1e-6)
    judged = judge_without_scan(candidate, angle_deg=50.0)
    assert judged.split and "sharply" in judged.reason


@pytest.mark.parametrize("radius_mm", [6.0, 7.0])
def test_a_tight_rounded_turn_keeps_turning_over_longer_chords_and_is_not_split(radius_mm):
    candidates = find_candidates(
        _polyline_turn(90.0, bend_radius_m=radius_mm * MM),
        spacing_m=MM,
        angle_deg=50.0,
        scale_m=4 * MM,
    )
    assert candidates, "a 90 degree turn on a small radius is a candidate"
    for candidate in candidates:
        assert not candidate.sharp
        assert candidate.long_angle_deg > 1.5 * candidate.angle_deg
        assert not judge_without_scan(candidate, angle_deg=50.0).split
        assert "rounded bend" in judge_without_scan(candidate, angle_deg=30.0).reason


def test_a_smooth_circle_has_no_candidates():
    a = np.linspace(0, 2 * np.pi, 315)
    points = np.column_stack([0.05 * np.cos(a), 0.05 * np.sin(a), np.zeros_like(a)])
    assert find_candidates(points, spacing_m=MM, angle_deg=50.0, scale_m=4 * MM) == []


def test_a_turn_below_the_threshold_is_not_split_without_a_scan():
    judged = judge_without_scan(Candidate(10, 40.0, 41.0), angle_deg=50.0)
    assert not judged.split and "less than the corner threshold" in judged.reason


@pytest.mark.parametrize("seed", range(8))
def test_local_peaks_agree_with_scipy_find_peaks(seed):
    """An independent implementation: scipy.signal.find_peaks with height and distance."""
    rng = np.random.default_rng(seed)
    values = np.convolve(rng.uniform(0, 100, 400), np.ones(5) / 5, mode="same")
    # Plateaus (equal neighbours) too; no two peaks of equal height, where the two may break
    # the tie differently.
    for start in rng.integers(0, 395, 6):
        values[start : start + 3] = 80.0 + rng.uniform(0, 20)
    ours = local_peaks(values, height=50.0, distance=8)
    theirs, _ = find_peaks(values, height=50.0, distance=8)
    np.testing.assert_array_equal(ours, theirs)


@pytest.mark.parametrize("name", ["box_corner", "corner_60", "corner_120"])
def test_the_scan_places_the_corner_where_its_edges_meet(name):
    """Scan frame: the corner point from the scan's two edge lines is the workpiece's corner
    (independent of how well the trace was registered)."""
    for seed in range(3):
        scene = scenes.ACCURACY_SCENES[name](seed)
        recon = reconstruct(scene.recording, scene.scan)
        (corner,) = [c for c in recon.corners if c.split]
        assert corner.point_m is not None, corner.reason
        in_scan = apply_transform(recon.T_scan_tracker, np.array([corner.point_m]))[0]
        truth = apply_transform(scene.T_scan_tracker, scene.corners_m)[0]
        assert np.linalg.norm(in_scan - truth) < 1.0 * MM, (name, seed)
        # Both segments end on it: no spike where they meet.
        first, second = recon.segments
        assert first.stop - 1 == second.start
        np.testing.assert_allclose(recon.points_m[second.start], corner.point_m, atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("radius_mm", [15, 40])
def test_rounded_bends_are_never_split_with_or_without_a_scan(radius_mm):
    for with_scan in (True, False):
        for seed in range(6):
            scene = scenes.turning_edge(seed, bend_radius_m=radius_mm * MM, with_scan=with_scan)
            params = ReconParams() if with_scan else ReconParams(radius_m=0.016)
            recon = reconstruct(scene.recording, scene.scan, params=params)
            assert len(recon.segments) == 1, (radius_mm, with_scan, seed, recon.corners)


def test_a_trace_that_only_looks_sharp_is_not_split_where_the_scan_runs_straight():
    """A hand that hesitates on a straight edge draws a kink; the scan's edge runs straight."""
    scene = scenes.polynomial_ridge(0)
    points = scene.recording.points_m.copy()
    n = len(points)
    kink = np.zeros((n, 3))
    mid = n // 2
    kink[mid : mid + 12, 1] = np.linspace(0, 4 * MM, 12)
    kink[mid + 12 : mid + 24, 1] = np.linspace(4 * MM, 0, 12)
    from recon.inputs import Recording

    recording = Recording(points_m=points + kink, t_s=scene.recording.t_s)
    recon = reconstruct(recording, scene.scan)
    assert recon.corners, "the kink is a candidate"
    assert not any(c.split for c in recon.corners)
    assert any("not split" in c.reason for c in recon.corners)
    assert score_path(recon.points_m, scene.truth_m).max_m < 2.0 * MM


def test_a_corner_near_the_start_of_a_path_without_a_scan_is_joined():
    """Six millimetres, then a right angle: the first segment is shorter than the lines the
    join fits (it crashed once)."""
    from recon.inputs import Recording

    first = np.column_stack([np.arange(6) * MM, np.zeros(6), np.zeros(6)])
    second = np.column_stack([np.full(40, 5 * MM), np.arange(1, 41) * MM, np.zeros(40)])
    recon = reconstruct(Recording(points_m=np.concatenate([first, second])))
    assert [c.split for c in recon.corners] == [True]
    a, b = recon.segments
    np.testing.assert_array_equal(recon.points_m[a.stop - 1], recon.points_m[b.start])
