"""The canonical trace file: CSV with a header naming ``x,y,z`` and optionally ``t`` and
``qx,qy,qz,qw`` (scalar-last quaternion), in metres and seconds unless told otherwise."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from drivers.errors import InputFileError
from drivers.files import csv_rows
from drivers.tracking.base import name_excerpt
from drivers.units import metres_per
from recon.inputs import Recording

POSITION_COLUMNS = ("x", "y", "z")
QUATERNION_COLUMNS = ("qx", "qy", "qz", "qw")


#: The most columns a trace CSV may have (a 200,000-column file held a parse slot for 300 s;
#: a data logger's export of a few hundred channels is fine).
MAX_COLUMNS = 1024


def read_trace_csv(
    source: str | Path | bytes, *, units: str = "m", name: str | None = None
) -> Recording:
    """Read a canonical trace CSV.

    Parameters
    ----------
    source : path or bytes
        The file, or its content (an upload).
    units : {"m", "mm"}
        Length unit of the positions.
    name : str, optional
        The file's name, for messages (uploads).

    Returns
    -------
    Recording
        Positions in metres, times in seconds if a ``t`` column is present, orientations if all
        four quaternion columns are present (normalised; a row whose quaternion has zero length
        is an error).

    Raises
    ------
    InputFileError
        Missing file, no header with x, y and z, non-numeric cells, NaN or infinite values,
        times that do not increase, or fewer than two rows.
    ValueError
        An unknown unit.
    """
    scale = metres_per(units)
    name = name or ("upload" if isinstance(source, bytes) else str(source))
    text = _read_text(source, name)
    rows = csv_rows(io.StringIO(text), name)
    rows = [row for row in rows if any(cell.strip() for cell in row)]
    if not rows:
        raise InputFileError(f"{name} is empty; expected a CSV with a header row x,y,z")
    if len(rows[0]) > MAX_COLUMNS:
        raise InputFileError(
            f"{name} has {len(rows[0])} columns; a trace file has at most {MAX_COLUMNS} "
            "(x,y,z, optionally t and qx,qy,qz,qw, and a few more): export the pen's columns "
            "only"
        )
    header = [cell.strip().lower() for cell in rows[0]]
    missing = [c for c in POSITION_COLUMNS if c not in header]
    if missing:
        # A header is quoted in part: a recorder's can run to kilobytes.
        raise InputFileError(
            f"{name} has no column {', '.join(missing)} in its header "
            f"({name_excerpt(cell.strip() for cell in rows[0])}); the first row must name the "
            "columns, at least x,y,z (optionally t and qx,qy,qz,qw)"
        )
    body = rows[1:]
    if len(body) < 2:
        raise InputFileError(f"{name} has {len(body)} data rows; a trace needs at least two")
    width = len(header)
    for line, row in enumerate(body, start=2):
        if len(row) != width:
            raise InputFileError(
                f"{name} line {line} has {len(row)} cells where the header has {width}"
            )
    try:
        data = np.array([[float(cell) for cell in row] for row in body], dtype=np.float64)
    except ValueError as exc:
        raise InputFileError(f"{name} has a cell that is not a number: {exc}") from None
    bad = ~np.isfinite(data).all(axis=1)
    if np.any(bad):
        line = int(np.flatnonzero(bad)[0]) + 2
        raise InputFileError(
            f"{name} has {int(bad.sum())} rows with NaN or infinite values (first on line "
            f"{line}); remove those samples or fill the gaps before reconstructing"
        )
    first: dict[str, int] = {}
    for index, label in enumerate(header):
        first.setdefault(label, index)  # a repeated name: its first column, as before
    wanted = (*POSITION_COLUMNS, "t", *QUATERNION_COLUMNS)
    column = {label: data[:, first[label]] for label in wanted if label in first}
    points = np.column_stack([column[c] for c in POSITION_COLUMNS]) * scale
    times = column.get("t")
    if times is not None and np.any(np.diff(times) <= 0):
        line = int(np.flatnonzero(np.diff(times) <= 0)[0]) + 3
        raise InputFileError(
            f"{name}: the times in column t do not increase (line {line}); sort the samples by "
            "time and remove repeated ones"
        )
    orientations = None
    if all(c in column for c in QUATERNION_COLUMNS):
        q = np.column_stack([column[c] for c in QUATERNION_COLUMNS])
        norm = np.linalg.norm(q, axis=1)
        if np.any(norm < 1e-9):
            line = int(np.flatnonzero(norm < 1e-9)[0]) + 2
            raise InputFileError(f"{name} line {line} has a zero quaternion")
        orientations = q / norm[:, None]
    return Recording(points_m=points, t_s=times, orientations_xyzw=orientations)


def write_trace_csv(path: Path, recording: Recording) -> None:
    """Write a recording as a canonical CSV (metres, seconds, scalar-last quaternions)."""
    columns = (["t"] if recording.t_s is not None else []) + list(POSITION_COLUMNS)
    parts = ([recording.t_s[:, None]] if recording.t_s is not None else []) + [recording.points_m]
    if recording.orientations_xyzw is not None:
        columns += list(QUATERNION_COLUMNS)
        parts.append(recording.orientations_xyzw)
    data = np.hstack(parts)
    np.savetxt(path, data, delimiter=",", header=",".join(columns), comments="", fmt="%.9g")


def _read_text(source: str | Path | bytes, name: str) -> str:
    if isinstance(source, bytes):
        raw = source
    else:
        try:
            raw = Path(source).read_bytes()
        except FileNotFoundError:
            raise InputFileError(f"{name} does not exist") from None
        except IsADirectoryError:
            raise InputFileError(f"{name} is a directory, not a CSV file") from None
        except OSError as exc:
            raise InputFileError(f"cannot read {name}: {exc.strerror}") from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputFileError(f"{name} is not a text (UTF-8) CSV file") from None
