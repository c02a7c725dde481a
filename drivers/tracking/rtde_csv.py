"""Universal Robots RTDE recordings: the arm's TCP pose, recorded while it is guided by hand, as a
trace.

The layout, as UR's RTDE client library writes it (``examples/record.py`` through
``rtde/csv_writer.py``: a header of the recipe's names, vectors split into ``name_0`` ...
``name_5``, values separated by single spaces) and as ur_rtde's
``RTDEReceiveInterface.startFileRecording`` writes it (the same names, comma-separated)::

    timestamp target_q_0 ... actual_TCP_pose_0 actual_TCP_pose_1 ... actual_TCP_pose_5 ...
    5324.904 0.0131 ... 0.412 -0.133 0.219 2.21 -2.22 0.01 ...

``timestamp`` is the controller's clock in seconds. ``actual_TCP_pose`` is the tool centre point
in the robot's base frame: x, y, z in metres, then a rotation vector rx, ry, rz (the axis times the
angle, radians). Other columns (joints, currents, I/O...) are ignored, however many there are.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from drivers.errors import InputFileError
from drivers.tracking.base import SampleBatch, name_excerpt
from drivers.units import metres_per

#: The recipe field read: the pose the controller measured (``target_TCP_pose`` is the commanded
#: one, which lags a hand-guided arm).
POSE_FIELD = "actual_TCP_pose"
#: Its six columns: position, then rotation vector.
POSE_COLUMNS = tuple(f"{POSE_FIELD}_{i}" for i in range(6))
TIME_COLUMN = "timestamp"


@dataclass(frozen=True)
class RTDETrace:
    """The TCP pose of an RTDE recording.

    Attributes
    ----------
    batch : SampleBatch
        ``t_s`` (N,) seconds of the controller's clock; ``position_m`` (N, 3) metres, base frame;
        ``orientation_xyzw`` (N, 4) unit quaternions, scalar last; ``valid`` all True.
    rate_hz : float
        The recording's rate, from the median time step.
    pose : str
        The recipe field read ("actual_TCP_pose").
    delimiter : str
        " " or ",", as the file has it.
    columns : tuple of str
        Every column name of the header.
    torn_last_line : bool
        Whether a last line cut short (the recorder stopped mid-write) was left out.
    """

    batch: SampleBatch
    rate_hz: float
    pose: str
    delimiter: str
    columns: tuple[str, ...]
    torn_last_line: bool = False

    def __len__(self) -> int:
        return len(self.batch)


def read_rtde_csv(
    source: str | Path | bytes, *, units: str | None = None, name: str | None = None
) -> RTDETrace:
    """Read the TCP pose of an RTDE recording, space- or comma-delimited.

    Parameters
    ----------
    source : path or bytes
        The file, or its content (an upload).
    units : {"m", "mm"}, optional
        Accepted for the readers' common call; RTDE is in metres whatever is passed.
    name : str, optional
        The file's name, for messages (uploads).

    Returns
    -------
    RTDETrace

    Raises
    ------
    InputFileError
        Missing, empty or binary file; no ``timestamp`` or ``actual_TCP_pose_0..5`` column; a
        row of another width (but the last, which is left out); a cell that is not a finite
        number; times that do not increase; fewer than two rows.
    ValueError
        An unknown ``units``.
    """
    if units is not None:
        metres_per(units)  # an unknown name is still an error; a known one changes nothing
    name = name or ("upload" if isinstance(source, bytes) else str(source))
    lines = _lines(_read_text(source, name))
    if not lines:
        raise InputFileError(f"{name} is empty; expected an RTDE recording")
    _, header = lines[0]
    delimiter = "," if "," in header else " "
    names = _split(header, delimiter)
    wanted = _wanted_columns(names, name)
    rows, torn = _rows(lines[1:], len(names), delimiter, name)
    data = _numbers(rows, wanted, names, name)
    if len(data) < 2:
        raise InputFileError(f"{name} has {len(data)} data rows; a trace needs at least two")
    t = data[:, 0]
    steps = np.diff(t)
    if np.any(steps <= 0):
        line = rows[int(np.flatnonzero(steps <= 0)[0]) + 1][0]
        raise InputFileError(
            f"{name}: the times in column {TIME_COLUMN!r} do not increase (line {line}); record "
            "again, or sort the rows by time and remove repeated ones"
        )
    quat = Rotation.from_rotvec(data[:, 4:7]).as_quat(scalar_first=False)
    batch = SampleBatch(
        t_s=t,
        position_m=data[:, 1:4],
        orientation_xyzw=quat,
        valid=np.ones(len(t), dtype=bool),
    )
    return RTDETrace(
        batch=batch,
        rate_hz=float(1.0 / np.median(steps)),
        pose=POSE_FIELD,
        delimiter=delimiter,
        columns=tuple(names),
        torn_last_line=torn,
    )


def _read_text(source: str | Path | bytes, name: str) -> str:
    if isinstance(source, bytes):
        raw = source
    else:
        try:
            raw = Path(source).read_bytes()
        except FileNotFoundError:
            raise InputFileError(f"{name} does not exist") from None
        except IsADirectoryError:
            raise InputFileError(f"{name} is a directory, not an RTDE recording") from None
        except OSError as exc:
            raise InputFileError(f"cannot read {name}: {exc.strerror}") from None
    if b"\x00" in raw[:4096]:
        raise InputFileError(
            f"{name} is a binary file; RTDE recordings are read as text (record.py without "
            "--binary, or ur_rtde's startFileRecording)"
        )
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputFileError(f"{name} is not a text (UTF-8) RTDE recording") from None


def _lines(text: str) -> list[tuple[int, str]]:
    """The lines that are not blank, with their (1-based) line numbers."""
    return [(i, line) for i, line in enumerate(text.splitlines(), start=1) if line.strip()]


def _split(line: str, delimiter: str) -> list[str]:
    if delimiter == ",":
        return [cell.strip() for cell in line.split(",")]
    return line.split()


def _wanted_columns(names: list[str], name: str) -> list[int]:
    """Indices of the time and the six pose columns."""
    needed = (TIME_COLUMN, *POSE_COLUMNS)
    missing = [column for column in needed if column not in names]
    if missing:
        raise InputFileError(
            f"{name} is an RTDE recording without the TCP pose: it has no column "
            f"{name_excerpt(missing)}; add {POSE_FIELD} to the output recipe (the record "
            f"configuration) and record again. Its {len(names)} columns: {name_excerpt(names)}"
        )
    return [names.index(column) for column in needed]


def _rows(
    lines: list[tuple[int, str]], width: int, delimiter: str, name: str
) -> tuple[list[tuple[int, list[str]]], bool]:
    """The data rows split into cells; a last row cut short is left out (and said so)."""
    rows = [(number, _split(line, delimiter)) for number, line in lines]
    torn = bool(rows) and len(rows[-1][1]) < width
    if torn:
        # A recorder stopped mid-write leaves its last line short; the rows before it are whole.
        rows.pop()
    for number, cells in rows:
        if len(cells) != width:
            raise InputFileError(
                f"{name} line {number} has {len(cells)} cells where the header names {width}; "
                "the file was edited or damaged, record again"
            )
    return rows, torn


def _numbers(
    rows: list[tuple[int, list[str]]], wanted: list[int], names: list[str], name: str
) -> np.ndarray:
    out = np.empty((len(rows), len(wanted)))
    for i, (number, cells) in enumerate(rows):
        for j, column in enumerate(wanted):
            try:
                value = float(cells[column])
            except ValueError:
                value = float("nan")
            if not np.isfinite(value):
                raise InputFileError(
                    f"{name} line {number}, column {names[column]!r}: {cells[column][:40]!r} is "
                    "not a finite number; record again"
                )
            out[i, j] = value
    return out
