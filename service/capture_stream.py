"""A capture's samples as they arrive, for drawing the trace while the operator traces.

The capture runner appends each batch to the capture's file (:mod:`service.capture_runner`);
:class:`CaptureTail` reads the complete lines added since its last read, so a page can follow a
capture from any sample on (after a reload too) and several pages can follow one capture, without
the runner knowing. A live feed's rigid-body positions are moved to the pen's tip with the
session's tip offset, as the recording will be when the capture stops.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from drivers.errors import InputFileError
from drivers.tracking.base import SampleBatch
from recon.arrays import FloatArray

#: The most bytes one read takes from the file (about 12 000 samples).
READ_BYTES = 1 << 20
FIELDS = 9  # t, x, y, z, qx, qy, qz, qw, valid


class CaptureTail:
    """The complete lines appended to a capture file since the last read.

    Parameters
    ----------
    path : Path
        The capture's file (``t,x,y,z,qx,qy,qz,qw,valid`` with a header line).
    from_sample : int
        The first sample to return (those before it are read past, not returned).
    tip_offset_m : ndarray of shape (3,), optional
        The pen's tip in the rigid body's frame: positions are moved to it (a live feed).
    """

    def __init__(
        self, path: Path, from_sample: int = 0, tip_offset_m: FloatArray | None = None
    ) -> None:
        self.path = Path(path)
        self.offset = 0  # bytes of the file consumed (whole lines)
        self.line = 0  # lines consumed, the header included
        self.next_sample = 0  # index of the next sample in the file
        self.from_sample = from_sample
        self.tip_offset_m = None if tip_offset_m is None else np.asarray(tip_offset_m, float)

    def read(self) -> tuple[int, SampleBatch] | None:
        """The samples appended since the last call: (index of the first, samples), or None
        when nothing new is complete (a line still being written waits for the next call).

        Raises
        ------
        InputFileError
            A complete line that is not 9 numbers (the file was changed by something else).
        """
        # Samples before `from_sample` are read past chunk by chunk, so that a page resuming
        # late in a long capture gets its next samples now, not one chunk per poll.
        while (result := self._read_chunk()) is not None:
            first, batch = result
            if batch is not None:
                return first, batch
        return None

    def _read_chunk(self) -> tuple[int, SampleBatch | None] | None:
        """One chunk: None at the end of what is written, (first, None) when all of it lay
        before ``from_sample``."""
        if not self.path.is_file():
            return None
        with self.path.open("rb") as handle:
            handle.seek(self.offset)
            chunk = handle.read(READ_BYTES)
        end = chunk.rfind(b"\n")
        if end < 0:
            return None
        lines = chunk[: end + 1].split(b"\n")[:-1]
        self.offset += end + 1
        if self.line == 0:
            lines = lines[1:]  # the header
            self.line = 1
        rows = np.empty((len(lines), FIELDS))
        for k, line in enumerate(lines):
            fields = line.split(b",")
            try:
                if len(fields) != FIELDS:
                    raise ValueError(f"{len(fields)} fields, expected {FIELDS}")
                rows[k] = [float(f) for f in fields]
            except ValueError as exc:
                raise InputFileError(
                    f"capture file {self.path.name}, line {self.line + k + 1}: {exc}"
                ) from None
        self.line += len(lines)
        first = self.next_sample
        self.next_sample += len(rows)
        skip = max(0, self.from_sample - first)
        rows = rows[skip:]
        if not len(rows):
            return first + skip, None
        quats = rows[:, 4:8]
        batch = SampleBatch(
            t_s=rows[:, 0],
            position_m=rows[:, 1:4],
            orientation_xyzw=quats if np.isfinite(quats).any() else None,
            valid=rows[:, 8] > 0.5,
        )
        if self.tip_offset_m is not None and batch.orientation_xyzw is not None:
            from drivers.tracking.gaps import apply_tip_offset

            batch = apply_tip_offset(batch, self.tip_offset_m)
        return first + skip, batch


def samples_event(first: int, batch: SampleBatch) -> dict[str, Any]:
    """One event's body: ``first`` (the index of the first sample), ``t_s``, ``points_m``
    (tracker frame, metres; null where the sample was lost) and ``valid``."""
    valid = np.asarray(batch.valid, dtype=bool) & np.isfinite(batch.position_m).all(axis=1)
    points = np.round(np.asarray(batch.position_m, dtype=np.float64), 7)
    return {
        "first": int(first),
        "t_s": np.round(batch.times_s(), 6).tolist(),
        "points_m": [p if ok else None for p, ok in zip(points.tolist(), valid, strict=True)],
        "valid": valid.tolist(),
    }
