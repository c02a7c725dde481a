"""The journal of an execution: every sample the arm reported, on disk as it arrives.

A real arm's execution is written down while it runs (by the process that talks to the arm),
so that a crash of the service keeps what was executed: the next start turns the journal into
the execution's record. One CSV line per sample: time since the start (s), the actual joints
(rad) and the actual TCP pose (m, rotation vector). Lines are flushed every
:data:`FLUSH_EVERY` samples and when the journal closes; a torn last line (the writer died
mid-line) is dropped on reading.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from drivers.errors import InputFileError
from recon.types import FloatArray

HEADER = "t,q0,q1,q2,q3,q4,q5,x,y,z,rx,ry,rz\n"
#: Samples between flushes (0.1 s at 500 Hz): a crash loses at most this many.
FLUSH_EVERY = 50
COLUMNS = 13


class JournalWriter:
    """Appends samples to a journal file; ``close()`` is idempotent."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # Private (0600) from the start: what the arm did is the site's record.
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        self._file = os.fdopen(fd, "w", buffering=1 << 16)
        self._file.write(HEADER)
        self._pending = 0

    def add(self, t_s: float, q_rad, tcp_pose) -> None:
        """One sample: time (s), joints (6, rad), TCP pose (6)."""
        values = (t_s, *q_rad, *tcp_pose)
        self._file.write(",".join(f"{v:.9g}" for v in values) + "\n")
        self._pending += 1
        if self._pending >= FLUSH_EVERY:
            self._file.flush()
            self._pending = 0

    def close(self) -> None:
        if not self._file.closed:
            self._file.flush()
            self._file.close()

    def __enter__(self) -> JournalWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_journal(path: str | Path) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The samples of a journal: times (K,), joints (K, 6), TCP poses (K, 6).

    Raises
    ------
    InputFileError
        The file is missing, or a complete line is not 13 numbers (changed by something else).
    """
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise InputFileError(
            f"the execution journal {Path(path).name} cannot be read: {exc}"
        ) from None
    lines = text.split("\n")
    # After the header, complete lines end in a newline: the last element is "" or torn.
    body = [line for line in lines[1:-1] if line.strip()]
    data = np.zeros((len(body), COLUMNS))
    for row, line in enumerate(body):
        fields = line.split(",")
        try:
            if len(fields) != COLUMNS:
                raise ValueError(f"{len(fields)} fields")
            data[row] = [float(f) for f in fields]
        except ValueError as exc:
            raise InputFileError(
                f"the execution journal {Path(path).name}, line {row + 2}: {exc}"
            ) from None
    return data[:, 0], data[:, 1:7], data[:, 7:13]
