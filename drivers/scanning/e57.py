"""E57 scan files (ASTM E2807), read with pye57.

An E57 file holds any number of scans, each in its own frame with a pose (a rigid transform into
the file's common frame). Every scan is read, transformed by its pose and appended, giving one
cloud in the file's frame. Coordinates are metres by the standard. Scans stored only in
spherical coordinates (range, azimuth, elevation) are converted with pye57's conversion; points
flagged invalid by the file (``cartesianInvalidState`` / ``sphericalInvalidState``) are left out
and counted.

pye57 sizes its arrays from each scan's declared record count before it reads a record: a 4 KB
file declaring 10^8 points made it allocate 3.3 GB (22 s) before failing. So the count is
checked first against the file's size, at the bits a record of the scan's prototype takes.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import pye57
from pye57 import libe57
from pye57.utils import convert_spherical_to_cartesian
from scipy.spatial.transform import Rotation

from drivers.errors import InputFileError
from drivers.scanning._native import captured_native_stderr
from drivers.scanning.base import ReaderOptions, ScanFile, ScanReader
from recon.arrays import FloatArray
from recon.inputs import Scan
from recon.transforms import apply_transform

#: Every E57 file starts with this signature (the standard's file header).
E57_SIGNATURE = b"ASTM-E57"
#: Bits of a float field by precision (E57 stores IEEE singles and doubles).
_FLOAT_BITS = {libe57.FloatPrecision.E57_SINGLE: 32, libe57.FloatPrecision.E57_DOUBLE: 64}

_CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
_SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")


class E57Options(ReaderOptions):
    """Options of the E57 reader (none yet besides its kind)."""

    kind: Literal["e57"] = "e57"


class E57Reader(ScanReader):
    """Every scan of an E57 file, posed into the file's frame and merged into one cloud."""

    kind: ClassVar[str] = "e57"
    options_class: ClassVar[type[ReaderOptions]] = E57Options
    fixed_units: ClassVar[bool] = True

    def _unit_note(self) -> str:
        return "E57 coordinates are metres by the ASTM E2807 standard"

    def _read(self, path: Path, *, fmt: str, label: str, scale: float) -> ScanFile:
        with path.open("rb") as handle:
            head = handle.read(len(E57_SIGNATURE))
        if not head:
            raise InputFileError(f"{label} is empty")
        if head != E57_SIGNATURE:
            raise InputFileError(
                f"{label} is not an E57 file (it does not start with {E57_SIGNATURE.decode()!r})"
            )
        clouds: list[FloatArray] = []
        notes: list[str] = []
        n_dropped = 0
        file_bytes = path.stat().st_size
        with _opened(path, label) as e57:
            n_scans = _call(e57, label, lambda f: f.scan_count)
            if n_scans == 0:
                raise InputFileError(f"{label} holds no scans (its data3D section is empty)")
            _check_record_counts(e57, n_scans, label, file_bytes)
            for index in range(n_scans):
                points, dropped = _read_scan(e57, index, label)
                n_dropped += dropped
                if len(points):
                    clouds.append(points)
        if not clouds:
            raise InputFileError(
                f"{label} holds no valid points in any of its {n_scans} scan(s); export it again"
            )
        if n_scans > 1:
            notes.append(f"merged {len(clouds)} of {n_scans} E57 scans, each moved by its pose")
        points = np.concatenate(clouds)
        return ScanFile(
            scan=Scan(points_m=points),
            format=fmt,
            n_dropped=n_dropped,
            notes=tuple(notes),
            dropped_because="flagged invalid by the scanner or without finite coordinates",
        )


class _opened:
    """pye57.E57 opened for reading, with libe57's failures turned into InputFileError."""

    def __init__(self, path: Path, label: str) -> None:
        self.path, self.label = path, label

    def __enter__(self) -> pye57.E57:
        # libe57 raises E57Exception and sometimes also writes to stderr; keep both from the user.
        with captured_native_stderr():
            try:
                self.e57 = pye57.E57(str(self.path), mode="r")
            except libe57.E57Exception as exc:
                raise InputFileError(
                    f"{self.label} is not a readable E57 file ({_first_line(exc)}); it may be "
                    "truncated or corrupt: export it again"
                ) from None
        return self.e57

    def __exit__(self, *exc_info: object) -> None:
        self.e57.close()


def _first_line(exc: BaseException) -> str:
    # libe57's messages carry a multi-line debug dump after the first line.
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def _call(e57: pye57.E57, label: str, func: Callable[..., Any]) -> Any:
    try:
        with captured_native_stderr():
            return func(e57)
    except libe57.E57Exception as exc:
        raise InputFileError(
            f"{label} is a corrupt E57 file ({_first_line(exc)}); export it again"
        ) from None


def _read_scan(e57: pye57.E57, index: int, label: str) -> tuple[FloatArray, int]:
    """Points of scan ``index`` in the file's frame (metres) and how many were left out."""
    header = _call(e57, label, lambda f: f.get_header(index))
    fields = header.point_fields
    total = int(header.point_count)
    if total == 0:
        return np.empty((0, 3)), 0
    if all(name in fields for name in _CARTESIAN):
        system = "cartesian"
    elif all(name in fields for name in _SPHERICAL):
        system = "spherical"
    else:
        raise InputFileError(
            f"scan {index} of {label} has neither cartesianX/Y/Z nor sphericalRange/Azimuth/"
            f"Elevation point fields (it has {', '.join(fields)}); it cannot be read as points"
        )
    # transform=False: pye57 would read the pose quaternion's children in file order, but the
    # standard names them (w, x, y, z) without fixing an order, so the pose is applied below.
    data = _call(
        e57, label, lambda f: f.read_scan(index, transform=False, ignore_missing_fields=True)
    )
    if system == "cartesian":
        xyz = np.column_stack([np.asarray(data[name], dtype=np.float64) for name in _CARTESIAN])
    else:
        rae = np.column_stack([np.asarray(data[name], dtype=np.float64) for name in _SPHERICAL])
        xyz = convert_spherical_to_cartesian(rae)
    n_invalid_state = total - len(xyz)  # pye57 drops points the file flags invalid
    finite = np.isfinite(xyz).all(axis=1)
    T = _pose(header, index, label)
    points = apply_transform(T, xyz[finite])
    return points, n_invalid_state + int(np.count_nonzero(~finite))


def record_bits(header: Any) -> int:
    """Bits one record of a scan's points takes at least, from its prototype.

    Floats take 32 or 64 bits; integers and scaled integers the bits of their range
    (``maximum - minimum``, 0 for a constant); strings may be empty.
    """
    prototype = libe57.StructureNode(header.points.prototype())
    bits = 0
    for i in range(prototype.childCount()):
        node = prototype.get(i)
        kind = node.type()
        if kind == libe57.NodeType.E57_FLOAT:
            bits += _FLOAT_BITS.get(libe57.FloatNode(node).precision(), 32)
        elif kind == libe57.NodeType.E57_SCALED_INTEGER:
            typed = libe57.ScaledIntegerNode(node)
            bits += (typed.maximum() - typed.minimum()).bit_length()
        elif kind == libe57.NodeType.E57_INTEGER:
            typed = libe57.IntegerNode(node)
            bits += (typed.maximum() - typed.minimum()).bit_length()
    return bits


def _check_record_counts(e57: pye57.E57, n_scans: int, label: str, file_bytes: int) -> None:
    """Refuse declared point counts that the whole file could not hold (all scans together),
    before pye57 allocates for any of them."""
    left_bits = file_bytes * 8
    for index in range(n_scans):
        header = _call(e57, label, lambda f, i=index: f.get_header(i))
        total = int(header.point_count)
        if total == 0:
            continue
        bits = _call_header(lambda h=header: record_bits(h), label)
        # A record of constant fields takes no bits; one bit each still bounds what pye57
        # allocates.
        per_record = max(bits, 1)
        room = left_bits // per_record
        if total > room:
            before = " (after the scans before it)" if index else ""
            raise InputFileError(
                f"scan {index} of {label} declares {total:,} points of {bits} bits each, but the "
                f"whole file is {file_bytes:,} bytes, room for at most {room:,}{before}: the "
                "file is truncated or its header is wrong; export it again"
            )
        left_bits -= total * per_record


def _call_header(func: Callable[..., Any], label: str) -> Any:
    try:
        with captured_native_stderr():
            return func()
    except libe57.E57Exception as exc:
        raise InputFileError(
            f"{label} has a corrupt point prototype ({_first_line(exc)}); export it again"
        ) from None


def _pose(header: Any, index: int, label: str) -> FloatArray:
    """The scan's pose as a 4x4 transform into the file's frame (identity if it has none)."""
    T = np.eye(4)
    node = header.node
    if not node.isDefined("pose"):
        return T
    pose = node["pose"]
    try:
        if pose.isDefined("rotation"):
            rot = pose["rotation"]
            wxyz = np.array([rot[key].value() for key in ("w", "x", "y", "z")], dtype=np.float64)
            norm = np.linalg.norm(wxyz)
            if not (np.all(np.isfinite(wxyz)) and norm > 1e-9):
                raise InputFileError(
                    f"scan {index} of {label} has an invalid pose rotation {wxyz.tolist()} "
                    "(w, x, y, z); fix the pose in the scanner software and export again"
                )
            # E57 stores the quaternion scalar first; SciPy takes it scalar last.
            T[:3, :3] = Rotation.from_quat(np.roll(wxyz / norm, -1), scalar_first=False).as_matrix()
        if pose.isDefined("translation"):
            trans = pose["translation"]
            t = np.array([trans[key].value() for key in ("x", "y", "z")], dtype=np.float64)
            if not np.all(np.isfinite(t)):
                raise InputFileError(
                    f"scan {index} of {label} has a pose translation with NaN or infinite values"
                )
            T[:3, 3] = t
    except libe57.E57Exception as exc:
        raise InputFileError(
            f"scan {index} of {label} has a malformed pose ({_first_line(exc)})"
        ) from None
    return T
