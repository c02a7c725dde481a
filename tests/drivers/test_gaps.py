"""Cleaning a raw recording: dropouts bridged or split, outliers removed, all reported."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.errors import InputFileError
from drivers.tracking.base import SampleBatch
from drivers.tracking.gaps import GapParams, apply_tip_offset, clean_trace

RATE_HZ = 240.0


def _truth(seconds=4.0, rate_hz=RATE_HZ):
    """A pen moving along a smooth curve at ~60 mm/s, turning slowly."""
    t = np.arange(int(seconds * rate_hz)) / rate_hz
    pos = np.column_stack([0.06 * t, 0.02 * np.sin(t), 0.005 * np.cos(2 * t)])
    quat = Rotation.from_rotvec(np.column_stack([0.1 * t, 0.05 * t, 0 * t])).as_quat()
    return t, pos, quat


def _batch(t, pos, quat, valid=None):
    return SampleBatch(t, pos, quat, np.ones(len(t), bool) if valid is None else valid)


def test_a_clean_recording_passes_unchanged():
    t, pos, quat = _truth()
    clean = clean_trace(_batch(t, pos, quat))
    assert len(clean.pieces) == 1
    np.testing.assert_array_equal(clean.pieces[0].points_m, pos)
    assert clean.report.n_bridged == clean.report.n_outliers == clean.report.n_invalid == 0
    assert clean.report.events == ()


def test_short_dropouts_are_bridged_close_to_the_truth_and_flagged():
    t, pos, quat = _truth()
    lost = np.zeros(len(t), bool)
    lost[100:115] = True  # 62 ms
    lost[500:503] = True
    raw_pos = pos.copy()
    raw_pos[lost] = np.nan
    clean = clean_trace(_batch(t, raw_pos, np.where(lost[:, None], np.nan, quat), ~lost))
    (piece,) = clean.pieces
    assert len(piece) == len(t)
    np.testing.assert_array_equal(clean.bridged[0], lost)
    # A smooth motion is bridged to well under 0.1 mm; the orientation by slerp too.
    assert np.abs(piece.points_m - pos).max() < 1e-4
    angle = (
        Rotation.from_quat(piece.orientations_xyzw) * Rotation.from_quat(quat).inv()
    ).magnitude()
    assert np.degrees(angle.max()) < 0.05
    bridged = [e for e in clean.report.events if e.kind == "bridged"]
    assert [e.n_samples for e in bridged] == [15, 3]
    assert clean.report.n_bridged == 18 and clean.report.n_invalid == 18


def test_a_long_dropout_splits_the_recording():
    t, pos, quat = _truth()
    lost = np.zeros(len(t), bool)
    lost[300:420] = True  # 0.5 s
    clean = clean_trace(_batch(t, np.where(lost[:, None], np.nan, pos), quat, ~lost))
    assert len(clean.pieces) == 2
    assert len(clean.pieces[0]) == 300 and len(clean.pieces[1]) == len(t) - 420
    (split,) = [e for e in clean.report.events if e.kind == "split"]
    assert split.n_samples == 120 and "lost the pen for 0.50" in split.detail
    assert clean.longest() == 1
    assert clean.report.pieces[0] == (0.0, pytest.approx(t[299]))


def test_an_outlier_spike_is_removed_and_bridged():
    t, pos, quat = _truth()
    raw = pos.copy()
    raw[200:203] += [0.03, 0.0, 0.0]  # a marker swap for three frames: 30 mm off
    clean = clean_trace(_batch(t, raw, quat))
    (piece,) = clean.pieces
    assert clean.report.n_outliers == 3
    assert np.abs(piece.points_m - pos).max() < 1e-4
    assert any(e.kind == "outliers" and e.n_samples == 3 for e in clean.report.events)


def _hairpin(speed_m_s, radius_m, rate_hz=RATE_HZ, leg_m=0.2):
    """Out along +x, a half circle, back along -x; at constant speed (no slowing down)."""
    turn_m = np.pi * radius_m
    s = np.arange(0, 2 * leg_m + turn_m, speed_m_s / rate_hz)
    theta = np.clip((s - leg_m) / radius_m, 0, np.pi)
    back = np.clip(s - leg_m - turn_m, 0, None)
    x = np.minimum(s, leg_m) + radius_m * np.sin(theta) - back
    y = radius_m * (1 - np.cos(theta))
    return s / speed_m_s, np.column_stack([x, y, 0 * s])


def test_the_apex_of_a_fast_hairpin_is_kept_and_spikes_around_it_removed():
    # 0.8 m/s round a 5 mm radius: the apex is over 5 mm from its neighbours' median (a plain
    # Hampel filter cut it), but on the curve through them.
    t, pos = _hairpin(0.8, 0.005)
    clean = clean_trace(_batch(t, pos, None))
    assert clean.report.n_outliers == 0 and len(clean.pieces[0]) == len(t)
    apex = int(np.argmax(pos[:, 0]))
    raw = pos.copy()
    raw[apex + 2] += [0.0, 0.0, 0.02]  # a marker swap just past the apex
    raw[apex - 60] += [0.0, -0.01, 0.0]  # and one on the way in
    clean = clean_trace(_batch(t, raw, None))
    assert clean.report.n_outliers == 2
    np.testing.assert_allclose(clean.pieces[0].points_m, pos, atol=2e-3)  # bridged


def test_a_persistent_jump_splits():
    t, pos, quat = _truth()
    raw = pos.copy()
    raw[400:] += [0.0, 0.05, 0.0]  # the rigid body swapped for good: 50 mm in one frame
    clean = clean_trace(_batch(t, raw, quat))
    assert len(clean.pieces) == 2
    (split,) = [e for e in clean.report.events if e.kind == "split"]
    assert "jump of 50" in split.detail


def test_leading_and_trailing_losses_are_trimmed_and_short_pieces_dropped():
    t, pos, quat = _truth()
    lost = np.zeros(len(t), bool)
    lost[:10] = lost[-7:] = True
    lost[600:700] = True  # a split ...
    lost[720:900] = True  # ... leaving a 20-sample piece (83 ms) between two long dropouts
    clean = clean_trace(_batch(t, np.where(lost[:, None], np.nan, pos), quat, ~lost))
    kinds = [e.kind for e in clean.report.events]
    assert "trimmed" in kinds and "dropped_piece" in kinds
    assert len(clean.pieces) == 2
    assert clean.pieces[0].t_s[0] == t[10] and clean.pieces[-1].t_s[-1] == t[-8]


def test_quaternion_signs_are_made_continuous():
    t, pos, quat = _truth()
    flipped = quat.copy()
    flipped[::2] *= -1  # the same rotations, alternating signs
    lost = np.zeros(len(t), bool)
    lost[50:54] = True
    clean = clean_trace(_batch(t, pos, np.where(lost[:, None], np.nan, flipped), ~lost))
    q = clean.pieces[0].orientations_xyzw
    assert np.all(np.sum(q[1:] * q[:-1], axis=1) > 0.99)


def test_nothing_usable_is_a_clear_error():
    t, pos, quat = _truth(seconds=1.0)
    with pytest.raises(InputFileError, match="lost the pen the whole time"):
        clean_trace(_batch(t, pos * np.nan, quat, np.zeros(len(t), bool)))
    lost = np.zeros(len(t), bool)
    lost[np.arange(len(t)) % 60 >= 20] = True  # 20 valid frames (83 ms) then 40 lost
    with pytest.raises(InputFileError, match="shorter than"):
        clean_trace(_batch(t, np.where(lost[:, None], np.nan, pos), quat, ~lost))
    with pytest.raises(InputFileError, match="do not increase"):
        clean_trace(_batch(t[::-1], pos, quat))


def test_bad_parameters():
    with pytest.raises(ValueError, match="max_bridge_s"):
        GapParams(max_bridge_s=0)
    with pytest.raises(ValueError, match="min_piece_s"):
        GapParams(min_piece_s=-1)


def test_tip_offset_moves_samples_to_the_tip():
    t, pos, quat = _truth(seconds=0.5)
    offset = np.array([0.0, 0.0, 0.12])
    moved = apply_tip_offset(_batch(t, pos, quat), offset)
    expected = pos + Rotation.from_quat(quat).apply(offset)
    np.testing.assert_allclose(moved.position_m, expected, atol=1e-12)
    with pytest.raises(ValueError, match="orientation"):
        apply_tip_offset(_batch(t, pos, None), offset)
    with pytest.raises(ValueError, match="3 finite"):
        apply_tip_offset(_batch(t, pos, quat), [0.0, np.nan, 0.0])
