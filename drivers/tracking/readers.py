"""Trace files in any supported format, turned into clean pieces of pen-tip path.

A reader turns a file into a raw :class:`~drivers.tracking.base.SampleBatch` (every sample,
lost ones flagged); :func:`read_trace` then moves the samples to the pen's tip (with a tip
calibration), cleans dropouts and outliers (:mod:`drivers.tracking.gaps`) and picks a piece.

Formats are registered by name in :data:`TRACE_READERS` (a :class:`~drivers.registry.Registry`)
and imported lazily: ``csv`` (the canonical ``t,x,y,z,qx,qy,qz,qw``), ``motive`` (OptiTrack
Motive CSV exports), ``rtde`` (a Universal Robots arm's TCP pose recorded over RTDE), both of
which share the ``.csv`` suffix and are told apart by their first line, and ``c3d`` (marker
files). Packages add formats through the entry-point group ``teachpath.trace_readers``: a
function taking ``(source, *, name, units, **options)`` and returning a :class:`RawTrace`, chosen
explicitly or by a suffix equal to its name.

Every trace is checked to move (:data:`MIN_TRACE_EXTENT_M`) once cleaned, in
:func:`trace_from_raw`, where the files and the live captures meet.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from drivers.errors import InputFileError, UnknownFormatError
from drivers.registry import Registry
from drivers.tracking.base import SampleBatch
from drivers.tracking.gaps import CleanTrace, GapParams, apply_tip_offset, clean_trace
from recon.arrays import FloatArray
from recon.inputs import Recording

#: Which piece of a trace split by long dropouts: an index, "all" (kept apart), None (the
#: longest).
Piece = int | Literal["all"] | None


@dataclass(frozen=True)
class RawTrace:
    """What a reader found in a file.

    Attributes
    ----------
    batch : SampleBatch
        Every sample (rigid-body origin or marker, tracker frame, metres), lost ones flagged.
    format : str
    rate_hz : float or None
        The tracker's frame rate, when the file states it.
    meta : dict
        Format-specific facts worth reporting (rigid body, marker, units, take name, ...).
    """

    batch: SampleBatch
    format: str
    rate_hz: float | None = None
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class TraceFile:
    """A trace file read, cleaned and ready to reconstruct.

    Attributes
    ----------
    recording : Recording
        The chosen piece (pen tip, tracker frame), or every piece kept apart (``piece`` "all").
    raw : RawTrace
    clean : CleanTrace
        Every piece and the gap report.
    piece : int or "all"
        Index of ``recording`` in ``clean.pieces``, or "all".
    tip_offset_applied : bool
        Whether the samples were moved to the pen's tip.
    """

    recording: Recording
    raw: RawTrace
    clean: CleanTrace
    piece: int | Literal["all"]
    tip_offset_applied: bool = False

    @property
    def format(self) -> str:
        return self.raw.format

    def summary(self) -> dict[str, Any]:
        """JSON-able facts: format, gaps, pieces."""
        return {
            "format": self.raw.format,
            "rate_hz": self.raw.rate_hz,
            **{k: v for k, v in self.raw.meta.items() if _jsonable(v)},
            "piece": self.piece,
            "n_pieces": len(self.clean.pieces),
            "gaps": self.clean.report.as_dict(),
            "gap_report": self.clean.report.lines(),
            "tip_offset_applied": self.tip_offset_applied,
        }


#: Trace readers by format name ("module:function"), each reading (source, *, name, units,
#: rigid_body, marker) into a RawTrace; imported on first use.
TRACE_READERS: Registry[Callable[..., RawTrace]] = Registry(
    "trace format",
    {
        "csv": "drivers.tracking.readers:read_canonical_raw",
        "motive": "drivers.tracking.readers:read_motive_raw",
        "rtde": "drivers.tracking.readers:read_rtde_raw",
        "c3d": "drivers.tracking.readers:read_c3d_raw",
    },
    group="teachpath.trace_readers",
    unknown_error=UnknownFormatError,
)
#: File suffix -> format name (".csv" is sniffed: canonical, Motive or RTDE).
TRACE_SUFFIXES: dict[str, str] = {".csv": "csv", ".c3d": "c3d"}
#: The first cells of a Motive export's first line (with or without its metadata header).
_MOTIVE_FIRST_CELLS = {"format version", "type", "name", "id", "frame"}
#: Row labels that Motive writes after empty leading cells.
_MOTIVE_ROW_LABELS = {"type", "name", "id"}
#: First cells of the legacy OptiTrack CSV (Tracking Tools, early Motive), which the Motive reader
#: recognises and refuses with advice.
_LEGACY_OPTITRACK_FIRST_CELLS = {"comment", "info", "righthanded", "lefthanded", "trackable"}
#: How RTDE's output names start (actual_TCP_pose, target_q...), after the header's "timestamp".
_RTDE_NAME_PREFIXES = ("actual_", "target_")
#: A trace whose cleaned samples span less than this (the diagonal of their bounding box) is a pen
#: that did not move. 3 mm is well above what a still pen spans: an optical tracker's jitter is
#: a tenth of a millimetre or less (a still take of the issue spanned 0.04 mm) and a hand held
#: still drifts about a millimetre; yet it is below the 8 mm neighbourhood over which the
#: reconstruction fits the scan, so no feature can be traced within it.
MIN_TRACE_EXTENT_M = 3e-3
#: t,x,y,z,qx,qy,qz,qw: a longer row of bare numbers is no canonical trace.
_CANONICAL_MAX_COLUMNS = 8


def read_raw_trace(
    source: str | Path | bytes,
    *,
    name: str | None = None,
    fmt: str | None = None,
    units: str | None = None,
    rigid_body: str | None = None,
    marker: str | None = None,
) -> RawTrace:
    """Read a trace file into raw samples (no cleaning), in any supported format.

    Parameters
    ----------
    source : path or bytes
        The file, or its content (an upload; ``name`` then gives the suffix).
    name : str, optional
        File name for the suffix and for messages.
    fmt : str, optional
        Format name (see :data:`TRACE_READERS`); default from the suffix (and the content).
    units : {"m", "mm"}, optional
        Length unit where the file does not state one (canonical CSV; default metres).
    rigid_body, marker : str, optional
        Which rigid body (Motive) or marker (Motive, C3D) is the pen.

    Raises
    ------
    UnknownFormatError
        No reader for the format or suffix.
    MissingDependencyError
        The format's reader needs a package that is not installed (a subclass of
        UnknownFormatError).
    InputFileError
        The file is wrong for its format.
    ValueError
        An option that the format does not take.
    """
    label = name or ("upload" if isinstance(source, bytes) else str(source))
    fmt = _format_for(source, label, fmt)
    if rigid_body is not None and fmt != "motive":
        raise ValueError("a rigid body name applies to Motive CSV exports only")
    if marker is not None and fmt not in ("motive", "c3d"):
        raise ValueError("a marker name applies to Motive CSV exports and C3D files only")
    reader = TRACE_READERS.load(fmt)
    options = {"rigid_body": rigid_body, "marker": marker}
    options = {k: v for k, v in options.items() if v is not None}
    return reader(source, name=label, units=units, **options)


def read_trace(
    source: str | Path | bytes,
    *,
    name: str | None = None,
    fmt: str | None = None,
    units: str | None = None,
    rigid_body: str | None = None,
    marker: str | None = None,
    tip_offset_m: FloatArray | None = None,
    gaps: GapParams | None = None,
    piece: Piece = None,
    tip_needs_orientations: bool = True,
) -> TraceFile:
    """Read a trace file, move it to the pen's tip, clean it and pick a piece.

    Parameters
    ----------
    source, name, fmt, units, rigid_body, marker
        See :func:`read_raw_trace`.
    tip_offset_m : ndarray of shape (3,), optional
        The pen's tip in its rigid body's frame (a pivot calibration); without it the tracked
        point is used as it is (the rigid body's pivot as set in the tracker's software).
    gaps : GapParams, optional
        How dropouts and outliers are handled.
    piece : int or "all", optional
        Which piece to return when long dropouts split the recording (0-based, time order), or
        "all": every piece, kept apart (the arm lifts between them); default the longest.
    tip_needs_orientations : bool
        True: a tip offset with a position-only trace is an error (the user asked for the
        offset). False: such a trace is used as it is and ``tip_offset_applied`` says so (a
        session's stored offset meets a file that already holds tip positions).

    Raises
    ------
    UnknownFormatError, InputFileError, ValueError
        See :func:`read_raw_trace`; also a piece index out of range.
    """
    raw = read_raw_trace(
        source, name=name, fmt=fmt, units=units, rigid_body=rigid_body, marker=marker
    )
    return trace_from_raw(
        raw,
        tip_offset_m=tip_offset_m,
        gaps=gaps,
        piece=piece,
        tip_needs_orientations=tip_needs_orientations,
    )


def trace_from_raw(
    raw: RawTrace,
    *,
    tip_offset_m: FloatArray | None = None,
    gaps: GapParams | None = None,
    piece: Piece = None,
    tip_needs_orientations: bool = True,
) -> TraceFile:
    """Raw samples (from a file or a capture) moved to the pen's tip, cleaned, a piece picked.

    Parameters and errors as :func:`read_trace` from ``tip_offset_m`` on.
    """
    batch = raw.batch
    check_trace_units(batch.position_m[np.asarray(batch.valid, dtype=bool)], raw.meta.get("units"))
    apply_tip = tip_offset_m is not None and (
        tip_needs_orientations or batch.orientation_xyzw is not None
    )
    if apply_tip and tip_offset_m is not None:
        batch = apply_tip_offset(batch, tip_offset_m)
    clean = _clean(batch, gaps)
    if piece == "all":
        recording = Recording.joined(list(clean.pieces))
        require_motion(recording)
        return TraceFile(
            recording=recording,
            raw=raw,
            clean=clean,
            piece="all",
            tip_offset_applied=apply_tip,
        )
    if piece is None:
        index = clean.longest()
    elif isinstance(piece, int) and 0 <= piece < len(clean.pieces):
        index = piece
    else:
        raise ValueError(
            f"piece {piece} does not exist: the recording has {len(clean.pieces)} piece(s) "
            f"(0 to {len(clean.pieces) - 1}, or all)"
        )
    require_motion(clean.pieces[index], None if len(clean.pieces) == 1 else index)
    return TraceFile(
        recording=clean.pieces[index],
        raw=raw,
        clean=clean,
        piece=index,
        tip_offset_applied=apply_tip,
    )


#: A traced path fits in a robot's reach; one wider than this (m) is a unit mix-up.
MAX_TRACE_EXTENT_M = 10.0
#: Motion-capture volumes are tens of metres at most: a sample farther from the tracker's
#: origin (m) is a unit mix-up.
MAX_TRACKER_DISTANCE_M = 100.0


def check_trace_units(points_m: FloatArray, units: str | None) -> None:
    """Refuse a trace whose size says its numbers are in the other unit.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3), metres
        The valid samples, as read.
    units : str or None
        The unit the numbers were read in ("m", "mm", or what the file declared).

    Raises
    ------
    UnitsMismatchError
        Millimetres read as metres (a path wider than a robot's reach or samples beyond any
        tracking volume), or metres read as millimetres (a path of a fraction of a millimetre
        narrower than :data:`MIN_TRACE_EXTENT_M`, which would be a plausible path in metres).
    """
    from recon.errors import UnitsMismatchError

    if len(points_m) == 0:
        return
    extent_m = float(np.linalg.norm(np.ptp(points_m, axis=0)))
    farthest_m = float(np.abs(points_m).max())
    stated = f"read as {units}" if units else "read as metres"
    if extent_m > MAX_TRACE_EXTENT_M or farthest_m > MAX_TRACKER_DISTANCE_M:
        raise UnitsMismatchError(
            f"the trace, {stated}, spans {extent_m:.3g} m and reaches {farthest_m:.3g} m from "
            "the tracker's origin, beyond any robot cell: its numbers look like millimetres; "
            "upload it with its units set to mm (units=mm, --units mm)"
        )
    as_metres_m = extent_m * 1e3
    plausible = MIN_TRACE_EXTENT_M <= as_metres_m <= MAX_TRACE_EXTENT_M
    if units == "mm" and extent_m < MIN_TRACE_EXTENT_M and plausible:
        raise UnitsMismatchError(
            f"the trace, read as millimetres, spans only {extent_m * 1e3:.3g} mm: if its "
            f"numbers are metres it would span {as_metres_m:.3g} m; upload it with its units "
            "set to m (units=m, --units m). Otherwise the pen did not move: record the trace again"
        )


def require_motion(recording: Recording, piece: int | None = None) -> None:
    """Refuse a trace of a pen that did not move (see :data:`MIN_TRACE_EXTENT_M`).

    Reconstructing a still pen gives a few points of jitter cut into segments, which look like a
    result; this says what happened instead.

    Parameters
    ----------
    recording : Recording
        The cleaned trace (pen tip, metres).
    piece : int, optional
        Which piece of a split recording it is, for the message.

    Raises
    ------
    InputFileError
        Its samples span less than :data:`MIN_TRACE_EXTENT_M`.
    """
    points = recording.points_m
    if len(points) == 0:
        return  # the readers refuse empty traces with their own reasons
    extent = float(np.linalg.norm(np.ptp(points, axis=0)))
    if extent >= MIN_TRACE_EXTENT_M:
        return
    where = "" if piece is None else f" in piece {piece} of the recording"
    raise InputFileError(
        f"the pen did not move{where} (extent {extent * 1e3:.2f} mm); record a trace that "
        f"follows the feature, at least {MIN_TRACE_EXTENT_M * 1e3:.0f} mm of motion"
    )


def _clean(batch: SampleBatch, gaps: GapParams | None) -> CleanTrace:
    if batch.t_s is not None:
        return clean_trace(batch, params=gaps)
    # Without times there is nothing to tell a dropout by: one piece, as given.
    from drivers.tracking.gaps import GapReport

    recording = Recording(points_m=batch.position_m, orientations_xyzw=batch.orientation_xyzw)
    report = GapReport(n_samples=len(recording), n_invalid=0, n_outliers=0, n_bridged=0)
    return CleanTrace((recording,), (np.zeros(len(recording), dtype=bool),), report)


def read_canonical_raw(
    source: str | Path | bytes, *, name: str | None = None, units: str | None = None
) -> RawTrace:
    """The canonical CSV as raw samples (every row valid; ``t_s`` None if it has no t)."""
    from drivers.tracking.canonical_csv import read_trace_csv

    recording = read_trace_csv(source, units=units or "m", name=name)
    batch = SampleBatch(
        t_s=recording.t_s,
        position_m=recording.points_m,
        orientation_xyzw=recording.orientations_xyzw,
        valid=np.ones(len(recording), dtype=bool),
    )
    rate = None
    if recording.t_s is not None and len(recording) > 1:
        rate = float(1.0 / np.median(np.diff(recording.t_s)))
    return RawTrace(batch=batch, format="csv", rate_hz=rate, meta={"units": units or "m"})


def read_motive_raw(
    source: str | Path | bytes,
    *,
    name: str | None = None,
    units: str | None = None,
    rigid_body: str | None = None,
    marker: str | None = None,
) -> RawTrace:
    """A Motive CSV export's rigid body (or marker) as raw samples."""
    from drivers.tracking.motive_csv import read_motive_csv

    trace = read_motive_csv(source, rigid_body=rigid_body, marker=marker, units=units, name=name)
    meta = {
        "units": trace.length_units,
        "rigid_body": trace.rigid_body,
        "marker": trace.marker,
        "rotation_type": trace.rotation_type,
        "take_name": trace.take_name,
        "rigid_bodies": list(trace.available),
    }
    return RawTrace(batch=trace.batch, format="motive", rate_hz=trace.rate_hz, meta=meta)


def read_rtde_raw(
    source: str | Path | bytes,
    *,
    name: str | None = None,
    units: str | None = None,
) -> RawTrace:
    """A Universal Robots RTDE recording's TCP pose as raw samples (robot base frame)."""
    from drivers.tracking.rtde_csv import read_rtde_csv

    trace = read_rtde_csv(source, units=units, name=name)
    meta = {
        "units": "m",
        "frame": "robot base",
        "pose": trace.pose,
        "torn_last_line_dropped": trace.torn_last_line,
    }
    return RawTrace(batch=trace.batch, format="rtde", rate_hz=trace.rate_hz, meta=meta)


def read_c3d_raw(
    source: str | Path | bytes,
    *,
    name: str | None = None,
    units: str | None = None,
    marker: str | None = None,
) -> RawTrace:
    """One marker of a C3D file as raw samples (positions only)."""
    from drivers.tracking.c3d import read_c3d

    trace = read_c3d(source, marker=marker, units=units, name=name)
    meta = {"units": trace.units, "marker": trace.marker, "markers": list(trace.available)}
    if trace.notes:
        meta["notes"] = list(trace.notes)
    return RawTrace(batch=trace.batch, format="c3d", rate_hz=trace.rate_hz, meta=meta)


def _format_for(source: str | Path | bytes, label: str, fmt: str | None) -> str:
    if fmt is not None:
        fmt = fmt.lower()
        if fmt not in TRACE_READERS:
            raise TRACE_READERS.unknown(fmt)
        return fmt
    suffix = Path(label).suffix.lower()
    fmt = TRACE_SUFFIXES.get(suffix)
    if fmt is None and suffix[1:] and suffix[1:] in TRACE_READERS:
        return suffix[1:]  # a format a package registered, named like its suffix
    if fmt is None:
        raise UnknownFormatError(
            f"cannot tell the trace format of {label!r} from its suffix; use one of "
            f"{', '.join(sorted(TRACE_SUFFIXES))} or give the format "
            f"({', '.join(TRACE_READERS.names())})"
        )
    if fmt == "csv":
        return _sniff_csv(source)
    return fmt


def _sniff_csv(source: str | Path | bytes) -> str:
    """Which reader a ``.csv`` file is for, from its first line that is not blank."""
    try:
        if isinstance(source, bytes):
            head = source[:4096]
        else:
            with open(source, "rb") as handle:
                head = handle.read(4096)
    except OSError:
        return "csv"  # the reader reports the missing file
    for line in head.decode("utf-8-sig", errors="replace").splitlines():
        if line.strip(" ,\t"):
            if _looks_like_rtde(line):
                return "rtde"
            return "motive" if _looks_like_motive(line) else "csv"
    return "csv"


def _looks_like_motive(line: str) -> bool:
    """Motive exports start with their metadata line (``Format Version,...``) or, exported
    without it, with the ``Type``/``Name``/``Frame`` rows (the first cells of the Type, Name
    and ID rows are empty), or with bare data rows (a whole frame number, then more numbers
    than a canonical row can hold); canonical files start with column names. Routing the
    header-less exports, and the legacy OptiTrack CSV, to the Motive reader gets them its
    message about what to export instead."""
    cells = [cell.strip().strip('"').lower() for cell in line.split(",")]
    label = next((cell for cell in cells if cell), "")
    if label in _MOTIVE_FIRST_CELLS and (cells[0] or label in _MOTIVE_ROW_LABELS):
        return True
    if cells[0] in _LEGACY_OPTITRACK_FIRST_CELLS:
        return True
    return cells[0].isdigit() and len(cells) > _CANONICAL_MAX_COLUMNS


def _looks_like_rtde(line: str) -> bool:
    """RTDE recordings name their columns after the recipe, time first: ``timestamp`` then
    ``actual_q_0``, ``actual_TCP_pose_0``..., separated by spaces (UR's ``record.py``) or
    commas (ur_rtde)."""
    names = line.replace(",", " ").split()
    return (
        len(names) > 1
        and names[0] == "timestamp"
        and any(n.startswith(_RTDE_NAME_PREFIXES) for n in names[1:])
    )


def _jsonable(value: object) -> bool:
    return isinstance(value, (str, int, float, bool, type(None), list, tuple))


def recording_to_batch(recording: Recording) -> SampleBatch:
    """A recording as raw samples (all valid), e.g. to clean a capture."""
    return SampleBatch(
        t_s=recording.t_s,
        position_m=recording.points_m,
        orientation_xyzw=recording.orientations_xyzw,
        valid=np.ones(len(recording), dtype=bool),
    )


def require_orientations(raw: RawTrace, what: str) -> None:
    """Refuse a raw trace without orientations where ``what`` needs them."""
    if raw.batch.orientation_xyzw is None:
        raise InputFileError(
            f"{what} needs the pen's orientation, and this {raw.format} recording has positions "
            "only: record the pen as a rigid body (Motive) or export its quaternions"
        )
