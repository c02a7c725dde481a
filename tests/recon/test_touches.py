"""The scanner registered by touching the workpiece: rests found, registered against ground truth,
the motions they fix named, refusals where they fix too little."""

import numpy as np
import pytest

from recon import scenes
from recon.errors import RegistrationError, TouchesInsufficientError
from recon.metrics import score_path
from recon.reconstruct import reconstruct, touches_for_trace
from recon.touches import find_dwells, register_touches
from recon.transforms import apply_transform, invert_transform
from recon.types import Recording

MM = 1e-3


def _rests(points, durations_s, *, rate_hz=120.0, noise_m=0.05 * MM, move_s=0.4, seed=0):
    """A tip resting at each point for its duration, moving in straight lines between them."""
    rng = np.random.default_rng(seed)
    samples = []
    for k, (p, d) in enumerate(zip(points, durations_s, strict=True)):
        samples.append(p + noise_m * rng.standard_normal((int(d * rate_hz), 3)))
        if k + 1 < len(points):
            u = np.linspace(0, 1, int(move_s * rate_hz), endpoint=False)[1:]
            samples.append(p + u[:, None] * (points[k + 1] - p))
    positions = np.concatenate(samples)
    return positions, np.arange(len(positions)) / rate_hz


def test_rests_of_the_tip_are_found_and_averaged():
    points = np.array([[0.0, 0, 0], [0.05, 0, 0], [0.05, 0.04, 0], [0.0, 0.04, 0.01]])
    positions, t = _rests(points, [0.5, 0.8, 0.35, 1.0])
    dwells, notes = find_dwells(positions, t)
    assert len(dwells) == 4 and notes == []
    found = np.array([d.point_m for d in dwells])
    np.testing.assert_allclose(found, points, atol=0.03 * MM)  # 0.05 mm noise, 40+ samples
    assert all(d.spread_m < 0.2 * MM for d in dwells)
    # Shorter than 0.3 s is not a rest; a sliding tip is reported and left out.
    short, _ = find_dwells(*_rests(points[:2], [0.2, 0.2]))
    assert short == []


def test_a_tip_that_wanders_while_resting_is_named_and_left_out():
    positions, t = _rests(np.array([[0.0, 0, 0], [0.05, 0, 0]]), [4.0, 0.6])
    wander = t < 4.0
    # 1.5 mm to and fro at 0.25 Hz: under 3 mm/s, so not a move, but no rest either.
    positions[wander, 2] += 0.0015 * np.sin(0.5 * np.pi * t[wander])
    dwells, notes = find_dwells(positions, t)
    assert len(dwells) == 1 and "slid" in notes[0]
    np.testing.assert_allclose(dwells[0].point_m, [0.05, 0, 0], atol=0.02 * MM)


@pytest.mark.parametrize("name", ["box_corner", "corner_60", "bend_40"])
def test_touches_recover_the_scanner_against_ground_truth(name):
    """Six touches on three faces, tip noise 0.07 mm, pivot error 0.1 mm, a scanner misplaced
    by 2 mm / 1 degree: the truth moved by the remaining error stays within 0.5 mm."""
    for seed in range(3):
        scene = scenes.ACCURACY_SCENES[name](seed)
        touch = scenes.touch_recording(scene, seed)
        dwells, _ = find_dwells(touch.recording.points_m, touch.recording.t_s)
        assert len(dwells) == len(touch.points_m)
        result = register_touches(
            np.array([d.point_m for d in dwells]),
            scene.scan.points_m,
            T_scan_tracker_init=np.eye(4),
        )
        error = invert_transform(result.T_scan_tracker) @ scene.T_scan_tracker
        moved = apply_transform(error, scene.truth_m)
        assert score_path(moved, scene.truth_m).max_m < 0.5 * MM, (name, seed)
        assert result.fixed_motions >= 5
        assert np.all(np.abs(result.residual_m[result.used]) < 0.3 * MM)


def test_touches_on_one_plate_fix_three_motions_and_name_the_others():
    scene = scenes.flat_liftoff(0)
    touch = scenes.touch_recording(scene, 0)
    dwells, _ = find_dwells(touch.recording.points_m, touch.recording.t_s)
    result = register_touches(
        np.array([d.point_m for d in dwells]), scene.scan.points_m, T_scan_tracker_init=np.eye(4)
    )
    assert result.fixed_motions == 3
    assert sorted(m.split(" ")[0] for m in result.free_motions) == ["sliding", "sliding", "turning"]
    # What they fix, they fix: the plate's height at the path.
    error = invert_transform(result.T_scan_tracker) @ scene.T_scan_tracker
    assert np.abs(apply_transform(error, scene.truth_m)[:, 2]).max() < 0.4 * MM


def test_a_touch_off_the_workpiece_is_left_out_and_named():
    scene = scenes.box_corner(0)
    touch = scenes.touch_recording(scene, 0)
    dwells, _ = find_dwells(touch.recording.points_m, touch.recording.t_s)
    points = np.array([d.point_m for d in dwells])
    # A seventh, 3 mm above the top (the tip lifted off): six touches fix six motions, the
    # seventh is the one that can disagree.
    points = np.vstack([points, [0.05, 0.04, 0.003]])
    result = register_touches(points, scene.scan.points_m, T_scan_tracker_init=np.eye(4))
    assert not result.used[-1] and result.used[:-1].all()
    assert any("touch 7" in note for note in result.notes)


def test_too_few_touches_are_refused_with_what_to_do():
    scene = scenes.box_corner(0)
    with pytest.raises(RegistrationError, match="at least 3 are needed"):
        register_touches(
            np.array([[0.05, 0.04, 0.0], [0.06, 0.04, 0.0]]),
            scene.scan.points_m,
            T_scan_tracker_init=np.eye(4),
        )


def test_touches_that_leave_free_what_the_trace_needs_are_refused():
    """Only the box's top touched: sliding in the plane is free, and the path along two top
    edges needs it fixed."""
    scene = scenes.box_corner(0)
    rng = np.random.default_rng(3)
    top = np.column_stack([rng.uniform(0.01, 0.09, 5), rng.uniform(0.01, 0.07, 5), np.zeros(5)])
    with pytest.raises(TouchesInsufficientError, match="sliding along") as refused:
        touches_for_trace(scene.recording, top, scene.scan)
    assert "touch a face that faces" in str(refused.value)


def test_a_reconstruction_with_touches_keeps_the_drift_out_of_where_the_robot_goes():
    """Tracker frame, ground truth: registered by touches the result is within half a
    millimetre; registered by the trace it keeps the rigid part of the hand's drift."""
    scene = scenes.box_corner(1)
    touch = scenes.touch_recording(scene, 1)
    dwells, _ = find_dwells(touch.recording.points_m, touch.recording.t_s)
    touches = touches_for_trace(scene.recording, np.array([d.point_m for d in dwells]), scene.scan)
    touched = reconstruct(scene.recording, scene.scan, touches=touches)
    traced = reconstruct(scene.recording, scene.scan)
    raw = score_path(scene.recording.points_m, scene.truth_m)
    with_touches = score_path(touched.points_m, scene.truth_m)
    assert touched.registration.target == "touches"
    assert with_touches.max_m < 0.5 * MM
    assert with_touches.mean_m < 0.3 * raw.mean_m
    assert with_touches.mean_m < score_path(traced.points_m, scene.truth_m).mean_m
    # Its uncertainty says so too.
    assert np.median(touched.uncertainty_m) < np.median(traced.uncertainty_m)


def test_a_recording_without_times_has_no_rests_to_find():
    with pytest.raises(ValueError):
        find_dwells(np.zeros((10, 3)), np.zeros(9))
    assert find_dwells(np.zeros((1, 3)), np.zeros(1)) == ([], [])
    recording = Recording(points_m=np.zeros((3, 3)) + np.arange(3)[:, None] * 0.01)
    assert recording.t_s is None


def test_stretches_above_the_uncertainty_tolerance_are_named_merged_and_counted():
    from recon.reconstruct import MAX_UNCERTAINTY_NOTES, uncertainty_notes

    arc = np.arange(400) * MM
    u = np.full(400, 0.2 * MM)
    u[10:20] = 0.7 * MM
    u[25:30] = 0.6 * MM  # 5 points after the first stretch: the same stretch to an operator
    notes = uncertainty_notes(u, arc, tolerance_m=0.5 * MM)
    assert notes == [
        "points 10-29 (10-29 mm along the path): uncertainty up to 0.70 mm, above the "
        "0.50 mm tolerance"
    ]
    many = np.full(400, 0.2 * MM)
    many[::30] = 0.9 * MM  # 14 separate stretches
    notes = uncertainty_notes(many, arc, tolerance_m=0.5 * MM)
    assert len(notes) == MAX_UNCERTAINTY_NOTES + 1
    assert notes[-1].startswith(f"and {14 - MAX_UNCERTAINTY_NOTES} more stretches")
    assert uncertainty_notes(u, arc, tolerance_m=1 * MM) == []


@pytest.mark.parametrize("n_touches, checked", [(6, False), (9, True)])
def test_touches_without_a_spare_say_their_residual_checks_nothing(n_touches, checked):
    """Six touches for six motions: the fit passes through every one (residual 0), which an
    operator must not read as a perfect calibration."""
    scene = scenes.box_corner(1)
    touch = scenes.touch_recording(scene, 1, n_touches=n_touches)
    dwells, _ = find_dwells(touch.recording.points_m, touch.recording.t_s)
    touches = touches_for_trace(scene.recording, np.array([d.point_m for d in dwells]), scene.scan)
    registration = reconstruct(scene.recording, scene.scan, touches=touches).registration
    assert registration.constrained_dof == 6
    assert ("residual checks nothing" in registration.reason) is not checked
    if not checked:
        assert registration.rmse_m < 1e-6  # what the words explain
