"""Replay of a stored recording as if it were arriving from a tracker."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from drivers.tracking.base import Pacer, SampleBatch, TrackerSource
from recon.types import Recording

#: Assumed tracker rate for recordings without times (OptiTrack's default is 240 Hz).
DEFAULT_RATE_HZ = 240.0


class ReplaySource(TrackerSource):
    """Yields a recording's samples in batches of ``batch_s`` seconds, paced by ``pacer``."""

    kind = "replay"

    def __init__(
        self, recording: Recording, *, pacer: Pacer | None = None, batch_s: float = 0.05
    ) -> None:
        self.recording = recording
        self.pacer = pacer or Pacer(1.0)
        self.batch_s = batch_s
        self._closed = False

    def batches(self) -> Iterator[SampleBatch]:
        rec = self.recording
        n = len(rec)
        t = rec.t_s if rec.t_s is not None else np.arange(n) / DEFAULT_RATE_HZ
        start = 0
        while start < n and not self._closed:
            stop = int(np.searchsorted(t, t[start] + self.batch_s, side="left"))
            stop = max(stop, start + 1)
            self.pacer.wait_for(float(t[stop - 1]))
            if self._closed:
                break
            yield SampleBatch(
                t_s=t[start:stop],
                position_m=rec.points_m[start:stop],
                orientation_xyzw=None
                if rec.orientations_xyzw is None
                else rec.orientations_xyzw[start:stop],
                valid=np.ones(stop - start, dtype=bool),
            )
            start = stop

    def close(self) -> None:
        self._closed = True
