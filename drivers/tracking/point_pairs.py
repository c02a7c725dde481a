"""Point pairs for the tracker-to-robot calibration: the same points in both frames, as CSV.

The header names ``base_x,base_y,base_z,tracker_x,tracker_y,tracker_z`` (any order, other
columns such as a label are ignored); one row per touched point.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from drivers.errors import InputFileError
from drivers.files import csv_rows
from drivers.units import metres_per
from recon.arrays import FloatArray

BASE_COLUMNS = ("base_x", "base_y", "base_z")
TRACKER_COLUMNS = ("tracker_x", "tracker_y", "tracker_z")


def read_point_pairs(
    source: str | Path | bytes, *, units: str = "m", name: str | None = None
) -> tuple[FloatArray, FloatArray]:
    """Read point pairs.

    Parameters
    ----------
    source : path or bytes
    units : {"m", "mm"}
    name : str, optional
        For messages (uploads).

    Returns
    -------
    base_m, tracker_m : ndarray of shape (N, 3), metres

    Raises
    ------
    InputFileError
        Missing file, missing columns, cells that are not finite numbers, no rows.
    ValueError
        An unknown unit.
    """
    scale = metres_per(units)
    label = name or ("upload" if isinstance(source, bytes) else str(source))
    try:
        raw = source if isinstance(source, bytes) else Path(source).read_bytes()
        text = raw.decode("utf-8-sig")
    except FileNotFoundError:
        raise InputFileError(f"{label} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"cannot read {label} as a text CSV: {exc}") from None
    rows = [row for row in csv_rows(io.StringIO(text), label) if any(c.strip() for c in row)]
    if not rows:
        raise InputFileError(
            f"{label} is empty; expected a header {','.join(BASE_COLUMNS + TRACKER_COLUMNS)}"
        )
    header = [c.strip().lower() for c in rows[0]]
    missing = [c for c in BASE_COLUMNS + TRACKER_COLUMNS if c not in header]
    if missing:
        raise InputFileError(
            f"{label} lacks the column(s) {', '.join(missing)}; the header must name "
            f"{','.join(BASE_COLUMNS + TRACKER_COLUMNS)}"
        )
    columns = [header.index(c) for c in BASE_COLUMNS + TRACKER_COLUMNS]
    values = []
    for line, row in enumerate(rows[1:], start=2):
        try:
            numbers = [float(row[i]) for i in columns]
        except (ValueError, IndexError):
            raise InputFileError(
                f"{label} line {line}: every pair needs six numbers ({row!r})"
            ) from None
        if not all(np.isfinite(numbers)):
            raise InputFileError(f"{label} line {line} has NaN or infinite values")
        values.append(numbers)
    if not values:
        raise InputFileError(f"{label} has a header but no point pairs")
    data = np.array(values) * scale
    return data[:, :3], data[:, 3:]
