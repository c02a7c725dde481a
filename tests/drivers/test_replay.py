"""File replay: a reader's samples, paced like the tracker that recorded them."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.robot.clock import FakeClock
from drivers.tracking.base import Pacer, SampleBatch, source_class
from drivers.tracking.replay import ReplaySource
from recon.inputs import Recording
from tests.drivers.tracking_fixtures import helix, write_motive_csv


def _recording(n=480, rate_hz=240.0):
    t, position, quat = helix(n, rate_hz)
    return Recording(points_m=position, t_s=10.0 + t, orientations_xyzw=quat)


def test_real_time_times_a_factor_on_a_fake_clock():
    clock = FakeClock()
    recording = _recording()
    source = ReplaySource(recording, pacer=Pacer(2.0, clock=clock), batch_s=0.05)
    start = clock.now()
    released = []
    for batch in source.batches():
        released.append((clock.now() - start, batch.t_s[-1] - recording.t_s[0]))
    # Each batch is released when its last sample is due, at twice the recorded pace.
    for elapsed, stream_time in released:
        assert elapsed == pytest.approx(stream_time / 2.0, abs=1e-9)
    assert sum(1 for _ in released) == pytest.approx(2.0 / 0.05, abs=1)


def test_as_fast_as_possible_yields_everything_in_order():
    recording = _recording()
    batches = list(ReplaySource(recording, pacer=Pacer(None)).batches())
    np.testing.assert_array_equal(np.concatenate([b.t_s for b in batches]), recording.t_s)
    np.testing.assert_array_equal(
        np.concatenate([b.position_m for b in batches]), recording.points_m
    )
    assert all(b.valid.all() for b in batches)


def test_raw_samples_keep_their_lost_frames(tmp_path):
    t, position, quat = helix(240)
    lost = np.zeros(len(t), bool)
    lost[50:60] = True
    write_motive_csv(tmp_path / "take.csv", t, position, quat, rigid_bodies=["pen"], lost=lost)
    source = ReplaySource.from_file(tmp_path / "take.csv", pacer=Pacer(None))
    batches = list(source.batches())
    valid = np.concatenate([b.valid for b in batches])
    np.testing.assert_array_equal(valid, ~lost)
    assert np.isnan(np.concatenate([b.position_m for b in batches])[lost]).all()


def test_close_ends_the_replay_and_the_registry_knows_it():
    source = ReplaySource(_recording(), pacer=Pacer(None), batch_s=0.01)
    seen = 0
    for batch in source.batches():
        seen += len(batch)
        source.close()
    assert seen < 480
    assert source_class("replay") is ReplaySource


def test_untimed_samples_get_the_default_rate_and_bad_arguments_are_refused():
    n = 24
    batch = SampleBatch(None, np.zeros((n, 3)), None, np.ones(n, bool))
    replayed = list(ReplaySource(batch, pacer=Pacer(None), batch_s=0.05).batches())
    assert np.concatenate([b.t_s for b in replayed])[-1] == pytest.approx((n - 1) / 240.0)
    with pytest.raises(ValueError, match="batch_s"):
        ReplaySource(_recording(), batch_s=0)
    with pytest.raises(ValueError, match="speed"):
        Pacer(0.0)
