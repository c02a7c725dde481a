"""The journal of an execution: every sample the arm reported, on disk as it arrives.

A real arm's execution is written down while it runs (by the process that talks to the arm),
so that a crash of the service keeps what was executed: the next start turns the journal into
the execution's record.

The journal is a memory-mapped binary file, so that the servo loop that writes it makes no
system call, formats no text and allocates nothing: a sample is a store of 14 float64 into
pages mapped (and touched) before the motion starts, and the kernel writes the dirty pages back
in its own time. What a killed process stored is in the page cache and reaches the file; a
power loss can lose what the kernel had not written back yet (as with the text journal before,
which was flushed but never synced). The file:

- a header of :data:`HEADER_BYTES`: the magic :data:`MAGIC` (8 bytes), the column count
  (uint32, 14) and 4 reserved bytes, the capacity in samples (uint64) and the count of
  complete samples (uint64), all little-endian;
- ``capacity`` rows of 14 float64: time since the start (s), the actual joints (rad), the
  actual TCP pose (m, rotation vector), and the time on the plan's clock the arm was sent to
  (s since the plan's first sample: the same as the first column unless the run was slowed or
  paused, :mod:`drivers.robot.timescale`).

A sample's row is written before the count that includes it, so a writer killed mid-row leaves
a row the count does not include. Journals of earlier versions (13 columns without the plan's
clock, magic ``TPJOURN\x01``; or CSV text) are still read (:func:`read_journal`): their samples
ran at the plan's own pace.
"""

from __future__ import annotations

import mmap
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from drivers.errors import InputFileError
from recon.arrays import FloatArray

MAGIC = b"TPJOURN\x02"
COLUMNS = 14
#: The binary journal of the version before: 13 columns, no plan clock.
MAGIC_V1, COLUMNS_V1 = b"TPJOURN\x01", 13
HEADER_BYTES = 64
ROW_BYTES = COLUMNS * 8
#: Rows mapped when the length of the motion is not known beforehand (a movePath); the map
#: doubles when it is full (outside a servo loop, whose capacity is given up front).
DEFAULT_CAPACITY = 4096
#: Refused beyond this many samples on reading: over two hours at 500 Hz (430 MB).
MAX_SAMPLES = 4_000_000
#: The text journal of earlier versions starts with this header.
CSV_HEADER = "t,q0,q1,q2,q3,q4,q5,x,y,z,rx,ry,rz\n"

_HEADER_DTYPE = np.dtype(
    [
        ("magic", "S8"),
        ("columns", "<u4"),
        ("reserved", "<u4"),
        ("capacity", "<u8"),
        ("count", "<u8"),
    ]
)


class JournalWriter:
    """Appends samples to a journal file; ``close()`` is idempotent.

    Parameters
    ----------
    path : str or Path
        The journal file (created private, 0600: what the arm did is the site's record).
    capacity_samples : int
        Rows mapped and touched now. A servo loop gives its number of samples, so that no
        sample of it remaps the file or takes a page fault.
    """

    def __init__(self, path: str | Path, capacity_samples: int = DEFAULT_CAPACITY) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        self._count = 0
        self._map: mmap.mmap | None = None
        try:
            self._map_rows(max(int(capacity_samples), 1))
        except BaseException:
            os.close(self._fd)
            raise

    def _map_rows(self, capacity: int) -> None:
        """Size the file for ``capacity`` rows and map it (the rows written so far are kept)."""
        self._release()
        os.ftruncate(self._fd, HEADER_BYTES + capacity * ROW_BYTES)
        mapped = mmap.mmap(self._fd, HEADER_BYTES + capacity * ROW_BYTES)
        self._map = mapped
        header = np.frombuffer(mapped, dtype=_HEADER_DTYPE, count=1)
        header["magic"], header["columns"], header["capacity"] = MAGIC, COLUMNS, capacity
        header["count"] = self._count
        self._count_field = np.frombuffer(mapped, dtype="<u8", count=1, offset=24)
        self._rows = np.frombuffer(mapped, dtype="<f8", offset=HEADER_BYTES).reshape(
            capacity, COLUMNS
        )
        # Touch every page of the free rows now: the first store to a page faults it in.
        self._rows[self._count :] = 0.0
        self._capacity = capacity

    def add(
        self,
        t_s: float,
        q_rad: Iterable[float],
        tcp_pose: Iterable[float],
        plan_s: float | None = None,
    ) -> None:
        """One sample: time (s), joints (6, rad), TCP pose (6), and where on the plan's clock
        the arm was sent (s; None: ``t_s``, a run at the plan's pace)."""
        if self._count == self._capacity:
            self._map_rows(2 * self._capacity)
        self._rows[self._count] = (t_s, *q_rad, *tcp_pose, t_s if plan_s is None else plan_s)
        self._count += 1
        self._count_field[0] = self._count  # after the row: a torn row is never counted

    def __len__(self) -> int:
        return self._count

    def _release(self) -> None:
        if self._map is not None:
            # The arrays are views of the map: it closes only once they are gone.
            del self._rows, self._count_field
            self._map.close()
            self._map = None

    def close(self) -> None:
        if self._fd < 0:
            return
        try:
            if self._map is not None:
                self._map.flush()
            self._release()
        finally:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> JournalWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_journal(path: str | Path) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The samples of a journal: times (K,), joints (K, 6), TCP poses (K, 6).

    See :func:`read_journal_with_plan` (which also gives the plan's clock) for the errors.
    """
    t_s, q_rad, tcp, _ = read_journal_with_plan(path)
    return t_s, q_rad, tcp


def read_journal_with_plan(
    path: str | Path,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The samples of a journal: times (K,), joints (K, 6), TCP poses (K, 6), and where on the
    plan's clock each was sent (K,; the times themselves in a journal of an earlier version).

    Raises
    ------
    InputFileError
        The file is missing, not a journal, declares more samples than it holds or than
        :data:`MAX_SAMPLES`, or holds a sample that is not finite or goes back in time.
    """
    name = Path(path).name
    try:
        with open(path, "rb") as file:
            head = file.read(HEADER_BYTES)
            if not head.strip(b"\0"):
                # Created, and nothing written before the writer died (a text journal not yet
                # flushed, a header never written back): the arm never moved under it.
                return np.zeros(0), np.zeros((0, 6)), np.zeros((0, 6)), np.zeros(0)
            if head.startswith(CSV_HEADER.encode()):
                t_s, q_rad, tcp = _read_csv_journal(path)
                return t_s, q_rad, tcp, t_s.copy()
            if len(head) < HEADER_BYTES or head[:8] not in (MAGIC, MAGIC_V1):
                raise InputFileError(
                    f"the execution journal {name} is not a teachpath journal (it does not start "
                    "with its header); it was not written by this service: move it out of the "
                    "journals folder"
                )
            header = np.frombuffer(head, dtype=_HEADER_DTYPE, count=1)[0]
            columns, capacity, count = (int(header[k]) for k in ("columns", "capacity", "count"))
            expected = COLUMNS if head[:8] == MAGIC else COLUMNS_V1
            size = os.fstat(file.fileno()).st_size
            held = (size - HEADER_BYTES) // (expected * 8)
            if columns != expected or count > capacity or count > held or count > MAX_SAMPLES:
                raise InputFileError(
                    f"the execution journal {name} declares {count:,} samples of {columns} "
                    f"numbers in room for {capacity:,}, but the file holds {held:,} samples of "
                    f"{expected} (at most {MAX_SAMPLES:,} are read): it was cut or changed by "
                    "something else; move it out of the journals folder"
                )
            data = np.fromfile(file, dtype="<f8", count=count * expected).reshape(count, expected)
    except OSError as exc:
        raise InputFileError(f"the execution journal {name} cannot be read: {exc}") from None
    # Rows counted but never written back (a power loss: the count's page reached the disk, a
    # row's did not) read as all zeros at the end: the samples before them are kept.
    written = np.flatnonzero(data.any(axis=1))
    data = data[: written[-1] + 1 if len(written) else 0]
    _check_samples(data, name)
    plan_s = data[:, 13] if data.shape[1] > 13 else data[:, 0].copy()
    return data[:, 0], data[:, 1:7], data[:, 7:13], plan_s


def _check_samples(data: FloatArray, name: str) -> None:
    """Refuse samples that no arm reported: not finite, time going backwards, or a plan clock
    that goes backwards or starts before the plan (a stream only ever moves forward on it)."""
    bad = np.logical_not(np.isfinite(data).all(axis=1))
    bad[1:] |= np.diff(data[:, 0]) < 0
    if data.shape[1] > 13:
        bad |= data[:, 13] < 0
        bad[1:] |= np.diff(data[:, 13]) < 0
    if bad.any():
        row = int(np.argmax(bad))
        raise InputFileError(
            f"the execution journal {name}, sample {row + 1}: not finite or earlier than the "
            "sample before; it was changed by something else: move it out of the journals folder"
        )


def _read_csv_journal(path: str | Path) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A text journal of an earlier version: one CSV line per sample, a torn last line
    (the writer died mid-line) dropped."""
    name = Path(path).name
    try:
        if os.path.getsize(path) > MAX_SAMPLES * 200:
            raise InputFileError(
                f"the execution journal {name} is larger than {MAX_SAMPLES:,} samples could "
                "be; move it out of the journals folder"
            )
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"the execution journal {name} cannot be read: {exc}") from None
    lines = text.split("\n")
    # After the header, complete lines end in a newline: the last element is "" or torn.
    body = [line for line in lines[1:-1] if line.strip()]
    data = np.zeros((len(body), COLUMNS_V1))
    for row, line in enumerate(body):
        fields = line.split(",")
        try:
            if len(fields) != COLUMNS_V1:
                raise ValueError(f"{len(fields)} fields")
            data[row] = [float(f) for f in fields]
        except ValueError as exc:
            raise InputFileError(f"the execution journal {name}, line {row + 2}: {exc}") from None
    _check_samples(data, name)
    return data[:, 0], data[:, 1:7], data[:, 7:13]
