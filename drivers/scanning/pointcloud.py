"""Point-cloud scan files (PLY, PCD, XYZ and relatives), read with Open3D.

Open3D's readers fail silently: a missing or corrupt file gives an empty cloud and a warning on
the console. Every read here is checked and turned into an :class:`InputFileError` that says
what is wrong. Uploads arrive as bytes and are written to a temporary file first, since Open3D
reads only XYZ text from memory.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from drivers.errors import InputFileError, UnknownFormatError
from drivers.units import metres_per
from recon.types import Scan

#: File suffix -> Open3D format name.
POINT_CLOUD_FORMATS: dict[str, str] = {
    ".ply": "ply",
    ".pcd": "pcd",
    ".xyz": "xyz",
    ".xyzn": "xyzn",
    ".xyzrgb": "xyzrgb",
    ".pts": "pts",
}


@dataclass(frozen=True)
class ScanFile:
    """A scan read from a file.

    Attributes
    ----------
    scan : Scan
        In metres.
    format : str
    n_dropped : int
        Points without finite coordinates (organised clouds mark holes with NaN), left out.
    """

    scan: Scan
    format: str
    n_dropped: int


def format_for(name: str, explicit: str | None = None) -> str:
    """The point-cloud format of a file, from ``explicit`` or the file's suffix.

    Raises
    ------
    UnknownFormatError
        No such format, or a suffix that names none.
    """
    known = sorted(set(POINT_CLOUD_FORMATS.values()))
    if explicit is not None:
        fmt = explicit.lower().lstrip(".")
        if fmt not in known:
            raise UnknownFormatError(
                f"unknown scan format {explicit!r}; use one of {', '.join(known)}"
            )
        return fmt
    suffix = Path(name).suffix.lower()
    if suffix not in POINT_CLOUD_FORMATS:
        raise UnknownFormatError(
            f"cannot tell the scan format of {name!r} from its suffix; name the file with one of "
            f"{', '.join(sorted(POINT_CLOUD_FORMATS))} or give the format explicitly"
        )
    return POINT_CLOUD_FORMATS[suffix]


def read_scan(
    source: str | Path | bytes,
    *,
    units: str = "m",
    fmt: str | None = None,
    name: str | None = None,
) -> ScanFile:
    """Read a point-cloud scan.

    Parameters
    ----------
    source : path or bytes
        The file, or its content (an upload; then ``name`` or ``fmt`` gives the format).
    units : {"m", "mm"}
    fmt : str, optional
        Format name (see :data:`POINT_CLOUD_FORMATS`); default from the suffix.
    name : str, optional
        File name of an upload, for its suffix and for messages.

    Returns
    -------
    ScanFile

    Raises
    ------
    InputFileError
        Missing, unreadable or empty file, or one with no finite point.
    UnknownFormatError
    ValueError
        An unknown unit.
    """
    scale = metres_per(units)
    label = name or ("upload" if isinstance(source, bytes) else str(source))
    fmt = format_for(name or ("" if isinstance(source, bytes) else str(source)), fmt)
    if isinstance(source, bytes):
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"scan.{fmt}"
            path.write_bytes(source)
            cloud = _read(path, fmt, label)
    else:
        path = Path(source)
        if not path.is_file():
            raise InputFileError(f"{label} does not exist or is not a file")
        cloud = _read(path, fmt, label)
    points = np.asarray(cloud.points, dtype=np.float64)
    if len(points) == 0:
        raise InputFileError(
            f"{label} holds no points as a {fmt.upper()} file: it is empty, corrupt or not a "
            f"{fmt.upper()} point cloud"
        )
    normals = np.asarray(cloud.normals, dtype=np.float64) if cloud.has_normals() else None
    finite = np.isfinite(points).all(axis=1)
    if normals is not None:
        finite &= np.isfinite(normals).all(axis=1)
    if not np.any(finite):
        raise InputFileError(f"{label} has no point with finite coordinates")
    scan = Scan(
        points_m=points[finite] * scale,
        normals=None if normals is None else normals[finite],
    )
    return ScanFile(scan=scan, format=fmt, n_dropped=int(np.count_nonzero(~finite)))


def write_scan(path: Path, scan: Scan) -> None:
    """Write a scan as a point cloud in metres; Open3D picks the format from the suffix."""
    format_for(str(path))  # refuse suffixes we could not read back
    # Vector3dVector needs writeable memory; Scan's arrays are read-only.
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(scan.points_m)))
    if scan.normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.array(scan.normals))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        ok = o3d.io.write_point_cloud(str(path), cloud)
    if not ok:
        raise InputFileError(f"could not write {path}")


def _check_signature(path: Path, fmt: str, label: str) -> None:
    """Refuse files whose first bytes cannot start a ``fmt`` file.

    Open3D's native readers print their complaints straight to the process's stderr (PLY:
    "Wrong magic number"), which Python cannot catch, so obvious mismatches are caught here.
    """
    with path.open("rb") as handle:
        head = handle.read(512)
    if not head.strip():
        raise InputFileError(f"{label} is empty")
    if fmt == "ply" and not head.startswith(b"ply"):
        raise InputFileError(f"{label} is not a PLY file (it does not start with 'ply')")
    if fmt == "pcd" and not any(key in head for key in (b"VERSION", b"FIELDS", b"# .PCD")):
        raise InputFileError(f"{label} is not a PCD file (no PCD header)")
    if fmt in ("xyz", "xyzn", "xyzrgb", "pts"):
        try:
            head.decode("ascii")
        except UnicodeDecodeError:
            raise InputFileError(
                f"{label} is not a text {fmt.upper()} file (it holds binary data)"
            ) from None


def _declared_count(path: Path, fmt: str) -> int | None:
    """Number of points a PLY or PCD header declares, or None for other formats."""
    if fmt not in ("ply", "pcd"):
        return None
    with path.open("rb") as handle:
        for raw in handle:
            line = raw.decode("ascii", errors="replace").strip()
            if fmt == "ply" and line.startswith("element vertex"):
                return int(line.split()[2])
            if fmt == "pcd" and line.startswith("POINTS"):
                return int(line.split()[1])
            if line in ("end_header",) or line.startswith("DATA"):
                return None
    return None


def _pcd_body_complete(path: Path, declared: int) -> bool:
    """Whether a PCD file's body holds the points its header declares.

    Open3D pads a short PCD body with made-up points without a word, so the body is measured:
    data lines for ASCII, bytes for binary (SIZE x COUNT per point). Compressed bodies are left
    to Open3D.
    """
    data = path.read_bytes()
    sizes, counts, offset, kind = [], [], None, None
    position = 0
    for raw in data.split(b"\n"):
        position += len(raw) + 1
        line = raw.decode("ascii", errors="replace").strip()
        if line.startswith("SIZE"):
            sizes = [int(v) for v in line.split()[1:]]
        elif line.startswith("COUNT"):
            counts = [int(v) for v in line.split()[1:]]
        elif line.startswith("DATA"):
            kind, offset = line.split()[1], position
            break
    if offset is None:
        return False
    body = data[offset:]
    if kind == "ascii":
        return sum(1 for row in body.split(b"\n") if row.strip()) >= declared
    if kind == "binary":
        point_size = sum(s * c for s, c in zip(sizes, counts or [1] * len(sizes), strict=False))
        return len(body) >= declared * point_size
    return True


_NATIVE_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def _captured_native_stderr():
    """Collect what native code writes to file descriptor 2 while the block runs.

    Yields a list that receives the captured text when the block ends. Held under a lock and
    only around one file read, so other threads lose at most a few milliseconds of stderr.
    """
    captured: list[str] = []
    with _NATIVE_STDERR_LOCK, tempfile.TemporaryFile() as sink:
        saved = os.dup(2)
        try:
            os.dup2(sink.fileno(), 2)
            yield captured
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            captured.append(sink.read().decode("utf-8", errors="replace").strip())


def _read(path: Path, fmt: str, label: str) -> o3d.geometry.PointCloud:
    _check_signature(path, fmt, label)
    try:
        declared = _declared_count(path, fmt)
    except (ValueError, IndexError):
        raise InputFileError(f"{label} has a malformed {fmt.upper()} header") from None
    # Open3D reports failures as console messages only; capture them for the error message and
    # judge the result instead.
    with (
        _captured_native_stderr() as native,
        o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error),
    ):
        try:
            cloud = o3d.io.read_point_cloud(
                str(path), format=fmt, remove_nan_points=False, remove_infinite_points=False
            )
        except RuntimeError as exc:  # raised by some readers on malformed headers
            raise InputFileError(f"{label} is not a readable {fmt.upper()} file: {exc}") from None
    detail = " ".join(native[0].split()) if native and native[0] else ""
    if declared is not None and (
        len(cloud.points) < declared or (fmt == "pcd" and not _pcd_body_complete(path, declared))
    ):
        raise InputFileError(
            f"{label} is truncated or corrupt: it holds fewer points than the {declared} its "
            "header declares; export the scan again" + (f" ({detail})" if detail else "")
        )
    if detail:
        # At Error verbosity Open3D and its native readers only write when reading failed;
        # what they returned may be padded with made-up points (seen with a truncated PLY).
        raise InputFileError(f"{label} could not be read as {fmt.upper()}: {detail}")
    return cloud
