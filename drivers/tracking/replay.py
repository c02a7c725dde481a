"""Replay of a stored recording as if it were arriving from a tracker: :class:`ReplaySource` and
its config, :class:`ReplayConfig`."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from drivers.robot.clock import Clock
from drivers.tracking.base import Pacer, SampleBatch, SourceConfig, TrackerSource
from recon.inputs import Recording

#: Assumed tracker rate for recordings without times (OptiTrack's default is 240 Hz).
DEFAULT_RATE_HZ = 240.0


class ReplayConfig(SourceConfig):
    """Settings of a replay (the samples themselves are given to :func:`create_source`).

    Attributes
    ----------
    speed : float or None
        Times real time; None replays as fast as the consumer takes the samples.
    batch_s : float
        Stream time per batch.
    """

    kind: Literal["replay"] = "replay"
    speed: float | None = Field(1.0, gt=0, description="times real time; None: as fast as possible")
    batch_s: float = Field(0.05, gt=0, description="stream time per batch (s)")


class ReplaySource(TrackerSource):
    """Yields a recording's samples in batches of ``batch_s`` seconds, paced by ``pacer``.

    Parameters
    ----------
    recording : Recording or SampleBatch
        A clean recording (every sample valid), or raw samples as a reader found them (lost
        frames flagged, as a live tracker would send them).
    pacer : Pacer, optional
        Real time by default; ``Pacer(None)`` replays as fast as the consumer takes it.
    batch_s : float
        Stream time per batch.
    """

    kind = "replay"
    config_class = ReplayConfig

    def __init__(
        self,
        recording: Recording | SampleBatch,
        *,
        pacer: Pacer | None = None,
        batch_s: float = 0.05,
    ) -> None:
        if isinstance(recording, Recording):
            n = len(recording)
            recording = SampleBatch(
                t_s=recording.t_s if recording.t_s is not None else np.arange(n) / DEFAULT_RATE_HZ,
                position_m=recording.points_m,
                orientation_xyzw=recording.orientations_xyzw,
                valid=np.ones(n, dtype=bool),
            )
        elif recording.t_s is None:
            n = len(recording.position_m)
            recording = SampleBatch(
                np.arange(n) / DEFAULT_RATE_HZ,
                recording.position_m,
                recording.orientation_xyzw,
                recording.valid,
            )
        if not batch_s > 0:
            raise ValueError(f"batch_s must be positive, got {batch_s}")
        self.samples = recording
        self.pacer = pacer or Pacer(1.0)
        self.batch_s = batch_s
        self._closed = False

    @classmethod
    def from_config(
        cls,
        config: SourceConfig,
        *,
        recording: Recording | SampleBatch | None = None,
        clock: Clock | None = None,
    ) -> ReplaySource:
        """Replay ``recording`` as ``config`` says, paced by ``clock`` (real time by default).

        Raises
        ------
        ValueError
            No recording given.
        """
        if recording is None:
            raise ValueError("a replay needs the recording to replay (recording=...)")
        if not isinstance(config, ReplayConfig):
            raise TypeError(f"a replay source needs a ReplayConfig, got {type(config).__name__}")
        return cls(recording, pacer=Pacer(config.speed, clock=clock), batch_s=config.batch_s)

    @classmethod
    def from_file(
        cls,
        source: str | Path | bytes,
        *,
        pacer: Pacer | None = None,
        batch_s: float = 0.05,
        **reader_options: str | None,
    ) -> ReplaySource:
        """Replay a trace file in any supported format, lost frames and all.

        ``reader_options`` go to :func:`drivers.tracking.readers.read_raw_trace` (``name``,
        ``fmt``, ``units``, ``rigid_body``, ``marker``).
        """
        from drivers.tracking.readers import read_raw_trace

        return cls(read_raw_trace(source, **reader_options).batch, pacer=pacer, batch_s=batch_s)

    def batches(self) -> Iterator[SampleBatch]:
        samples = self.samples
        t = samples.times_s()
        n = len(t)
        start = 0
        if n:
            self.pacer.wait_for(float(t[0]))  # the clock starts with the first sample
        while start < n and not self._closed:
            stop = int(np.searchsorted(t, t[start] + self.batch_s, side="left"))
            stop = max(stop, start + 1)
            self.pacer.wait_for(float(t[stop - 1]))
            if self._closed:
                break
            q = samples.orientation_xyzw
            yield SampleBatch(
                t_s=t[start:stop],
                position_m=samples.position_m[start:stop],
                orientation_xyzw=None if q is None else q[start:stop],
                valid=np.asarray(samples.valid[start:stop], dtype=bool),
            )
            start = stop

    def close(self) -> None:
        self._closed = True
