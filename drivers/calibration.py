"""Stored calibrations: rigid transforms between frames, as JSON.

A file holds one transform ``T_a_b`` (4x4, mapping points of frame b into frame a) with its
frames, units and, when measured, residuals::

    {"name": "T_base_tracker", "matrix": [[...], [...], [...], [0, 0, 0, 1]],
     "units": "m", "created": "2026-11-22T10:00:00+00:00", "residual_rms_m": 0.0003,
     "residuals_m": [0.0002, ...]}

The translation is in ``units`` and converted to metres on reading. A pen's tip calibration
(from a pivot calibration) is a file of its own::

    {"name": "tip_offset", "offset": [0.004, -0.007, 0.142], "units": "m",
     "rigid_body": "pen", "created": "...", "residual_rms_m": 0.0004}
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from drivers.errors import InputFileError, clipped
from drivers.files import atomic_path
from drivers.units import metres_per
from recon.arrays import FloatArray
from recon.calibrate import MAX_TIP_OFFSET_M
from recon.transforms import check_rigid


@dataclass(frozen=True)
class Calibration:
    """A stored transform. ``matrix`` is in metres."""

    name: str
    matrix: FloatArray
    created: str | None = None
    residual_rms_m: float | None = None


def read_calibration(
    source: str | Path | bytes, *, expect: str | None = None, label: str | None = None
) -> Calibration:
    """Read a calibration file.

    Parameters
    ----------
    expect : str, optional
        The transform's name the caller needs (e.g. "T_base_tracker"); a file naming another
        one is refused, so a scanner calibration is not used as a robot one by mistake.

    Raises
    ------
    InputFileError
        Unreadable JSON, a missing or non-rigid matrix, unknown units, the wrong name.
    """
    label = label or ("upload" if isinstance(source, bytes) else str(source))
    data = _load_json(source, label)
    name = str(data.get("name", expect or "transform"))
    if expect is not None and name != expect:
        raise InputFileError(f"{label} holds {name}, but {expect} is needed here")
    if "matrix" not in data:
        raise InputFileError(f'{label} has no "matrix" (a 4x4 list of rows)')
    try:
        scale = metres_per(str(data.get("units", "m")))
        matrix = np.array(data["matrix"], dtype=np.float64)
        matrix = check_rigid(matrix, name=f"the matrix in {label}").copy()
    except (ValueError, TypeError, OverflowError) as exc:  # a JSON integer of 400 digits
        raise InputFileError(f"{label}: {exc}") from None
    matrix[:3, 3] *= scale
    return Calibration(
        name=name,
        matrix=matrix,
        created=data.get("created"),
        residual_rms_m=_residual(data, label),
    )


def write_calibration(
    path: str | Path,
    name: str,
    matrix: FloatArray,
    *,
    residual_rms_m: float | None = None,
    extra: dict[str, Any] | None = None,
) -> None:
    """Write a calibration (metres, with the current time); ``extra`` holds JSON-able details
    such as per-pair residuals."""
    content = {
        "name": name,
        "matrix": np.asarray(check_rigid(matrix)).tolist(),
        "units": "m",
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    if residual_rms_m is not None:
        content["residual_rms_m"] = residual_rms_m
    content.update(extra or {})
    _write_json(path, content)


@dataclass(frozen=True)
class TipCalibration:
    """A pen's tip in its rigid body's frame (metres)."""

    offset_m: FloatArray
    rigid_body: str | None = None
    created: str | None = None
    residual_rms_m: float | None = None


def write_tip_calibration(
    path: str | Path,
    offset_m: FloatArray,
    *,
    rigid_body: str | None = None,
    residual_rms_m: float | None = None,
    extra: dict[str, Any] | None = None,
) -> None:
    """Write a tip calibration (metres, with the current time)."""
    offset = np.asarray(offset_m, dtype=np.float64)
    if offset.shape != (3,) or not np.all(np.isfinite(offset)):
        raise ValueError(f"offset_m must be 3 finite numbers, got {offset_m!r}")
    content = {
        "name": "tip_offset",
        "offset": offset.tolist(),
        "units": "m",
        "rigid_body": rigid_body,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    if residual_rms_m is not None:
        content["residual_rms_m"] = residual_rms_m
    content.update(extra or {})
    _write_json(path, content)


def read_tip_calibration(source: str | Path | bytes, *, label: str | None = None) -> TipCalibration:
    """Read a tip calibration written by :func:`write_tip_calibration`.

    Raises
    ------
    InputFileError
        Unreadable JSON, another kind of calibration, a missing or non-finite offset, unknown
        units, or an offset longer than a pen's 0.5 m (units wrong).
    """
    label = label or ("upload" if isinstance(source, bytes) else str(source))
    data = _load_json(source, label)
    if data.get("name") != "tip_offset" or "offset" not in data:
        raise InputFileError(
            f'{label} is not a tip calibration (expected "name": "tip_offset" and an "offset"); '
            "make one with: teachpath calibrate pivot RECORDING"
        )
    try:
        scale = metres_per(str(data.get("units", "m")))
        offset = np.array(data["offset"], dtype=np.float64) * scale
    except (ValueError, TypeError, OverflowError) as exc:  # a JSON integer of 400 digits
        raise InputFileError(f"{label}: {exc}") from None
    if offset.shape != (3,) or not np.all(np.isfinite(offset)):
        raise InputFileError(f'{label}: "offset" must be 3 finite numbers')
    if np.linalg.norm(offset) > MAX_TIP_OFFSET_M:
        raise InputFileError(
            f"{label}: a tip {np.linalg.norm(offset) * 1e3:.0f} mm from the rigid body, more "
            f"than a pen's {MAX_TIP_OFFSET_M * 1e3:.0f} mm; are the units "
            'right (metres unless the file says "units": "mm")?'
        )
    return TipCalibration(
        offset_m=offset,
        rigid_body=data.get("rigid_body"),
        created=data.get("created"),
        residual_rms_m=_residual(data, label),
    )


def _residual(data: dict[str, Any], label: str) -> float | None:
    """The optional ``residual_rms_m`` field: a non-negative number of metres, or absent."""
    value = data.get("residual_rms_m")
    if value is None:
        return None
    try:
        residual = float(value) if not isinstance(value, bool) else None
    except (TypeError, ValueError, OverflowError):
        residual = None
    if residual is None or not isinstance(value, int | float) or not 0 <= residual < np.inf:
        raise InputFileError(
            f'{label}: "residual_rms_m" must be a non-negative number of metres, got '
            f"{clipped(repr(value), 40)}"
        )
    return residual


def _load_json(source: str | Path | bytes, label: str) -> dict[str, Any]:
    try:
        raw = source if isinstance(source, bytes) else Path(source).read_bytes()
        data = json.loads(raw)
    except FileNotFoundError:
        raise InputFileError(f"{label} does not exist") from None
    except (OSError, ValueError, RecursionError) as exc:  # RecursionError: nested too deep
        raise InputFileError(f"{label} is not a readable JSON calibration: {exc}") from None
    if not isinstance(data, dict):
        raise InputFileError(f"{label} is not a JSON object")
    return data


def _write_json(path: str | Path, content: dict[str, Any]) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(content, indent=2) + "\n")
