"""What the child process of an upload's parse runs (see :func:`service.tasks.parse_in_child`).

Each ``parse_*`` function reads an upload from a file and returns its summary as JSON under
:data:`SUMMARY_KEY`, with its arrays, or writes the arrays to ``out_path`` itself so that they
never pass through the worker nor the server.

A child is a fresh interpreter, so what this module imports is paid for at every upload: only
the reader and the codecs, imported in the functions (a trace's child took 2.7 s with the
worker's module and its imports, Open3D's among them, and takes the reader's 1 s here). Whatever
else a parse checks afterwards (the units of a trace, from its bounds) is done by the worker.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Literal, TypedDict, Unpack

import numpy as np

from drivers.files import atomic_path
from drivers.npz import read_npz, write_npz

if TYPE_CHECKING:
    from recon.inputs import Recording, Scan

#: Key of a parse's summary among the arrays its child hands back (JSON text in a 0-d array: the
#: child's results cross as arrays only, never pickles).
SUMMARY_KEY = "summary_json"

Arrays = dict[str, np.ndarray]


def save_arrays(path: str | Path, arrays: Mapping[str, np.ndarray]) -> None:
    """Write arrays as an ``.npz`` (:func:`drivers.npz.write_npz`) that appears only when
    complete, readable by its owner only (it lands in the data folder). Every artifact's arrays
    are written here (as its codec in :mod:`service.artifacts` encoded them), read by
    :func:`load_arrays`.
    """
    with atomic_path(Path(path)) as tmp:
        with tmp.open("wb") as handle:
            write_npz(handle, arrays)
        os.chmod(tmp, 0o600)


def load_arrays(path: str | Path | IO[bytes]) -> Arrays:
    """The arrays of an ``.npz`` written by :func:`save_arrays` (never a pickle)."""
    return read_npz(path)


def recording_summary(recording: Recording, fmt: str) -> dict[str, Any]:
    """Size and extent of a recording (see :class:`service.artifacts.RecordingSummary`)."""
    points = np.asarray(recording.points_m)
    t = recording.t_s
    assert recording.piece is not None  # labels, set by Recording.__post_init__
    # Traced length only: the stretch between two pieces kept apart was not traced.
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)[np.diff(recording.piece) == 0]
    return {
        "format": fmt,
        "n_samples": int(len(points)),
        "length_m": float(np.sum(steps)),
        "duration_s": None if t is None else float(t[-1] - t[0]),
        "has_orientations": recording.orientations_xyzw is not None,
        "bounds_m": [points.min(axis=0).tolist(), points.max(axis=0).tolist()],
    }


def scan_summary(
    scan: Scan,
    fmt: str,
    *,
    n_dropped: int = 0,
    notes: Iterable[str] = (),
    dropped_because: str | None = None,
) -> dict[str, Any]:
    """Size and extent of a scan (see :class:`service.artifacts.ScanSummary`)."""
    points = np.asarray(scan.points_m)
    return {
        "format": fmt,
        "n_points": int(len(points)),
        "n_dropped": int(n_dropped),
        "dropped_because": dropped_because if n_dropped else None,
        "has_normals": scan.normals is not None,
        "notes": list(notes),
        "bounds_m": [points.min(axis=0).tolist(), points.max(axis=0).tolist()],
    }


def _handed_back(arrays: Arrays, summary: dict[str, Any], out_path: str | None) -> Arrays:
    """What a parse's child hands back: ``summary``, and ``arrays`` unless it wrote them to
    ``out_path``."""
    if out_path is not None:
        save_arrays(out_path, arrays)
        arrays = {}
    return {**arrays, SUMMARY_KEY: np.array(json.dumps(summary, default=_plain))}


def _plain(value: object) -> object:
    """numpy scalars and arrays as JSON values (``json.dumps``'s ``default``)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


class TraceOptions(TypedDict):
    """How to read a trace: :func:`parse_recording`'s options, which :func:`parse_touches`
    passes on."""

    format: str | None
    units: str | None
    rigid_body: str | None
    marker: str | None
    tip_offset_m: tuple[float, float, float] | None
    piece: int | Literal["all"] | None


def parse_recording(
    path: str,
    filename: str,
    *,
    format: str | None,
    units: str | None,
    rigid_body: str | None,
    marker: str | None,
    tip_offset_m: tuple[float, float, float] | None,
    piece: int | Literal["all"] | None,
    out_path: str | None = None,
) -> Arrays:
    """The trace at ``path`` as a recording's arrays and summary.

    Raises
    ------
    UnitsMismatchError
        A path too large to be in metres (nothing is written to ``out_path``).
    """
    from drivers.tracking.readers import read_trace
    from recon.reconstruct import check_scales
    from service.artifacts import RecordingCodec

    trace = read_trace(
        Path(path).read_bytes(),
        name=filename,
        fmt=format,
        units=units,
        rigid_body=rigid_body,
        marker=marker,
        tip_offset_m=None if tip_offset_m is None else np.array(tip_offset_m),
        piece=piece,
        # The session's offset is for rigid-body recordings; a position-only file holds tip
        # positions already (the summary says the offset was not applied).
        tip_needs_orientations=False,
    )
    recording = trace.recording
    check_scales(recording.points_m, None)
    summary = recording_summary(recording, trace.format)
    summary.update(trace.summary())
    if tip_offset_m is not None and not trace.tip_offset_applied:
        summary.setdefault("notes", []).append(
            "the session's tip offset was not applied: the file has positions only (taken "
            "as the pen's tip)"
        )
    return _handed_back(RecordingCodec.encode(recording), summary, out_path)


def parse_touches(
    path: str,
    filename: str,
    *,
    out_path: str | None = None,
    **trace_options: Unpack[TraceOptions],
) -> Arrays:
    """A touch recording: the trace's arrays, with the tip's rests found and summarised.

    The options are :func:`parse_recording`'s.

    Raises
    ------
    DegenerateInputError
        No sample times, or fewer rests than a registration needs (nothing is written).
    """
    from recon.touches import touches_in

    handed = parse_recording(path, filename, **trace_options)
    summary: dict[str, Any] = json.loads(str(handed.pop(SUMMARY_KEY)))
    arrays = handed
    found = touches_in(arrays["points_m"], arrays.get("t_s"), label=filename)
    dwells, notes = found.dwells, found.notes
    summary["n_touches"] = len(dwells)
    summary["touches_m"] = [d.point_m.tolist() for d in dwells]
    summary["touch_spread_m"] = [d.spread_m for d in dwells]
    summary.setdefault("notes", []).extend(notes)
    return _handed_back(arrays, summary, out_path)


def parse_pivot(
    path: str,
    filename: str,
    *,
    format: str | None,
    units: str | None,
    rigid_body: str | None,
    out_path: str | None = None,
) -> Arrays:
    """The pivot calibration of the recording at ``path`` (its JSON result as the summary)."""
    from drivers.tracking.readers import read_raw_trace
    from service import pipelines

    raw = read_raw_trace(
        Path(path).read_bytes(), name=filename, fmt=format, units=units, rigid_body=rigid_body
    )
    # Judged against its tolerance by the caller (tasks.ParsePivot), which keeps the figures.
    outcome = pipelines.pivot(raw, accept_poor_fit=True)
    return _handed_back({}, outcome.as_json(), out_path)


def parse_scan(
    path: str,
    filename: str,
    *,
    format: str | None,
    units: str,
    options: dict[str, Any] | None,
    limits: dict[str, float] | None,
    limit_names: dict[str, str] | None,
    out_path: str | None = None,
) -> Arrays:
    """The scan at ``path`` as a scan's arrays and summary."""
    from drivers.scanning.pointcloud import read_scan
    from service.artifacts import ScanCodec

    scan_file = read_scan(
        Path(path).read_bytes(),
        name=filename,
        fmt=format,
        units=units,
        options=options,
        limits=limits,
        limit_names=limit_names,
    )
    summary = scan_summary(
        scan_file.scan,
        scan_file.format,
        n_dropped=scan_file.n_dropped,
        notes=scan_file.notes,
        dropped_because=scan_file.dropped_because,
    )
    return _handed_back(ScanCodec.encode(scan_file.scan), summary, out_path)
