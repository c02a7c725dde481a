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
from collections.abc import Callable
from pathlib import Path

import numpy as np

from drivers.errors import InputFileError
from drivers.tracking.base import SampleBatch, TrackerSource, increasing_times
from service.store import Store

log = logging.getLogger("teachpath.captures")

HEADER = "t,x,y,z,qx,qy,qz,qw,valid\n"
FSYNC_EVERY_S = 0.5


class CaptureRunner:
    """Pulls batches from ``source`` in a thread until stopped or exhausted.

    ``finalize(capture_id, state, error)`` is called once at the end (in the runner's thread);
    ``kind`` is the source's kind ("replay", "natnet"), by which live captures are counted.
    """

    def __init__(
        self,
        store: Store,
        capture_id: str,
        source: TrackerSource,
        finalize: Callable[[str, str, str | None], None],
        *,
        kind: str = "replay",
    ) -> None:
        self.store, self.capture_id, self.source = store, capture_id, source
        self.finalize = finalize
        self.kind = kind
        self.thread = threading.Thread(target=self._run, name=f"capture {capture_id}", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        # The source ends its batches() after handing over what it had received (a live feed
        # flushes its receiver), so the last samples reach the file too.
        self.source.close()

    def _run(self) -> None:
        row = self.store.capture(self.capture_id)
        if row is None:  # its session was deleted before the capture started: nothing to write
            log.warning(
                "capture %s is gone before it started; its source is closed", self.capture_id
            )
            self.source.close()
            return
        path = self.store.data_dir / row.path
        count, state, error = 0, "stopped", None
        last_sync = time.monotonic()
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)  # private
            with os.fdopen(fd, "w", buffering=1) as handle:
                handle.write(HEADER)
                for batch in self.source.batches():
                    q = batch.orientation_xyzw
                    if q is None:
                        q = np.full((len(batch), 4), np.nan)
                    t_s = batch.times_s()
                    for i in range(len(batch)):
                        x, y, z = batch.position_m[i]
                        handle.write(
                            f"{t_s[i]:.6f},{x:.9g},{y:.9g},{z:.9g},"
                            f"{q[i, 0]:.9g},{q[i, 1]:.9g},{q[i, 2]:.9g},{q[i, 3]:.9g},"
                            f"{int(batch.valid[i])}\n"
                        )
                    handle.flush()
                    count += len(batch)
                    if time.monotonic() - last_sync >= FSYNC_EVERY_S:
                        os.fsync(handle.fileno())
                        self.store.update_capture(self.capture_id, n_samples=count)
                        last_sync = time.monotonic()
                os.fsync(handle.fileno())
        except Exception as exc:  # the samples so far are on disk: keep them
            log.exception("capture %s failed", self.capture_id)
            state, error = "failed", str(exc)
        finally:
            self.source.close()
            self.store.update_capture(self.capture_id, n_samples=count)
            self.finalize(self.capture_id, state, error)


def read_capture_file(path: str | Path) -> SampleBatch:
    """Every sample of a capture file (lost ones flagged), for cleaning into a recording.

    The file may end in a torn line (the process died mid-write) and may hold a stretch where
    the tracker's clock started again (a restarted stream): the torn line and the repeated
    stretch are dropped, everything else is kept.

    Raises
    ------
    InputFileError
        A complete line that is not 9 numbers (the file was changed by something else).
    """
    text = Path(path).read_text()
    lines = text.split("\n")
    # The last element is "" after a final newline, else a torn line written when the process
    # died: drop it either way.
    body = [line for line in lines[1:-1] if line.strip()]
    data = np.zeros((len(body), 9))
    for row, line in enumerate(body):
        fields = line.split(",")
        try:
            if len(fields) != 9:
                raise ValueError(f"{len(fields)} fields, expected 9")
            data[row] = [float(f) for f in fields]
        except ValueError as exc:
            raise InputFileError(
                f"capture file {Path(path).name}, line {row + 2}: {exc}; the file was changed "
                "after it was written -- restore it from a backup"
            ) from None
    data = data[increasing_times(data[:, 0])]
    quats = data[:, 4:8]
    has_q = len(quats) > 0 and bool(np.isfinite(quats[data[:, 8] > 0.5]).all())
    return SampleBatch(
        t_s=data[:, 0],
        position_m=data[:, 1:4],
        orientation_xyzw=quats if has_q else None,
        valid=data[:, 8] > 0.5,
    )
