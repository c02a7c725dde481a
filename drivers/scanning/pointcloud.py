"""Point-cloud scan files (PLY, PCD, XYZ and relatives), read with numpy or Open3D.

A binary PLY's vertices (what scanners write) are read straight into numpy after its header is
checked; every other file goes through Open3D, imported only then. Open3D's readers fail
silently: a missing or corrupt file gives an empty cloud and a warning on the console. Every read
here is checked and turned into an :class:`InputFileError` that says what is wrong; the counts a
header declares are checked against the file's size before anything allocates for them
(:mod:`drivers.scanning.declared`). Uploads arrive as bytes and are written to a temporary file
first, since Open3D reads only XYZ text from memory.

:func:`read_scan` here is the entry point the service and the CLI use: it dispatches to every
registered reader (:mod:`drivers.scanning.base`), point clouds being one kind among several.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

from drivers.errors import InputFileError, UnknownFormatError, clipped
from drivers.scanning import base
from drivers.scanning._native import captured_native_stderr, open3d_message, quiet_open3d
from drivers.scanning.base import ReaderOptions, ScanFile, ScanReader
from drivers.scanning.declared import (
    PLY_NUMPY_TYPES,
    PlyLayout,
    check_declared_counts,
    ply_layout,
)
from recon.inputs import Scan

__all__ = [
    "POINT_CLOUD_FORMATS",
    "PointCloudOptions",
    "PointCloudReader",
    "ScanFile",
    "format_for",
    "read_scan",
    "write_scan",
]

#: File suffix -> Open3D format name.
POINT_CLOUD_FORMATS: dict[str, str] = {
    ".ply": "ply",
    ".pcd": "pcd",
    ".xyz": "xyz",
    ".xyzn": "xyzn",
    ".xyzrgb": "xyzrgb",
    ".pts": "pts",
}

#: Bytes read to recognise a PCD file (its header may open with long comments).
SIGNATURE_BYTES = 1 << 16
#: Bytes of a text format (XYZ, PTS, ...) checked for binary data.
TEXT_CHECK_BYTES = 512

# Kept under its old name for callers of the module's private helper.
_captured_native_stderr = captured_native_stderr


class PointCloudOptions(ReaderOptions):
    """Options of the point-cloud reader (none yet besides its kind)."""

    kind: Literal["pointcloud"] = "pointcloud"


class PointCloudReader(ScanReader):
    """PLY, PCD, XYZ, XYZN, XYZRGB and PTS files: binary PLY vertices with numpy, the rest
    through Open3D; every read checked."""

    kind: ClassVar[str] = "pointcloud"
    options_class: ClassVar[type[ReaderOptions]] = PointCloudOptions

    def _read(self, path: Path, *, fmt: str, label: str, scale: float) -> ScanFile:
        points, normals = _read_points(path, fmt, label)
        if len(points) == 0:
            raise InputFileError(
                f"{label} holds no points as a {fmt.upper()} file: it is empty, corrupt or not "
                f"a {fmt.upper()} point cloud"
            )
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


def format_for(name: str, explicit: str | None = None) -> str:
    """The scan format of a file, from ``explicit`` or the file's suffix.

    Covers every registered reader (see :func:`drivers.scanning.base.format_for`).

    Raises
    ------
    UnknownFormatError
        No such format, or a suffix that names none.
    """
    return base.format_for(name, explicit)


def read_scan(
    source: str | Path | bytes,
    *,
    units: str = "m",
    fmt: str | None = None,
    name: str | None = None,
    options: ReaderOptions | dict[str, Any] | None = None,
    limits: dict[str, float] | None = None,
    limit_names: dict[str, str] | None = None,
) -> ScanFile:
    """Read a scan: a point cloud, an E57 file, RGB-D frames or a RealSense bag.

    Parameters
    ----------
    source : path or bytes
        The file (or a folder of RGB-D frames), or its content (an upload; then ``name`` or
        ``fmt`` gives the format).
    units : {"m", "mm"}
        Unit of point-cloud coordinates; E57, RGB-D and bag input fix their own (metres).
    fmt : str, optional
        Format name (see :data:`drivers.scanning.base.SCAN_READERS`); default from the suffix.
    name : str, optional
        File name of an upload, for its suffix and for messages.
    options : ReaderOptions or dict, optional
        Options of the format's reader (e.g. ``{"depth_trunc_m": 1.5}`` for RGB-D frames).
    limits : dict, optional
        Upper bounds for resource options (see :func:`drivers.scanning.base.make_reader`).
    limit_names : dict, optional
        The settings behind those bounds, named in messages.

    Returns
    -------
    ScanFile

    Raises
    ------
    InputFileError
        Missing, unreadable or empty file, one with no finite point, or a header that declares
        more points than the file holds.
    InputTooLargeError
        An input past a resource bound (see :func:`drivers.scanning.base.read_scan`).
    UnknownFormatError
    ValueError
        An unknown unit, or options that do not fit the reader.
    """
    return base.read_scan(
        source,
        units=units,
        fmt=fmt,
        name=name,
        options=options,
        limits=limits,
        limit_names=limit_names,
    )


def write_scan(path: Path, scan: Scan) -> None:
    """Write a scan as a point cloud in metres; Open3D picks the format from the suffix."""
    # Refuse suffixes we could not read back (and formats Open3D cannot write, like E57).
    if Path(path).suffix.lower() not in POINT_CLOUD_FORMATS:
        raise UnknownFormatError(
            f"cannot write a scan as {Path(path).name!r}; name the file with one of "
            f"{', '.join(sorted(POINT_CLOUD_FORMATS))}"
        )
    import open3d as o3d

    # Vector3dVector needs writeable memory; Scan's arrays are read-only.
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(scan.points_m)))
    if scan.normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.array(scan.normals))
    with quiet_open3d():
        ok = o3d.io.write_point_cloud(Path(path), cloud)
    if not ok:
        raise InputFileError(f"could not write {path}")


def _check_signature(path: Path, fmt: str, label: str) -> None:
    """Refuse files whose first bytes cannot start a ``fmt`` file.

    Open3D's native readers print their complaints straight to the process's stderr (PLY:
    "Wrong magic number"), which Python cannot catch, so obvious mismatches are caught here.
    """
    with path.open("rb") as handle:
        head = handle.read(SIGNATURE_BYTES if fmt == "pcd" else TEXT_CHECK_BYTES)
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


def _read_points(path: Path, fmt: str, label: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (M, 3) and normals (M, 3) or None, as stored (not yet checked for finiteness)."""
    _check_signature(path, fmt, label)
    if fmt == "ply":
        layout = ply_layout(path, label)
        _check_ply_coordinates(layout, label)
        direct = _binary_ply_vertices(path, layout, label)
        if direct is not None:
            return direct
        declared = None if layout.vertex is None else layout.vertex.count
    else:
        # Open3D sizes its arrays from the header: what it declares must fit in the file first.
        declared = check_declared_counts(path, fmt, label)
    cloud = _read_with_open3d(path, fmt, label, declared)
    points = np.asarray(cloud.points, dtype=np.float64)
    normals = np.asarray(cloud.normals, dtype=np.float64) if cloud.has_normals() else None
    return points, normals


def _check_ply_coordinates(layout: PlyLayout, label: str) -> None:
    """Refuse a PLY whose vertices have no x, y and z (Open3D reads such files as all zeros)."""
    vertex = layout.vertex
    if vertex is None or vertex.count == 0:
        return
    names = [name for name, _ in vertex.properties]
    if not {"x", "y", "z"} <= set(names):
        raise InputFileError(
            f"{label}'s vertices have no x, y and z coordinates (their properties: "
            f"{clipped(', '.join(names) or 'none')}); export the scan with point positions"
        )


def _binary_ply_vertices(
    path: Path, layout: PlyLayout, label: str
) -> tuple[np.ndarray, np.ndarray | None] | None:
    """The vertices of a binary PLY read straight into numpy, or None to leave it to Open3D.

    A binary PLY's vertex element is an array of fixed-size records at a known offset when no
    element before it (and not the element itself) has list properties, which is how scanners
    and meshing tools write them. Reading it with one ``numpy.fromfile`` takes 25 ms for 1M points
    where Open3D's reader takes 80 ms and Open3D's import 0.9 s;
    it also skips whatever elements follow (a mesh's faces). ASCII files and other layouts
    (lists before the vertices, a property named twice) go to Open3D.
    """
    vertex = layout.vertex
    if layout.format == "ascii" or vertex is None or vertex.has_lists:
        return None
    if vertex.count == 0:  # refused by the caller as holding no points
        return np.zeros((0, 3)), None
    names = [name for name, _ in vertex.properties]
    if len(set(names)) != len(names):
        return None
    offset = layout.body_offset
    for element in layout.elements:
        if element is vertex:
            break
        if element.has_lists:
            return None
        offset += element.count * element.fixed_bytes
    order = "<" if layout.format == "binary_little_endian" else ">"
    record = np.dtype([(name, order + PLY_NUMPY_TYPES[kind]) for name, kind in vertex.properties])
    data = np.fromfile(path, dtype=record, count=vertex.count, offset=offset)
    if len(data) < vertex.count:  # the header check makes this a file changed while read
        raise InputFileError(
            f"{label} is truncated: it holds fewer points than the {vertex.count} its header "
            "declares; export the scan again"
        )
    points = np.column_stack([data[axis].astype(np.float64) for axis in "xyz"])
    normals = None
    if {"nx", "ny", "nz"} <= set(names):
        normals = np.column_stack([data[axis].astype(np.float64) for axis in ("nx", "ny", "nz")])
    return points, normals


def _read_with_open3d(path: Path, fmt: str, label: str, declared: int | None) -> Any:
    """Read through Open3D (imported here: it takes 0.9 s), every failure an InputFileError."""
    import open3d as o3d

    # Open3D reports failures as console messages only; capture them for the error message and
    # judge the result instead.
    with (
        captured_native_stderr() as native,
        quiet_open3d(),
    ):
        try:
            cloud = o3d.io.read_point_cloud(
                Path(path), format=fmt, remove_nan_points=False, remove_infinite_points=False
            )
        except RuntimeError as exc:  # raised by some readers on malformed headers
            raise InputFileError(
                f"{label} is not a readable {fmt.upper()} file: {open3d_message(exc)}"
            ) from None
    detail = " ".join(native[0].split()) if native and native[0] else ""
    if declared is not None and len(cloud.points) < declared:
        raise InputFileError(
            f"{label} is truncated or corrupt: it holds fewer points than the {declared} its "
            "header declares; export the scan again" + (f" ({detail})" if detail else "")
        )
    if detail:
        # At Error verbosity Open3D and its native readers only write when reading failed;
        # what they returned may be padded with made-up points (seen with a truncated PLY).
        raise InputFileError(f"{label} could not be read as {fmt.upper()}: {detail}")
    return cloud
