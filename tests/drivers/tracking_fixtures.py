"""Writers of tracker files with known content, for the reader tests, the benchmarks and the
service's tests.

:func:`write_motive_csv` writes what OptiTrack Motive's "CSV export" writes (format 1.23, the layout
of Motive 2.x and 3.x): the metadata row, a blank row, the Type / Name / ID rows, the row naming
Rotation / Position / Mean Marker Error / Marker Quality, the ``Frame,Time (Seconds),X,Y,Z,...``
row, then one row per frame with empty cells where a body or marker was lost. Each rigid body is
followed by its rigid body markers (the solved marker positions) and the file ends with the
physical markers, named ``<body>:Marker<k>`` as Motive names them. With ``format_version`` 1.21
or 1.22 it writes Motive 1.x's layout instead: the Type / Name / ID rows without their labels
(``,,Rigid Body,...``), ``Frame,Time,...``, and ``Error Per Marker`` for the rigid body's error.

:func:`write_c3d` writes a C3D file with ezc3d; a take longer than 65535 frames also declares its
length in ``POINT:LONG_FRAMES`` and ``TRIAL:ACTUAL_START_FIELD`` / ``ACTUAL_END_FIELD``, as Vicon
and the C3D user guide do, because the header's 16-bit frame numbers cannot.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

#: Length unit names of the Motive header, by the short name the writers take.
MOTIVE_UNITS = {"m": ("Meters", 1.0), "cm": ("Centimeters", 1e-2), "mm": ("Millimeters", 1e-3)}
#: Marker positions in the body frame (metres): an asymmetric constellation like a real pen's.
PEN_MARKERS_M = np.array(
    [[0.0, 0.0, 0.12], [0.03, 0.0, 0.10], [-0.02, 0.025, 0.09], [0.0, -0.035, 0.11]]
)
EULER_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")


def helix(n: int, rate_hz: float = 240.0, *, seed: int = 0):
    """A known pen trajectory: times, tip positions (metres) and tumbling orientations.

    Returns
    -------
    t_s : ndarray of shape (n,)
    position_m : ndarray of shape (n, 3)
        A helix of radius 0.1 m around (0.3, 0.1, 0.2).
    quat_xyzw : ndarray of shape (n, 4)
        Unit quaternions, scalar last, turning through all orientations.
    """
    t = np.arange(n) / rate_hz
    u = np.linspace(0.0, 4.0 * np.pi, n)
    position = np.column_stack(
        [0.3 + 0.1 * np.cos(u), 0.1 + 0.1 * np.sin(u), 0.2 + 0.02 * u / np.pi]
    )
    rng = np.random.default_rng(seed)
    axis = rng.standard_normal(3)
    rotvec = np.outer(u, axis / np.linalg.norm(axis)) * 0.7 + np.column_stack(
        [0.3 * np.sin(3 * u), 0.2 * np.cos(2 * u), np.zeros(n)]
    )
    quat = Rotation.from_rotvec(rotvec).as_quat(scalar_first=False)
    return t, position, quat


def write_motive_csv(  # noqa: C901
    path: str | Path,
    t_s: np.ndarray,
    position_m: np.ndarray,
    quat_xyzw: np.ndarray,
    *,
    units: str = "mm",
    rotation: str = "quaternion",
    rigid_bodies: Sequence[str] | None = None,
    lost: np.ndarray | None = None,
    header: bool = True,
    rate_hz: float | None = None,
    marker_error_m: np.ndarray | float = 1e-4,
    quality: bool = True,
    markers_per_body: int = 4,
    take_name: str = "Take 2024-05-14 10.21.07 AM",
    format_version: str = "1.23",
) -> Path:
    """Write a Motive CSV export.

    Parameters
    ----------
    path : path
    t_s : ndarray of shape (N,), seconds
    position_m : ndarray of shape (N, 3) or (B, N, 3), metres
        The rigid bodies' pivot points (the pen tip).
    quat_xyzw : ndarray of shape (N, 4) or (B, N, 4)
        Orientations, scalar last.
    units : {"mm", "cm", "m"}
        The export's length unit.
    rotation : {"quaternion", "XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"}
        Quaternions, or Euler angles in degrees in that (intrinsic) order.
    rigid_bodies : sequence of B str, optional
        Body names; default "Pen" for one body, "Rigid Body 1" … otherwise.
    lost : ndarray of shape (N,) or (B, N), bool, optional
        Frames where a body is lost: its cells (and its physical markers' cells) are empty.
    header : bool
        False writes what Motive writes with "Header information" unchecked: the data rows only.
    rate_hz : float, optional
        The capture and export rate of the metadata row (default: from the times).
    marker_error_m : float or ndarray of shape (N,) or (B, N), metres
        The "Mean Marker Error" column.
    quality : bool
        Write the quality statistics (Mean Marker Error, Marker Quality columns).
    markers_per_body : int
        Rigid body markers (and physical markers) per body, at most 4.
    take_name : str
    format_version : {"1.23", "1.22", "1.21"}
        1.23: Motive 2.x and 3.x; 1.21 and 1.22: Motive 1.x.

    Returns
    -------
    Path
    """
    path = Path(path)
    t = np.asarray(t_s, dtype=float)
    pos = np.asarray(position_m, dtype=float)
    quat = np.asarray(quat_xyzw, dtype=float)
    if pos.ndim == 2:
        pos, quat = pos[None], quat[None]
    n_bodies, n = pos.shape[:2]
    names = (
        list(rigid_bodies)
        if rigid_bodies is not None
        else (["Pen"] if n_bodies == 1 else [f"Rigid Body {i + 1}" for i in range(n_bodies)])
    )
    # (N,) masks and errors, or scalars, apply to every body.
    lost_mask = np.broadcast_to(np.asarray(False if lost is None else lost, bool), (n_bodies, n))
    error = np.broadcast_to(np.asarray(marker_error_m, dtype=float), (n_bodies, n))
    unit_name, scale = MOTIVE_UNITS[units]
    euler = None if rotation.lower() == "quaternion" else rotation.upper()
    if euler is not None and euler not in EULER_ORDERS:
        raise ValueError(f"unknown rotation {rotation!r}")
    offsets = PEN_MARKERS_M[:markers_per_body]
    motive_1 = format_version in ("1.21", "1.22")
    error_name = "Error Per Marker" if motive_1 else "Mean Marker Error"

    types, labels, ids, kinds, axes, columns = [], [], [], [], [], []

    def add(kind_type, name, ident, kind, axis, values, lost_rows):
        types.append(kind_type)
        labels.append(name)
        ids.append(ident)
        kinds.append(kind)
        axes.append(axis)
        columns.append(np.where(lost_rows, np.nan, values))

    physical = []
    for b, name in enumerate(names):
        rot = Rotation.from_quat(quat[b], scalar_first=False)
        gone = lost_mask[b]
        if euler is None:
            for i, axis in enumerate("XYZW"):
                add("Rigid Body", name, b + 1, "Rotation", axis, quat[b][:, i], gone)
        else:
            angles = rot.as_euler(euler, degrees=True)
            # Columns named by axis, whatever the order of the rotations.
            for axis in "XYZ":
                add("Rigid Body", name, b + 1, "Rotation", axis, angles[:, euler.index(axis)], gone)
        for i, axis in enumerate("XYZ"):
            add("Rigid Body", name, b + 1, "Position", axis, pos[b][:, i] / scale, gone)
        if quality:
            add("Rigid Body", name, b + 1, error_name, "", error[b] / scale, gone)
        for k, offset in enumerate(offsets):
            marker = pos[b] + rot.apply(offset)
            label, ident = f"{name}:Marker{k + 1}", f"{b + 1}:{k + 1}"
            # Solved marker positions exist whenever the body is tracked.
            for i, axis in enumerate("XYZ"):
                add("Rigid Body Marker", label, ident, "Position", axis, marker[:, i] / scale, gone)
            if quality:
                add("Rigid Body Marker", label, ident, "Marker Quality", "", np.full(n, 0.97), gone)
            physical.append((label, ident, marker, gone))
    for label, ident, marker, gone in physical:
        for i, axis in enumerate("XYZ"):
            add("Marker", label, ident, "Position", axis, marker[:, i] / scale, gone)

    data = np.column_stack(columns)
    lines = []
    if header:
        rate = rate_hz if rate_hz is not None else 1.0 / float(np.median(np.diff(t)))
        rotation_name = "Quaternion" if euler is None else euler
        meta = [
            ("Format Version", format_version),
            ("Take Name", take_name),
            *([] if motive_1 else [("Take Notes", "")]),
            ("Capture Frame Rate", f"{rate:.6f}"),
            ("Export Frame Rate", f"{rate:.6f}"),
            ("Capture Start Time", "2024-05-14 10.21.07.512 AM"),
            ("Capture Start Frame", "0"),
            ("Total Frames in Take", str(n)),
            ("Total Exported Frames", str(n)),
            ("Rotation Type", rotation_name),
            ("Length Units", unit_name),
            ("Coordinate Space", "Global"),
        ]
        lines.append(",".join(f"{k},{v}" for k, v in meta))
        lines.append("")
        # Motive 1.x leaves the row labels out and calls the time column "Time".
        label = {row: ",," if motive_1 else f",{row}," for row in ("Type", "Name", "ID")}
        lines.append(label["Type"] + ",".join(types))
        lines.append(label["Name"] + ",".join(labels))
        lines.append(label["ID"] + ",".join(str(i) for i in ids))
        lines.append(",," + ",".join(kinds))
        lines.append(("Frame,Time," if motive_1 else "Frame,Time (Seconds),") + ",".join(axes))
    # Motive writes six decimals and leaves the cells of lost bodies and markers empty.
    row_format = "%d,%.6f," + ",".join(["%.6f"] * data.shape[1])
    for i in range(n):
        lines.append((row_format % (i, t[i], *data[i])).replace("nan", ""))
    path.write_text("\r\n".join(lines) + "\r\n", encoding="utf-8")
    return path


def write_c3d(
    path: str | Path,
    labels: Sequence[str],
    positions_m: np.ndarray,
    rate_hz: float,
    *,
    units: str = "mm",
    lost: np.ndarray | None = None,
) -> Path:
    """Write a C3D file of marker trajectories with ezc3d.

    Parameters
    ----------
    path : path
        Should end in ``.c3d`` (ezc3d appends it otherwise).
    labels : sequence of M str
    positions_m : ndarray of shape (F, M, 3), metres
    rate_hz : float
    units : {"mm", "m", ""}
        ``POINT:UNITS``; "" writes none.
    lost : ndarray of shape (F, M), bool, optional
        Samples written as invalid (residual -1), as a tracker marks an occluded marker.

    Returns
    -------
    Path
    """
    import ezc3d

    path = Path(path)
    pos = np.asarray(positions_m, dtype=float)
    frames, n_markers = pos.shape[:2]
    scale = {"mm": 1e-3, "m": 1.0, "": 1.0}[units]
    lost_mask = np.zeros((frames, n_markers), bool) if lost is None else np.asarray(lost, bool)
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [float(rate_hz)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    c3d["parameters"]["POINT"]["UNITS"]["value"] = [units] if units else []
    points = np.ones((4, n_markers, frames))
    points[:3] = np.transpose(pos / scale, (2, 1, 0))
    points[:3, lost_mask.T] = np.nan
    residuals = np.where(lost_mask.T, -1.0, 0.0)[None]
    c3d["data"]["points"] = points
    c3d["data"]["meta_points"] = {
        "residuals": residuals,
        "camera_masks": np.zeros((7, n_markers, frames), dtype=bool),
    }
    if frames > 0xFFFF:
        # The header's frame numbers are 16-bit: declare the real length where readers look.
        c3d.add_parameter("POINT", "LONG_FRAMES", float(frames))
        for param, value in (("ACTUAL_START_FIELD", 1), ("ACTUAL_END_FIELD", frames)):
            c3d.add_parameter("TRIAL", param, [0, 0])
            # Two 16-bit words (low, high) in INT parameters; ezc3d would store floats.
            c3d["parameters"]["TRIAL"][param]["type"] = 2
            c3d["parameters"]["TRIAL"][param]["value"] = np.array(
                [_int16(value & 0xFFFF), _int16(value >> 16)]
            )
    c3d.write(str(path))
    return path


def _int16(word: int) -> int:
    return word - 0x10000 if word > 0x7FFF else word
