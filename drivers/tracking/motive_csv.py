"""OptiTrack Motive CSV exports (Motive 1.x to 3.x, "Data Export: CSV" with the header on).

The layout, as Motive writes it::

    Format Version,1.23,Take Name,pen_07,...,Export Frame Rate,240.000000,...,
        Rotation Type,Quaternion,Length Units,Millimeters,Coordinate Space,Global
    <blank row>
    ,Type,Rigid Body,Rigid Body,...,Rigid Body Marker,...,Marker,...
    ,Name,Pen,Pen,...,Pen:Marker1,...
    ,ID,1,1,...                       (Motive 3 may add a Parent row)
    ,,Rotation,Rotation,Rotation,Rotation,Position,Position,Position,Mean Marker Error,...
    Frame,Time (Seconds),X,Y,Z,W,X,Y,Z,,...
    0,0.000000,0.012345,...

Quaternions are written X, Y, Z, W (scalar last). With an Euler rotation type (``XYZ``, ``ZYX``…)
the rotation columns are angles in degrees about the named axes, composed in that order about the
body's own (moved) axes -- Motive's "relative" convention, SciPy's upper-case (intrinsic)
sequences. Positions are in the header's ``Length Units``. A body or marker that was not tracked
in a frame leaves its cells empty. A rigid body's position is its pivot point, which the operator
places at the pen tip in Motive.

Variants read as well:

* Motive 1.x (format 1.21, 1.22): the Type, Name and ID rows have no labels (``,,Rigid Body,...``),
  the time column is ``Time``, and the quality statistics are ``Error Per Marker`` (the rigid
  body's mean marker error) and ``Marker Quality`` (after each rigid body marker).
* Files re-saved by a spreadsheet: ``120`` for ``120.000000``, rows padded with commas, blank rows
  of commas only.
* Skeletons (``Bone`` and ``Bone Marker`` columns, Motive 3's ``Parent`` row): a bone is chosen
  like a rigid body, a bone marker like a marker.

The legacy OptiTrack CSV of Tracking Tools and early Motive (format 1.1: ``comment``, ``info`` and
``frame`` rows, or the still older "trackable" rows) is recognised and refused: its rows vary in
length with what was seen in each frame and it does not state its length unit.
"""

from __future__ import annotations

import io
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from operator import itemgetter, methodcaller
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from drivers.errors import InputFileError
from drivers.files import csv_rows
from drivers.tracking.base import SampleBatch, name_excerpt
from drivers.units import metres_per
from recon.arrays import FloatArray
from recon.inputs import Recording

#: Metres per unit, by the names Motive writes in "Length Units".
MOTIVE_LENGTH_UNITS: dict[str, float] = {"meters": 1.0, "centimeters": 1e-2, "millimeters": 1e-3}
#: Euler orders Motive offers for "Rotation Type" (upper case: about the moved axes).
EULER_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")
#: Header rows before the ``Frame,Time`` row: Type, Name, ID, Parent and the component row, with
#: room to spare; a file that has not reached the ``Frame`` row by then is not a Motive export.
_MAX_HEADER_ROWS = 16
#: What Motive writes in the data rows. A body of only these characters needs no per-cell checks
#: for NaN or infinity spelled out, since neither can be written with them.
_PLAIN_NUMBER_BYTES = b"0123456789.,-\r\n"
_HEADERLESS_HINT = (
    "export the take again with the CSV export option 'Header information' checked (the header "
    "names the rigid bodies and gives the length unit)"
)
#: Asset types of the Type row. Motive 1.x writes the Type, Name and ID rows without their labels;
#: a row of these is how its Type row is known.
_ASSET_TYPES = {"Rigid Body", "Rigid Body Marker", "Marker", "Bone", "Bone Marker"}
#: The rigid body's mean marker error, by the names Motive 2+ and Motive 1.x give it.
_ERROR_COMPONENTS = ("Mean Marker Error", "Error Per Marker")
#: First cells of the legacy OptiTrack CSV (Tracking Tools, Motive before format 1.2).
_LEGACY_FIRST_CELLS = {"comment", "info", "righthanded", "lefthanded", "trackable"}
#: The options that give the length unit a file does not state, as messages name them.
_UNITS_OPTION = "--units mm (or m) on the command line, units='mm' (or 'm') in an upload"


@dataclass(frozen=True)
class MotiveTrace:
    """One rigid body (or one marker) of a Motive CSV export.

    Attributes
    ----------
    batch : SampleBatch
        ``t_s`` (N,) seconds from the file's Time column; ``position_m`` (N, 3) metres, NaN where
        the body was lost; ``orientation_xyzw`` (N, 4) unit quaternions, scalar last, NaN where
        lost, or None for a marker; ``valid`` (N,) False where lost or flagged low quality.
    rate_hz : float
        The export frame rate of the header (else the capture rate, else from the times).
    length_units : str
        The unit the file declares ("Millimeters"…), or the one passed if it declares none.
    rotation_type : str or None
        "Quaternion" or an Euler order such as "XYZ"; None for a marker.
    take_name : str
    rigid_body : str or None
        The rigid body read, or None when a marker was.
    marker : str or None
        The marker read, or None when a rigid body was.
    available : tuple of str
        The rigid bodies in the file.
    available_markers : tuple of str
        The markers in the file (physical and rigid body markers).
    mean_marker_error_m : ndarray of shape (N,), metres, or None
        Motive's "Mean Marker Error" of the rigid body (exported with the quality statistics);
        NaN where lost.
    metadata : dict
        The header's first row as written (key -> value).
    """

    batch: SampleBatch
    rate_hz: float
    length_units: str
    rotation_type: str | None
    take_name: str
    rigid_body: str | None
    marker: str | None
    available: tuple[str, ...]
    available_markers: tuple[str, ...]
    mean_marker_error_m: FloatArray | None = None
    metadata: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.batch)

    def to_recording(self) -> Recording:
        """The valid samples as a :class:`~recon.inputs.Recording` (lost frames left out).

        Raises
        ------
        InputFileError
            Fewer than two valid samples.
        """
        keep = self.batch.valid
        what = f"rigid body {self.rigid_body!r}" if self.rigid_body else f"marker {self.marker!r}"
        if int(keep.sum()) < 2:
            raise InputFileError(
                f"{what} is tracked in {int(keep.sum())} of {len(keep)} frames; a trace needs at "
                "least two"
            )
        q = self.batch.orientation_xyzw
        return Recording(
            points_m=self.batch.position_m[keep],
            t_s=self.batch.times_s()[keep],
            orientations_xyzw=None if q is None else q[keep],
        )


def read_motive_csv(  # noqa: C901
    source: str | Path | bytes,
    *,
    rigid_body: str | None = None,
    marker: str | None = None,
    units: str | None = None,
    name: str | None = None,
    max_marker_error_m: float | None = None,
) -> MotiveTrace:
    """Read one rigid body (or one marker) of a Motive CSV export.

    Parameters
    ----------
    source : path or bytes
        The file, or its content (an upload).
    rigid_body : str, optional
        The rigid body to read; needed when the file has several. A skeleton's bone is named the
        same way (a file of skeletons only always needs the name).
    marker : str, optional
        Read this marker's position instead of a rigid body (no orientation). A physical marker
        is preferred to a rigid body or bone marker of the same name.
    units : {"m", "mm"}, optional
        Length unit of the positions, used only when the header does not declare one.
    name : str, optional
        The file's name, for messages (uploads).
    max_marker_error_m : float, optional
        Frames whose Mean Marker Error exceeds this are flagged not valid (their positions are
        kept).

    Returns
    -------
    MotiveTrace

    Raises
    ------
    InputFileError
        Missing, empty or binary file; an export without its header; a legacy OptiTrack CSV; no
        rigid body, bone or marker of that name (or several and none named, or none at all);
        columns missing; a row cut short; cells that are not numbers or spell out NaN or infinity;
        times that do not increase; no length unit; Euler angles of an undeclared order.
    ValueError
        Both ``rigid_body`` and ``marker`` given, an unknown ``units`` or a negative
        ``max_marker_error_m``.
    """
    if rigid_body is not None and marker is not None:
        raise ValueError("give rigid_body or marker, not both")
    fallback_scale = None if units is None else metres_per(units)
    if max_marker_error_m is not None and not max_marker_error_m >= 0:
        raise ValueError(f"max_marker_error_m must be >= 0, got {max_marker_error_m}")
    name = name or ("upload" if isinstance(source, bytes) else str(source))
    raw = _read_bytes(source, name)
    if not raw or raw.isspace():
        raise InputFileError(f"{name} is empty; expected a Motive CSV export")
    if b"\x00" in raw[:4096]:
        raise InputFileError(f"{name} is a binary file, not a Motive CSV export")

    header = _parse_header(raw, name)
    meta = header.metadata
    scale, length_units = _length_scale(meta, fallback_scale, units, name)
    table = header.columns

    assets = _Assets.of(table)
    try:
        rigid_body, marker, kind = _choose(assets, rigid_body, marker, name)
    except InputFileError as refusal:
        if rigid_body or marker or assets.rigid_bodies or assets.bones or not assets.markers:
            raise
        # Only markers: say which of them moved, so that the pen's is easy to name.
        raise InputFileError(
            f"{refusal}. {_movement_ranking(raw, header, table, assets, scale, name)}"
        ) from None
    label = rigid_body or marker
    assert label is not None  # _choose names the one it chose
    cols = _columns_of(table, (kind,), label, name)
    rotation_type = None
    if rigid_body is not None:
        rotation_type = _rotation_type(meta, cols, rigid_body, name)
    what = f"{_KIND_NAMES[kind]} {rigid_body or marker!r}"
    position_cols = [cols.get(("Position", axis)) for axis in "XYZ"]
    missing = [f"Position {a}" for a, c in zip("XYZ", position_cols, strict=True) if c is None]
    if missing:
        raise InputFileError(
            f"{name} has no {', '.join(missing)} column for {what}, which Motive always writes "
            "(was the file edited?); export the take again"
        )
    rotation_cols: list[int] = []
    if rotation_type is not None:
        axes = "XYZW" if rotation_type == "Quaternion" else "XYZ"
        rotation_cols = [cols[("Rotation", a)] for a in axes]
    # The error column has no axis label (some exports may give it one).
    error_col = next((j for (part, _), j in cols.items() if part in _ERROR_COMPONENTS), None)

    present = [c for c in position_cols if c is not None]  # all three (checked above)
    wanted = [1, *present, *rotation_cols] + ([error_col] if error_col is not None else [])
    data = _parse_body(raw, header.body_start, header.body_line, wanted, table, name)
    n = len(data)
    expected = _int_or_none(meta.get("Total Exported Frames"))
    if expected is not None and n < expected:
        raise InputFileError(
            f"{name} is truncated: its header promises {expected} frames but it holds {n}; copy "
            "or export the take again (if you shortened the file on purpose, remove 'Total "
            "Exported Frames' from its first row)"
        )
    if n < 2:
        raise InputFileError(f"{name} has {n} data rows; a trace needs at least two")

    t = data[:, 0]
    if not np.all(np.isfinite(t)):
        line = header.body_line + int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputFileError(f"{name} line {line} has no time; every row needs its {table.axes[1]}")
    steps = np.diff(t)
    if np.any(steps <= 0):
        line = header.body_line + 1 + int(np.flatnonzero(steps <= 0)[0])
        raise InputFileError(
            f"{name}: the times in column {table.axes[1]!r} do not increase (line {line}); export "
            "the take again, or sort the rows by time and remove repeated ones"
        )

    position = data[:, 1:4] * scale
    tracked = np.isfinite(position).all(axis=1)
    orientation = None
    if rotation_type is not None:
        rot = data[:, 4 : 4 + len(rotation_cols)]
        tracked &= np.isfinite(rot).all(axis=1)
        orientation = np.full((n, 4), np.nan)
        orientation[tracked] = _to_quaternions(
            rot[tracked], rotation_type, np.flatnonzero(tracked), header.body_line, name
        )
    position[~tracked] = np.nan
    error_m = None
    valid = np.array(tracked, dtype=bool)
    if error_col is not None:
        error_m = np.where(tracked, data[:, -1] * scale, np.nan)
        if max_marker_error_m is not None:
            valid &= ~(error_m > max_marker_error_m)

    rate = _rate(meta, t)
    batch = SampleBatch(t_s=t, position_m=position, orientation_xyzw=orientation, valid=valid)
    return MotiveTrace(
        batch=batch,
        rate_hz=rate,
        length_units=length_units,
        rotation_type=rotation_type,
        take_name=meta.get("Take Name", ""),
        rigid_body=rigid_body,
        marker=marker,
        available=tuple(assets.rigid_bodies),
        available_markers=tuple(assets.markers),
        mean_marker_error_m=error_m,
        metadata=dict(meta),
    )


@dataclass(frozen=True)
class _Columns:
    """The header rows, one entry per column (Frame and Time included)."""

    types: list[str]
    names: list[str]
    components: list[str]
    axes: list[str]


@dataclass(frozen=True)
class _Header:
    metadata: dict[str, str]
    columns: _Columns
    body_start: int  # byte offset of the first data row
    body_line: int  # its line number (1-based)


def _read_bytes(source: str | Path | bytes, name: str) -> bytes:
    if isinstance(source, bytes):
        return source
    try:
        return Path(source).read_bytes()
    except FileNotFoundError:
        raise InputFileError(f"{name} does not exist") from None
    except IsADirectoryError:
        raise InputFileError(f"{name} is a directory, not a CSV file") from None
    except OSError as exc:
        raise InputFileError(f"cannot read {name}: {exc.strerror}") from None


def _decode(line: bytes) -> str:
    # Take names and notes may be in the Windows code page rather than UTF-8.
    try:
        return line.decode("utf-8-sig")
    except UnicodeDecodeError:
        return line.decode("cp1252", errors="replace")


def _cells(line: bytes) -> list[str]:
    rows = csv_rows(io.StringIO(_decode(line).rstrip("\r\n")), "a Motive export's header line")
    return rows[0] if rows else []


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _parse_header(raw: bytes, name: str) -> _Header:
    lines = _header_lines(raw)
    first_row = _cells(lines[0])
    label = first_row[0].strip() if first_row else ""
    if label != "Format Version":
        raise _not_motive(first_row, lines, name)
    metadata = {
        first_row[i].strip(): first_row[i + 1].strip() for i in range(0, len(first_row) - 1, 2)
    }
    metadata.pop("", None)  # the padding of a spreadsheet's re-save
    rows = [_cells(line) for line in lines[1:]]
    axis_index = next(
        (i for i, row in enumerate(rows) if row and row[0].strip().lower() == "frame"), None
    )
    if axis_index is None:
        raise InputFileError(
            f"{name} has no 'Frame,Time (Seconds),...' row after its first row; the column header "
            f"is incomplete or missing: {_HEADERLESS_HINT}"
        )
    axis_row = rows[axis_index]
    if len(axis_row) < 2 or not axis_row[1].strip().lower().startswith("time"):
        raise InputFileError(
            f"{name}: the second column should be 'Time (Seconds)', not "
            f"{(axis_row[1][:40] if len(axis_row) > 1 else '')!r}; export the take again"
        )
    if not any(cell.strip() for cell in axis_row[2:]):
        raise InputFileError(
            f"{name} holds no rigid body or marker: its only columns are Frame and Time, so the "
            "take exported no assets; check 'Rigid Bodies' (or 'Markers') in Motive's CSV export "
            "options, with the pen's rigid body defined in the take, and export again"
        )
    width = len(axis_row)

    def padded(row: list[str]) -> list[str]:
        cells = [cell.strip() for cell in row[:width]]
        return cells + [""] * (width - len(cells))

    types, names, components = _asset_rows(rows[:axis_index], name)
    columns = _Columns(
        types=padded(types),
        names=padded(names),
        components=padded(components),
        axes=padded(axis_row),
    )
    body_start = sum(len(line) for line in lines[: axis_index + 2])
    return _Header(metadata, columns, body_start, body_line=axis_index + 3)


def _header_lines(raw: bytes) -> list[bytes]:
    """The lines up to the ``Frame,Time`` row (or as many as a header may have)."""
    pos = 0
    lines: list[bytes] = []
    # Only the header is split here; the body is parsed in bulk.
    while pos < len(raw) and len(lines) < _MAX_HEADER_ROWS + 2:
        end = raw.find(b"\n", pos)
        end = len(raw) if end < 0 else end + 1
        lines.append(raw[pos:end])
        pos = end
        if len(lines) > 1:
            cells = _cells(lines[-1])
            if cells and cells[0].strip().lower() == "frame":
                break
    return lines


def _not_motive(first_row: list[str], lines: list[bytes], name: str) -> InputFileError:
    """Why a file whose first row is not Motive's metadata row is refused."""
    label = first_row[0].strip() if first_row else ""
    if label.lower() in _LEGACY_FIRST_CELLS:
        return _legacy(lines, name)
    if label and _is_number(label):
        return InputFileError(f"{name} has no header (its first row is data); {_HEADERLESS_HINT}")
    second = first_row[1].strip() if len(first_row) > 1 else ""
    if not label and second in ("Type", "Name", "ID"):
        return InputFileError(
            f"{name} lacks the metadata row (Format Version, Length Units, Rotation Type) "
            f"above its {second!r} row, so its units are unknown; {_HEADERLESS_HINT}"
        )
    return InputFileError(
        f"{name} is not a Motive CSV export: its first row should start with 'Format "
        f"Version', not {label[:40]!r}"
    )


def _legacy(lines: list[bytes], name: str) -> InputFileError:
    """The refusal of the legacy OptiTrack CSV (Tracking Tools, early Motive)."""
    version = next(
        (
            cells[2].strip()
            for cells in map(_cells, lines)
            if len(cells) > 2 and [c.strip().lower() for c in cells[:2]] == ["info", "version"]
        ),
        None,
    )
    what = f"format {version[:10]}" if version else "'comment', 'info' and 'frame' rows"
    # Each frame row holds the bodies and markers seen in that frame, so columns shift from row to
    # row, and nothing in the file says whether positions are in metres or millimetres.
    return InputFileError(
        f"{name} is a legacy OptiTrack CSV (Tracking Tools or early Motive, {what}), which is not "
        "read: its rows change layout with what was seen in each frame and it does not state its "
        "length unit; export the take from Motive as CSV with 'Header information' checked, or "
        "convert it to the canonical t,x,y,z,qx,qy,qz,qw CSV"
    )


def _asset_rows(rows: list[list[str]], name: str) -> tuple[list[str], list[str], list[str]]:
    """The Type, Name and component rows of the header (between the metadata and Frame rows).

    Motive 2+ labels the Type and Name rows in their second cell; Motive 1.x leaves both first
    cells empty, so its rows are told by their order (Type, Name, ID, components) and the Type row
    by its content. The component row is the unlabelled row just above the Frame row in both.
    """
    rows = [row for row in rows if any(cell.strip() for cell in row)]
    labelled = {}
    unlabelled = []
    for row in rows:
        first = row[0].strip()
        key = row[1].strip() if len(row) > 1 else ""
        if first == "" and key == "":
            unlabelled.append(row)
        elif first == "":
            labelled[key] = row
    components = unlabelled[-1] if unlabelled else None
    if "Type" not in labelled and len(unlabelled) >= 3:
        types = {cell.strip() for cell in unlabelled[0][2:]} - {""}
        if types and types <= _ASSET_TYPES:
            labelled.setdefault("Type", unlabelled[0])
            labelled.setdefault("Name", unlabelled[1])
    missing = [r for r in ("Type", "Name") if r not in labelled]
    if components is None:
        missing.append("the Rotation/Position row")
    if missing or components is None:
        raise InputFileError(
            f"{name} lacks the header rows {', '.join(missing)}; {_HEADERLESS_HINT}"
        )
    return labelled["Type"], labelled["Name"], components


def _length_scale(
    meta: dict[str, str], fallback: float | None, units: str | None, name: str
) -> tuple[float, str]:
    declared = meta.get("Length Units", "")
    if declared:
        scale = MOTIVE_LENGTH_UNITS.get(declared.lower())
        if scale is None:
            raise InputFileError(
                f"{name} has an unknown length unit {declared!r}; export the take again in "
                f"{', '.join(u.capitalize() for u in MOTIVE_LENGTH_UNITS)}"
            )
        return scale, declared
    if fallback is None:
        # Both go missing together when a spreadsheet or a script rewrites the first row.
        also = (
            ""
            if meta.get("Rotation Type")
            else "; 'Rotation Type' is missing too, which is no matter for quaternions (their W "
            "column tells them) but is for Euler angles"
        )
        raise InputFileError(
            f"{name} does not say its length unit (no 'Length Units' in its first row); give the "
            f"unit the positions are in: {_UNITS_OPTION}{also}"
        )
    return fallback, str(units)


def _unique(names: Iterable[str]) -> list[str]:
    return list(dict.fromkeys(n for n in names if n))


#: How messages call each kind of column the trace can come from.
_KIND_NAMES = {
    "Rigid Body": "rigid body",
    "Bone": "bone",
    "Marker": "marker",
    "Rigid Body Marker": "marker",
    "Bone Marker": "marker",
}


@dataclass(frozen=True)
class _Assets:
    """The names of what the file holds, in column order."""

    rigid_bodies: list[str]
    bones: list[str]
    markers: list[str]  # physical, rigid body and bone markers
    kinds: dict[str, list[str]]  # marker name -> its column types

    @classmethod
    def of(cls, table: _Columns) -> _Assets:
        pairs = list(zip(table.types, table.names, strict=True))
        kinds: dict[str, list[str]] = {}
        for t, n in pairs:
            if n and t.endswith("Marker") and t not in kinds.setdefault(n, []):
                kinds[n].append(t)
        return cls(
            rigid_bodies=_unique(n for t, n in pairs if t == "Rigid Body"),
            bones=_unique(n for t, n in pairs if t == "Bone"),
            markers=list(kinds),
            kinds=kinds,
        )


def _choose(
    assets: _Assets, rigid_body: str | None, marker: str | None, name: str
) -> tuple[str | None, str | None, str]:
    """Which rigid body (or bone) or marker is the pen, and its column type."""
    if rigid_body is None and marker is None:
        if len(assets.rigid_bodies) == 1:
            rigid_body = assets.rigid_bodies[0]
        elif not assets.rigid_bodies and not assets.bones and len(assets.markers) == 1:
            marker = assets.markers[0]
        else:
            raise _which_one(assets, name)
    if rigid_body is not None:
        if rigid_body in assets.rigid_bodies:
            return rigid_body, None, "Rigid Body"
        if rigid_body in assets.bones:
            return rigid_body, None, "Bone"
        bones = f"; bones {name_excerpt(assets.bones)}" if assets.bones else ""
        raise InputFileError(
            f"{name} has no rigid body named {rigid_body!r}; it has "
            f"{name_excerpt(assets.rigid_bodies)}{bones}"
        )
    if marker not in assets.kinds:
        raise InputFileError(
            f"{name} has no marker named {marker!r}; it has {name_excerpt(assets.markers)}"
        )
    # A physical marker is what the cameras saw; the others are where a solver expects one.
    kinds = assets.kinds[marker]
    kind = next(k for k in ("Marker", "Rigid Body Marker", "Bone Marker") if k in kinds)
    return None, marker, kind


#: Markers whose movement is measured for a refusal that lists them (the rest are not named).
_RANKED_MARKERS = 64


def _movement_ranking(
    raw: bytes, header: _Header, table: _Columns, assets: _Assets, scale: float, name: str
) -> str:
    """The markers ranked by how far they moved (the extent of what the cameras saw of each),
    for a file that holds only markers: a pen's tip sweeps the path, the workpiece's markers
    and stray reflections barely move."""
    moved = []
    for label in assets.markers[:_RANKED_MARKERS]:
        kinds = assets.kinds[label]
        kind = next(k for k in ("Marker", "Rigid Body Marker", "Bone Marker") if k in kinds)
        cols = _columns_of(table, (kind,), label, name)
        found = [cols.get(("Position", axis)) for axis in "XYZ"]
        position_cols = [c for c in found if c is not None]
        if len(position_cols) < 3:
            continue
        data = _parse_body(raw, header.body_start, header.body_line, position_cols, table, name)
        seen = np.isfinite(data).all(axis=1)
        if not seen.any():
            moved.append((0.0, 0.0, label))
            continue
        extent_mm = float(np.linalg.norm(np.ptp(data[seen], axis=0))) * scale * 1e3
        moved.append((extent_mm, float(seen.mean()), label))
    moved.sort(reverse=True)
    listed = ", ".join(
        f"{label} {extent:.0f} mm (seen in {share * 100:.0f} % of frames)"
        for extent, share, label in moved[:5]
    )
    still = [label for extent, _, label in moved if extent < 5.0]
    text = f"The markers that moved most: {listed}"
    if still:
        text += f"; {len(still)} moved less than 5 mm (not a pen tracing a path)"
    return text + "."


def _which_one(assets: _Assets, name: str) -> InputFileError:
    """The refusal of a file whose pen cannot be told without a name."""
    if assets.rigid_bodies:
        return InputFileError(
            f"{name} has several rigid bodies ({name_excerpt(assets.rigid_bodies, quote=False)}); "
            "say which one traced the path (rigid_body=... or --rigid-body)"
        )
    if assets.bones:
        skeletons = _unique(bone.split(":")[0] for bone in assets.bones if ":" in bone)
        held = f" ({name_excerpt(skeletons, quote=False)})" if skeletons else ""
        return InputFileError(
            f"{name} holds a skeleton{held} and no rigid body; name the bone that traced the path "
            "(rigid_body=... or --rigid-body) or one marker (marker=... or --marker): bones "
            f"{name_excerpt(assets.bones)}; markers {name_excerpt(assets.markers)}"
        )
    listed = f" ({name_excerpt(assets.markers, quote=False)})" if assets.markers else ""
    return InputFileError(
        f"{name} has no rigid body and {len(assets.markers)} markers{listed}; export the pen's "
        "rigid body (CSV option 'Rigid Bodies') or name the pen-tip marker (marker=... or "
        "--marker)"
    )


def _columns_of(
    table: _Columns, kinds: tuple[str, ...], label: str, name: str
) -> dict[tuple[str, str], int]:
    found: dict[tuple[str, str], int] = {}
    for j in range(2, len(table.types)):
        if table.types[j] in kinds and table.names[j] == label:
            key = (table.components[j], table.axes[j].upper())
            if key in found:
                raise InputFileError(
                    f"{name} has two '{key[0]} {key[1]}' columns for {label!r} (columns "
                    f"{found[key] + 1} and {j + 1}); give each rigid body and marker its own name "
                    "in Motive and export again"
                )
            found[key] = j
    return found


def _rotation_type(
    meta: dict[str, str], cols: dict[tuple[str, str], int], body: str, name: str
) -> str | None:
    present = [axis for axis in "XYZW" if ("Rotation", axis) in cols]
    if not present:
        return None  # positions only: exported without rotations
    declared = meta.get("Rotation Type", "").strip()
    if not declared:
        # Motive writes a W column for quaternions only: four components need no declaration.
        if present == list("XYZW"):
            return "Quaternion"
        raise InputFileError(
            f"{name} does not say its rotation type (no 'Rotation Type' in its first row), and "
            f"the rotation columns of {body!r} ({', '.join(present)}, no W) are Euler angles of an "
            "unknown order; no option supplies it: export the take again with its header, or with "
            "the rotation type Quaternion"
        )
    if declared.lower() == "quaternion":
        needed = "XYZW"
        declared = "Quaternion"
    elif declared.upper() in EULER_ORDERS:
        needed = "XYZ"
        declared = declared.upper()
    else:
        raise InputFileError(
            f"{name} has an unknown rotation type {declared!r}; export with Quaternion or one of "
            f"the Euler orders {', '.join(EULER_ORDERS)}"
        )
    lacking = [a for a in needed if a not in present]
    if lacking:
        raise InputFileError(
            f"{name} has no 'Rotation {', '.join(lacking)}' column for rigid body {body!r} "
            f"although its rotation type is {declared}; export the take again"
        )
    return declared


def _parse_body(
    raw: bytes, start: int, first_line: int, wanted: list[int], table: _Columns, name: str
) -> np.ndarray:
    """The ``wanted`` columns of every data row, as floats with NaN for empty cells."""
    body = raw[start:]
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        text = body.decode("latin-1")  # only to report the offending cell
    lines = text.splitlines()
    # A spreadsheet's re-save writes the blank rows at the end as rows of commas.
    while lines and not lines[-1].strip(" ,\t"):
        lines.pop()
    n = len(lines)
    if n == 0:
        return np.empty((0, len(wanted)))
    counts = np.fromiter(map(methodcaller("count", ","), lines), dtype=np.int64, count=n)
    width = int(counts[0]) + 1
    ragged = np.flatnonzero(counts != counts[0])
    if len(ragged):
        row = int(ragged[0])
        cells = int(counts[row]) + 1
        if row == n - 1 and cells < width:
            raise InputFileError(
                f"{name} is truncated: its last row (line {first_line + row}) has {cells} of "
                f"{width} cells; copy or export the take again"
            )
        raise InputFileError(
            f"{name} line {first_line + row} has {cells} cells where line {first_line} has "
            f"{width}; the file was edited or damaged, export the take again"
        )
    needed = max(wanted) + 1
    if width < needed:
        raise InputFileError(
            f"{name}: its rows have {width} cells but the header names column {needed} "
            f"({_column_label(table, needed - 1)}); the file is damaged, export the take again"
        )
    pick = itemgetter(*wanted)
    split = methodcaller("split", ",", needed)  # cells past the last wanted column stay unsplit
    rows = list(map(pick, map(split, lines)))
    if not body.translate(None, _PLAIN_NUMBER_BYTES):
        # Digits, dots and minus signs only: float() accepts every cell or raises (then the slow
        # path below finds which), and an empty cell is the only way to get NaN.
        try:
            flat = np.fromiter(
                map(float, [cell or "nan" for row in rows for cell in row]),
                dtype=np.float64,
                count=n * len(wanted),
            )
            return flat.reshape(n, len(wanted))
        except ValueError:
            pass
    return _parse_cells(rows, wanted, table, first_line, name)


def _parse_cells(
    rows: list[tuple[str, ...]], wanted: list[int], table: _Columns, first_line: int, name: str
) -> np.ndarray:
    out = np.empty((len(rows), len(wanted)))
    for i, row in enumerate(rows):
        for j, cell in enumerate(row):
            text = cell.strip()
            if not text:
                out[i, j] = math.nan
                continue
            try:
                value = float(text)
            except ValueError:
                raise InputFileError(
                    f"{name} line {first_line + i}, column {_column_label(table, wanted[j])}: "
                    f"{cell[:40]!r} is not a number; correct or empty that cell, or export the "
                    "take again"
                ) from None
            if not math.isfinite(value):
                raise InputFileError(
                    f"{name} line {first_line + i}, column {_column_label(table, wanted[j])} "
                    f"holds {cell!r}: NaN or infinite values are not Motive's (it leaves lost "
                    "frames empty); empty those cells or export the take again"
                )
            out[i, j] = value
    return out


def _column_label(table: _Columns, j: int) -> str:
    if j == 1:
        return table.axes[1]
    parts = [table.names[j], table.components[j], table.axes[j]] if j < len(table.names) else []
    return f"{j + 1} ({' '.join(p for p in parts if p)})" if parts else str(j + 1)


def _to_quaternions(
    rot: np.ndarray, rotation_type: str, rows: np.ndarray, first_line: int, name: str
) -> np.ndarray:
    if rotation_type == "Quaternion":
        norm = np.linalg.norm(rot, axis=1)
        if np.any(norm < 1e-9):
            line = first_line + int(rows[np.flatnonzero(norm < 1e-9)[0]])
            raise InputFileError(f"{name} line {line} has a zero quaternion")
        # Motive writes six decimals: renormalise what the rounding took away.
        unit: np.ndarray = rot / norm[:, None]
        return unit
    # Euler angles are written under their axis names; compose them in the declared order.
    angles = rot[:, ["XYZ".index(axis) for axis in rotation_type]]
    if len(angles) == 0:
        return np.empty((0, 4))
    quaternions: np.ndarray = Rotation.from_euler(rotation_type, angles, degrees=True).as_quat(
        scalar_first=False
    )
    return quaternions


def _int_or_none(text: str | None) -> int | None:
    try:
        return int(text) if text else None
    except ValueError:
        return None


def _rate(meta: dict[str, str], t: np.ndarray) -> float:
    for key in ("Export Frame Rate", "Capture Frame Rate"):
        try:
            rate = float(meta.get(key, ""))
        except ValueError:
            continue
        if math.isfinite(rate) and rate > 0:
            return rate
    return float(1.0 / np.median(np.diff(t)))
