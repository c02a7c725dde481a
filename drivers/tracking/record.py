"""Recording the live tracker into a canonical trace file (``teachpath record --natnet``)."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from drivers.errors import TrackerError, TrackerTimeoutError
from drivers.files import atomic_path
from drivers.tracking.base import increasing_times
from drivers.tracking.canonical_csv import write_trace_csv
from drivers.tracking.natnet_source import (
    NatNetBatch,
    NatNetConfig,
    NatNetServerInfo,
    NatNetSource,
)
from recon.inputs import Recording

StopReason = Literal["duration", "stop_event", "stream_stalled", "interrupted"]


class StopEvent(Protocol):
    """What :func:`record_natnet` needs of a stop flag (``threading.Event`` or a
    ``multiprocessing`` one)."""

    def is_set(self) -> bool: ...

    def wait(self, timeout: float | None = None) -> bool: ...


@dataclass(frozen=True)
class RecordSummary:
    """What a recording got.

    Attributes
    ----------
    path : Path
        The CSV written: ``t,x,y,z,qx,qy,qz,qw``, metres, seconds from the first row.
    frames_received : int
        Frames received during the recording (tracked or not).
    frames_written : int
        Rows of the file: the frames in which the rigid body was tracked.
    frames_dropped : int
        Frame numbers missing between received frames (lost on the network or never sent).
    frames_invalid : int
        Received frames in which the rigid body was not tracked (not written).
    frames_discarded : int
        Tracked frames whose timestamp did not increase (a restarted stream; not written).
    t0_s : float
        The server's timestamp of the first row (the file's times start at 0).
    duration_s : float
        Stream time from the first to the last row, seconds.
    stop_reason : {"duration", "stop_event", "stream_stalled", "interrupted"}
        Why the recording ended: the requested duration was reached, the stop event was set,
        the stream went silent for ``stall_timeout_s``, or Ctrl-C.
    server : NatNetServerInfo
    """

    path: Path
    frames_received: int
    frames_written: int
    frames_dropped: int
    frames_invalid: int
    frames_discarded: int
    t0_s: float
    duration_s: float
    stop_reason: StopReason
    server: NatNetServerInfo


def record_natnet(
    config: NatNetConfig,
    out_path: str | Path,
    *,
    duration_s: float | None = None,
    stop_event: StopEvent | None = None,
) -> RecordSummary:
    """Record a rigid body from a NatNet server into a canonical trace CSV.

    Runs until ``duration_s`` of stream time has been recorded, ``stop_event`` is set, the
    stream goes silent for ``config.stall_timeout_s`` after its first frame, or Ctrl-C; then
    writes the tracked frames atomically (the file appears complete or not at all).

    Parameters
    ----------
    config : NatNetConfig
    out_path : path
        The CSV to write; its folder must exist.
    duration_s : float, optional
        Stream time to record, seconds (frames with ``t - t_first < duration_s``).
    stop_event : threading.Event or multiprocessing.Event, optional
        Set it (from another thread or a signal handler) to end the recording.

    Returns
    -------
    RecordSummary

    Raises
    ------
    ValueError
        ``duration_s`` not positive, or the output folder does not exist.
    TrackerTimeoutError, UnknownRigidBodyError, TrackerError
        From connecting (see :meth:`NatNetSource.connect`); a stream that never sent a frame;
        fewer than two tracked frames (nothing is written).
    """
    out_path = Path(out_path)
    if duration_s is not None and not duration_s > 0:
        raise ValueError(f"duration_s must be > 0, got {duration_s}")
    if not out_path.parent.is_dir():
        raise ValueError(f"the folder of {out_path} does not exist; create it first")
    source = NatNetSource(config)
    finished = threading.Event()

    def watch(stop_event: StopEvent) -> None:
        # batches() blocks while the stream is quiet: closing the source is what ends it.
        while not finished.is_set():
            if stop_event.wait(0.1):
                source.close()
                return

    watcher = None
    parts: list[dict[str, NDArray[Any]]] = []
    # batches() only ends by itself when the watcher closed the source.
    stop_reason: StopReason = "stop_event"
    try:
        server = source.connect()
        if stop_event is not None:
            watcher = threading.Thread(
                target=watch, args=(stop_event,), name="record stop watcher", daemon=True
            )
            watcher.start()
        t_first = None
        try:
            for batch in source.batches():
                if t_first is None:
                    t_first = float(batch.times_s()[0])
                if duration_s is not None:
                    inside = np.asarray(batch.times_s() - t_first < duration_s)
                    parts.append(_select(batch, inside))
                    if not inside.all():
                        stop_reason = "duration"
                        break
                else:
                    parts.append(_select(batch, slice(None)))
        except TrackerTimeoutError:
            if not parts:
                raise
            stop_reason = "stream_stalled"
        except KeyboardInterrupt:
            stop_reason = "interrupted"
    finally:
        finished.set()
        source.close()
        if watcher is not None:
            watcher.join()
    return _write(out_path, parts, config.rigid_body, stop_reason, server)


def _select(batch: NatNetBatch, index: NDArray[np.bool_] | slice) -> dict[str, NDArray[Any]]:
    t, q = batch.t_s, batch.orientation_xyzw
    if t is None or q is None:  # NatNetSource's batches always carry both
        raise TypeError("a NatNet batch without sample times or orientations")
    return {
        "frame": np.asarray(batch.frame_numbers)[index],
        "t": t[index],
        "p": batch.position_m[index],
        "q": q[index],
        "valid": batch.valid[index],
    }


def _write(
    out_path: Path,
    parts: list[dict[str, NDArray[Any]]],
    rigid_body: str,
    stop_reason: StopReason,
    server: NatNetServerInfo,
) -> RecordSummary:
    def column(key: str, shape_tail: tuple[int, ...] = ()) -> NDArray[Any]:
        if not parts:
            return np.zeros((0, *shape_tail))
        return np.concatenate([p[key] for p in parts])

    frames = column("frame").astype(np.int64)
    t, p, q, valid = column("t"), column("p", (3,)), column("q", (4,)), column("valid")
    valid = valid.astype(bool)
    steps = np.diff(frames)
    dropped = int(np.sum(steps[steps > 1] - 1))
    tracked = np.flatnonzero(valid)
    # Keep strictly increasing times (a restarted stream starts its clock again).
    increasing = increasing_times(t[tracked])
    rows = tracked[increasing]
    if len(rows) < 2:
        raise TrackerError(
            f"only {len(rows)} frames with {rigid_body!r} tracked out of {len(frames)} received; "
            "nothing written. Is the pen in view of the cameras?"
        )
    quats = q[rows] / np.linalg.norm(q[rows], axis=1)[:, None]
    t0 = float(t[rows[0]])
    recording = Recording(points_m=p[rows], t_s=t[rows] - t0, orientations_xyzw=quats)
    with atomic_path(out_path) as tmp:
        write_trace_csv(tmp, recording)
    return RecordSummary(
        path=out_path,
        frames_received=len(frames),
        frames_written=len(rows),
        frames_dropped=dropped,
        frames_invalid=int((~valid).sum()),
        frames_discarded=int((~increasing).sum()),
        t0_s=t0,
        duration_s=float(t[rows[-1]] - t0),
        stop_reason=stop_reason,
        server=server,
    )
