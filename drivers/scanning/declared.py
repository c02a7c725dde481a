"""What a point-cloud file's header declares, bounded by the bytes the file holds.

Open3D sizes its arrays from the header before it reads the body: a 257-byte PLY whose header
declares 10^9 vertices had it allocate 24 GB (and 12 s, 2.4 GB for 10^8) before it found the body
short, and a PTS file declaring 10^8 points was read as 10^8 points at the origin (7.4 GB, 42 s).
So the header is read here first and every count it declares is checked against what the rest of
the file can hold, before Open3D sees the file:

* PLY, binary: each element's records have a fixed size (a list property at least its count),
  and the counts times those sizes must fit in the bytes after the header.
* PLY, ASCII: RPly reads tokens, not lines, so each record needs at least one character and one
  separator per value: ``count * 2 * values - 1`` bytes at least.
* PCD: ``POINTS`` and ``WIDTH x HEIGHT``, against ``SIZE x COUNT`` bytes per point (binary), the
  lines of an ASCII body (Open3D reads one point per line), or the sizes a compressed body
  states (which must agree with the bytes present and with LZF's largest expansion).
* PTS: the count on its first line, against the lines that follow.

Headers Open3D's native readers cannot take without crashing the process are refused too: PLY
header lines over :data:`MAX_PLY_LINE_BYTES`, PCD headers with some but not all of a field set
(:data:`PCD_FIELD_SETS`), field types or sizes PCD does not have, and PCD headers without
``WIDTH``, ``HEIGHT`` and ``POINTS`` (or where they disagree).

A count that does not fit is an :class:`~drivers.errors.InputFileError` that names the count and
what the file holds.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from drivers.errors import InputFileError, clipped

#: numpy type codes of each PLY property type (the PLY format's names and their sized aliases);
#: byte order comes from the header's format.
PLY_NUMPY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
#: Bytes of each PLY property type.
PLY_TYPE_BYTES = {name: int(code[1]) for name, code in PLY_NUMPY_TYPES.items()}
PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
#: Longest header read: real headers are a few hundred bytes; comments may make them longer, but
#: a file with no end of header within this much is not a point cloud.
MAX_HEADER_BYTES = 1 << 20
#: Most bytes an LZF stream (PCD's binary_compressed) expands one byte to: its longest back
#: reference is 3 bytes long and copies 264 bytes.
LZF_MAX_EXPANSION = 88
#: Longest PLY header line Open3D's reader (RPly) takes: it keeps a line in a 1024-byte buffer
#: and aborts the process on a longer comment or obj_info line (seen: a 2000-byte comment).
MAX_PLY_LINE_BYTES = 1000
#: Longest word of a PLY header (RPly's word buffer is 256 bytes).
MAX_PLY_WORD_BYTES = 255
#: PCD field types and the sizes each may have (bytes).
PCD_TYPE_SIZES = {"F": (4, 8), "I": (1, 2, 4, 8), "U": (1, 2, 4, 8)}
#: Fields that come as a set: Open3D reads normals when it finds normal_x and then reads the
#: other two without checking they exist (a PCD with normal_x alone crashed it).
PCD_FIELD_SETS = (("x", "y", "z"), ("normal_x", "normal_y", "normal_z"))
#: Text needs one character and one separator per value at least.
_MIN_TEXT_BYTES_PER_VALUE = 2


def check_declared_counts(path: Path, fmt: str, label: str) -> int | None:
    """Refuse a header that declares more than the file holds.

    Parameters
    ----------
    path : Path
        The file (its signature already checked).
    fmt : str
        Its format name; only ``ply``, ``pcd`` and ``pts`` declare counts.
    label : str
        The file's name in messages.

    Returns
    -------
    int or None
        The number of points the header declares (PLY vertices, PCD ``POINTS``, the PTS count),
        or None for formats without one (or a PLY without a vertex element).

    Raises
    ------
    InputFileError
        A malformed header, or a count the rest of the file cannot hold (the message names
        both).
    """
    if fmt == "ply":
        return _check_ply(path, label)
    if fmt == "pcd":
        return _check_pcd(path, label)
    if fmt == "pts":
        return _check_pts(path, label)
    return None


def _header(
    path: Path,
    label: str,
    fmt: str,
    last: Callable[[str], bool],
    max_line_bytes: int | None = None,
) -> tuple[list[str], int]:
    """The header's lines (decoded, stripped) up to and including the one ``last`` accepts, and
    the offset of the body after it; a line longer than ``max_line_bytes`` as stored (blanks
    and line end included) is refused."""
    with path.open("rb") as handle:
        head = handle.read(MAX_HEADER_BYTES)
    lines: list[str] = []
    position = 0
    while True:
        end = head.find(b"\n", position)
        if end < 0:
            raise InputFileError(
                f"{label} has no complete {fmt.upper()} header (it ends before its last header "
                "line): the file is truncated or not a point cloud; export the scan again"
            )
        if max_line_bytes is not None and end - position > max_line_bytes:
            shown = head[position : position + 40].decode("ascii", errors="replace")
            raise InputFileError(
                f"{label} has a {fmt.upper()} header line of {end - position:,} bytes, longer "
                f"than the {max_line_bytes} the {fmt.upper()} reader takes (at {shown!r}...); "
                "shorten its comments and export the scan again"
            )
        line = head[position:end].decode("ascii", errors="replace").strip()
        position = end + 1
        lines.append(line)
        if last(line):
            return lines, position


def _malformed(label: str, fmt: str, line: str) -> InputFileError:
    return InputFileError(
        f"{label} has a malformed {fmt.upper()} header (at {clipped(line)!r}); export the scan "
        "again"
    )


def _count(text: str, label: str, fmt: str, line: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise _malformed(label, fmt, line) from None
    if value < 0:
        raise _malformed(label, fmt, line)
    return value


def _too_many(
    label: str, declared: str, count: int, body: int, room: int, each: str
) -> InputFileError:
    return InputFileError(
        f"{label}: its header declares {count:,} {declared}, but the {body:,} bytes after the "
        f"header hold at most {room:,} ({each}): the file is truncated or its header is wrong; "
        "export the scan again"
    )


# --------------------------------------------------------------------------- PLY


@dataclass
class PlyElement:
    """One element of a PLY header: its name, count and properties (name, type; a list
    property's type is ``list``)."""

    name: str
    count: int
    properties: list[tuple[str, str]] = field(default_factory=list)
    fixed_bytes: int = 0  # binary bytes of the scalar properties, plus the lists' counts
    values: int = 0  # values of a record at least (a list: its count)

    @property
    def has_lists(self) -> bool:
        """Whether a record's size depends on its data (a list property)."""
        return any(kind == "list" for _, kind in self.properties)


@dataclass
class PlyLayout:
    """A PLY header as parsed: the body's format and offset, and the elements in order."""

    format: str
    body_offset: int
    elements: list[PlyElement]

    @property
    def vertex(self) -> PlyElement | None:
        """The vertex element, if the header has one."""
        return next((e for e in self.elements if e.name == "vertex"), None)


def _check_ply(path: Path, label: str) -> int | None:
    vertex = ply_layout(path, label).vertex
    return None if vertex is None else vertex.count


def ply_layout(path: Path, label: str) -> PlyLayout:
    """Parse a PLY header, refusing one that is malformed or declares more than the file holds.

    Raises
    ------
    InputFileError
        As :func:`check_declared_counts`.
    """
    lines, offset = _header(
        path, label, "ply", lambda line: line == "end_header", max_line_bytes=MAX_PLY_LINE_BYTES
    )
    body = path.stat().st_size - offset
    fmt = None
    elements: list[PlyElement] = []
    for line in lines[1:-1]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if any(len(word) > MAX_PLY_WORD_BYTES for word in words):
            raise InputFileError(
                f"{label} has a name longer than {MAX_PLY_WORD_BYTES} characters in its PLY "
                f"header (at {line[:40]!r}...); export the scan again"
            )
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
            if fmt not in PLY_FORMATS:
                raise _malformed(label, "ply", line)
        elif words[0] == "element" and len(words) == 3:
            elements.append(PlyElement(words[1], _count(words[2], label, "ply", line)))
        elif words[0] == "property" and elements:
            element = elements[-1]
            if len(words) == 5 and words[1] == "list":
                if words[2] not in PLY_TYPE_BYTES or words[3] not in PLY_TYPE_BYTES:
                    raise _malformed(label, "ply", line)
                element.fixed_bytes += PLY_TYPE_BYTES[words[2]]  # an empty list: its count only
                element.properties.append((words[4], "list"))
            elif len(words) == 3 and words[1] in PLY_TYPE_BYTES:
                element.fixed_bytes += PLY_TYPE_BYTES[words[1]]
                element.properties.append((words[2], words[1]))
            else:
                raise _malformed(label, "ply", line)
            element.values += 1
        else:
            raise _malformed(label, "ply", line)
    if fmt is None:
        raise InputFileError(
            f"{label} has a malformed PLY header (no format line); export the scan again"
        )
    used = 0
    for element in elements:
        declared = "vertices" if element.name == "vertex" else f"{element.name!r} elements"
        left = max(body - used, 0)
        if fmt == "ascii":
            # At least one character and a separator per value; the last one needs no separator.
            each = _MIN_TEXT_BYTES_PER_VALUE * max(element.values, 1)
            room = (left + 1) // each
            how = f"at least {each} bytes each as text"
        else:
            each = max(element.fixed_bytes, 1)
            room = left // each
            how = f"{each} bytes each in {fmt}"
        if element.count > room:
            raise _too_many(label, declared, element.count, body, room, how)
        used += element.count * each
    return PlyLayout(format=fmt, body_offset=offset, elements=elements)


# --------------------------------------------------------------------------- PCD


def _check_pcd(path: Path, label: str) -> int:  # noqa: C901
    lines, offset = _header(path, label, "pcd", lambda line: line.upper().startswith("DATA"))
    body = path.stat().st_size - offset
    fields: dict[str, list[str]] = {}
    for line in lines:
        words = line.split()
        if words and not words[0].startswith("#"):
            fields[words[0].upper()] = words[1:]
    data = (fields.get("DATA") or [""])[0].lower()
    if data not in ("ascii", "binary", "binary_compressed"):
        raise _malformed(label, "pcd", lines[-1])

    def number(key: str) -> int | None:
        values = fields.get(key)
        if values is None:
            return None
        if len(values) != 1:
            raise _malformed(label, "pcd", f"{key} {' '.join(values)}")
        return _count(values[0], label, "pcd", f"{key} {values[0]}")

    names = fields.get("FIELDS") or []
    try:
        sizes = [int(v) for v in fields.get("SIZE", [])]
        counts = [int(v) for v in fields.get("COUNT", [])] or [1] * len(sizes)
    except ValueError:
        raise InputFileError(
            f"{label} has a malformed PCD header (SIZE or COUNT); export the scan again"
        ) from None
    if not names or len(sizes) != len(names) or len(counts) != len(names):
        raise InputFileError(
            f"{label} has a malformed PCD header: FIELDS, SIZE and COUNT must give one entry per "
            f"field (got {len(names)}, {len(sizes)} and {len(counts)}); export the scan again"
        )
    if any(size <= 0 for size in sizes) or any(count <= 0 for count in counts):
        raise InputFileError(
            f"{label} has a malformed PCD header (a SIZE or COUNT below 1); export the scan again"
        )
    _check_pcd_fields(names, sizes, fields.get("TYPE"), label)
    points = number("POINTS")
    width, height = number("WIDTH"), number("HEIGHT")
    absent = [key for key, value in (("WIDTH", width), ("HEIGHT", height), ("POINTS", points))
              if value is None]  # fmt: skip
    if absent or width is None or height is None or points is None:
        # Open3D reads such a header with sizes it never set (different points on every read).
        raise InputFileError(
            f"{label} has a PCD header without {' and '.join(absent)}; a PCD file states WIDTH, "
            "HEIGHT and POINTS: export the scan again"
        )
    declared = [  # (what, count) the header states
        ("points (POINTS)", points),
        (f"points (WIDTH x HEIGHT = {width:,} x {height:,})", width * height),
    ]
    point_bytes = sum(size * count for size, count in zip(sizes, counts, strict=True))
    if data == "binary":
        room, how = body // point_bytes, f"{point_bytes} bytes each"
    elif data == "ascii":
        room, how = _text_rows(path, offset), "one per line of text"
    else:
        room, how = _compressed_room(path, offset, body, point_bytes, label)
    for what, count in declared:
        if count > room:
            raise _too_many(label, what, count, body, room, how)
    if points != width * height:
        raise InputFileError(
            f"{label}: its PCD header declares POINTS {points:,} but WIDTH x HEIGHT = {width:,} x "
            f"{height:,}; the header is inconsistent: export the scan again"
        )
    return points


def _check_pcd_fields(
    names: list[str], sizes: list[int], types: list[str] | None, label: str
) -> None:
    """Field sets complete, x, y and z among them, and each field's TYPE and SIZE a PCD pair."""
    present = set(names)
    for field_set in PCD_FIELD_SETS:
        have = [name for name in field_set if name in present]
        if have and len(have) < len(field_set):
            missing = [name for name in field_set if name not in present]
            raise InputFileError(
                f"{label}: its PCD header has {', '.join(have)} but not {', '.join(missing)}; "
                "export the scan again with all of them or none"
            )
    if "x" not in present:
        raise InputFileError(
            f"{label}: its PCD header has no x, y and z fields (FIELDS {' '.join(names[:8])}); "
            "export the scan with point coordinates"
        )
    types = [t.upper() for t in (types or [])]
    if len(types) != len(names):
        raise InputFileError(
            f"{label} has a malformed PCD header: TYPE must give one entry per field (got "
            f"{len(types)} for {len(names)} fields); export the scan again"
        )
    for name, kind, size in zip(names, types, sizes, strict=True):
        if size not in PCD_TYPE_SIZES.get(kind, ()):
            raise InputFileError(
                f"{label}: field {name[:40]!r} has TYPE {kind[:10]!r} and SIZE {size}, which PCD "
                "does not have (F: 4 or 8 bytes; I and U: 1, 2, 4 or 8); export the scan again"
            )


def _compressed_room(
    path: Path, offset: int, body: int, point_bytes: int, label: str
) -> tuple[int, str]:
    """Points a binary_compressed body can hold: its stated uncompressed size, checked."""
    with path.open("rb") as handle:
        handle.seek(offset)
        sizes = handle.read(8)
    if len(sizes) < 8:
        raise InputFileError(
            f"{label} is truncated: its binary_compressed body lacks the sizes it starts with; "
            "export the scan again"
        )
    compressed, uncompressed = struct.unpack("<II", sizes)
    if compressed > body - 8:
        raise InputFileError(
            f"{label}: its compressed body declares {compressed:,} bytes, but {body - 8:,} "
            "follow: the file is truncated; export the scan again"
        )
    if uncompressed > compressed * LZF_MAX_EXPANSION:
        raise InputFileError(
            f"{label}: its compressed body declares {uncompressed:,} bytes unpacked from "
            f"{compressed:,}, more than LZF compression can give ({LZF_MAX_EXPANSION} times): "
            "the header is wrong; export the scan again"
        )
    return uncompressed // point_bytes, f"{point_bytes} bytes each, {uncompressed:,} unpacked"


def _text_rows(path: Path, offset: int) -> int:
    """Non-empty lines after ``offset`` (read in blocks, not held)."""
    rows = 0
    with path.open("rb") as handle:
        handle.seek(offset)
        for line in handle:
            if line.strip():
                rows += 1
    return rows


# --------------------------------------------------------------------------- PTS


def _check_pts(path: Path, label: str) -> int | None:
    """The count on a PTS file's first line, against the lines that follow."""
    lines, offset = _header(path, label, "pts", lambda line: bool(line))
    words = lines[-1].split()
    if len(words) != 1:
        return None  # no count line: Open3D reads the lines as points
    count = _count(words[0], label, "pts", lines[-1])
    rows = _text_rows(path, offset)
    if count > rows:
        body = path.stat().st_size - offset
        raise _too_many(label, "points", count, body, rows, "one per line of text")
    return count
