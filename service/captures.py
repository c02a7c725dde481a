"""Captures: samples from a tracker source written to disk as they arrive.

Each capture appends its samples to ``captures/<id>.csv`` (flushed every batch, fsynced at
least every half second), so a crash keeps what was received. Stopping it (or the source
ending) turns the file into an immutable recording artifact; a capture left running by a
process that died is turned into one on the next start.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import warnings
from collections.abc import Callable

import numpy as np

from drivers.tracking.base import SampleBatch, TrackerSource
from service.store import Store

log = logging.getLogger("teachpath.captures")

HEADER = "t,x,y,z,qx,qy,qz,qw,valid\n"
FSYNC_EVERY_S = 0.5


class CaptureRunner:
    """Pulls batches from ``source`` in a thread until stopped or exhausted.

    ``finalize(capture_id, state, error)`` is called once at the end (in the runner's thread).
    """

    def __init__(
        self,
        store: Store,
        capture_id: str,
        source: TrackerSource,
        finalize: Callable[[str, str, str | None], None],
    ) -> None:
        self.store, self.capture_id, self.source = store, capture_id, source
        self.finalize = finalize
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name=f"capture {capture_id}", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self._stop.set()
        self.source.close()

    def _run(self) -> None:
        row = self.store.capture(self.capture_id)
        path = self.store.data_dir / row.path
        count, state, error = 0, "stopped", None
        last_sync = time.monotonic()
        try:
            with path.open("w", buffering=1) as handle:
                handle.write(HEADER)
                for batch in self.source.batches():
                    q = batch.orientation_xyzw
                    if q is None:
                        q = np.full((len(batch), 4), np.nan)
                    for i in range(len(batch)):
                        x, y, z = batch.position_m[i]
                        handle.write(
                            f"{batch.t_s[i]:.6f},{x:.9g},{y:.9g},{z:.9g},"
                            f"{q[i, 0]:.9g},{q[i, 1]:.9g},{q[i, 2]:.9g},{q[i, 3]:.9g},"
                            f"{int(batch.valid[i])}\n"
                        )
                    handle.flush()
                    count += len(batch)
                    if time.monotonic() - last_sync >= FSYNC_EVERY_S:
                        os.fsync(handle.fileno())
                        self.store.update_capture(self.capture_id, n_samples=count)
                        last_sync = time.monotonic()
                    if self._stop.is_set():
                        break
                os.fsync(handle.fileno())
        except Exception as exc:  # the samples so far are on disk: keep them
            log.exception("capture %s failed", self.capture_id)
            state, error = "failed", str(exc)
        finally:
            self.source.close()
            self.store.update_capture(self.capture_id, n_samples=count)
            self.finalize(self.capture_id, state, error)


def read_capture_file(path) -> SampleBatch:
    """Every sample of a capture file (lost ones flagged), for cleaning into a recording."""
    with warnings.catch_warnings():
        # A capture that received nothing has only its header: that is an answer, not a fault.
        warnings.filterwarnings("ignore", message="loadtxt: input contained no data")
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if data.size == 0:
        data = np.zeros((0, 9))
    # Times must increase: keep the first of repeated stamps.
    keep = np.concatenate(([True], np.diff(data[:, 0]) > 0)) if len(data) else np.zeros(0, bool)
    data = data[keep]
    quats = data[:, 4:8]
    has_q = len(quats) > 0 and bool(np.isfinite(quats[data[:, 8] > 0.5]).all())
    return SampleBatch(
        t_s=data[:, 0],
        position_m=data[:, 1:4],
        orientation_xyzw=quats if has_q else None,
        valid=data[:, 8] > 0.5,
    )
