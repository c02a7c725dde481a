"""Result files users open elsewhere (CSV): reconstructions and trajectories."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from drivers.errors import InputFileError
from drivers.files import atomic_path
from recon.types import (
    PER_POINT_FIELDS,
    FloatArray,
    JointTrajectory,
    PointMode,
    ReconstructedPath,
    Reconstruction,
)

QUATERNION_COLUMNS = ("qx", "qy", "qz", "qw")
#: Columns of a trajectory file (the contract of ``teachpath plan``).
TRAJECTORY_COLUMNS = ("t", "q0", "q1", "q2", "q3", "q4", "q5", "x", "y", "z", "rx", "ry", "rz")

#: Columns after x, y, z, t and the quaternion, in order (the CSV contract of ``teachpath
#: reconstruct``): the per-point diagnostics of a reconstruction.
DIAGNOSTIC_COLUMNS = PER_POINT_FIELDS[PER_POINT_FIELDS.index("displacement_m") :]


def write_reconstruction_csv(path: str | Path, recon: Reconstruction) -> None:
    """Write a reconstruction: ``x,y,z`` (metres), ``t`` and the pen's ``qx,qy,qz,qw`` if known,
    then per-point diagnostics. The file appears only when complete."""
    arrays = {name: getattr(recon, name) for name in PER_POINT_FIELDS}
    with atomic_path(path) as tmp:
        tmp.write_text(reconstruction_csv_text(arrays))


def reconstruction_csv_text(arrays: dict) -> str:
    """The CSV of a reconstruction from its arrays (the fields of :class:`Reconstruction`).

    ``mode`` is written as a word (path, surface, edge, unchanged); NaN residuals (no such fit)
    as empty cells.
    """
    labels = {int(m): m.label for m in PointMode}
    t, q = arrays.get("t_s"), arrays.get("orientations_xyzw")
    header = (
        ["x", "y", "z"]
        + (["t"] if t is not None else [])
        + (list(QUATERNION_COLUMNS) if q is not None else [])
        + list(DIAGNOSTIC_COLUMNS)
    )

    def number(value: float) -> str:
        return "" if not np.isfinite(value) else f"{value:.9g}"

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    points = arrays["points_m"]
    for i in range(len(points)):
        row = [number(v) for v in points[i]]
        if t is not None:
            row.append(number(t[i]))
        if q is not None:
            row += [number(v) for v in q[i]]
        row += [
            number(arrays["displacement_m"][i]),
            labels[int(arrays["mode"][i])],
            str(int(arrays["segment"][i])),
            str(int(arrays["n_path"][i])),
            str(int(arrays["n_surface"][i])),
            number(arrays["residual_path_m"][i]),
            number(arrays["residual_surface_m"][i]),
            number(arrays["alpha"][i]),
        ]
        writer.writerow(row)
    return buffer.getvalue()


def read_reconstruction_csv(
    source: str | Path | bytes, *, name: str | None = None
) -> ReconstructedPath:
    """Read a reconstruction CSV (as written by :func:`write_reconstruction_csv`, or any CSV with
    ``x,y,z`` in metres). The file does not say which ``T_scan_tracker`` the reconstruction used:
    the result's is None.

    Raises
    ------
    InputFileError
        Missing file, no x,y,z header, non-numeric or non-finite values, unknown modes, fewer
        than two rows.
    """
    rows, label = _read_rows(source, name)
    header = [c.strip().lower() for c in rows[0]]
    missing = [c for c in ("x", "y", "z") if c not in header]
    if missing:
        raise InputFileError(
            f"{label} has no column {', '.join(missing)}; expected the CSV "
            "`teachpath reconstruct` writes (x,y,z,...)"
        )
    body = rows[1:]
    if len(body) < 2:
        raise InputFileError(f"{label} has {len(body)} rows; a path needs at least two")
    points = _numbers(body, [header.index(c) for c in ("x", "y", "z")], label)
    modes = np.full(len(body), int(PointMode.PATH), dtype=np.int8)
    if "mode" in header:
        by_label = {m.label: int(m) for m in PointMode}
        column = header.index("mode")
        try:
            modes = np.array([by_label[r[column].strip()] for r in body], dtype=np.int8)
        except (KeyError, IndexError) as exc:
            raise InputFileError(
                f"{label} has an unknown mode {exc}; expected one of {', '.join(by_label)}"
            ) from None
    orientations = None
    if all(c in header for c in QUATERNION_COLUMNS):
        q = _numbers(body, [header.index(c) for c in QUATERNION_COLUMNS], label)
        orientations = q / np.maximum(np.linalg.norm(q, axis=1), 1e-12)[:, None]
    return ReconstructedPath(points_m=points, mode=modes, orientations_xyzw=orientations)


def write_trajectory_csv(path: str | Path, trajectory: JointTrajectory) -> None:
    """``t,q0..q5`` (s, rad) then the planned TCP ``x,y,z,rx,ry,rz`` (m, rotation vector), base
    frame, one row per controller period. The file appears only when complete."""
    with atomic_path(path) as tmp:
        tmp.write_text(trajectory_csv_text(trajectory))


def trajectory_csv_text(trajectory: JointTrajectory) -> str:
    """The CSV of a trajectory (see :func:`write_trajectory_csv`)."""
    data = np.column_stack(
        [trajectory.t_s, trajectory.q_rad, trajectory.tcp_m, trajectory.tcp_rotvec]
    )
    buffer = io.StringIO()
    np.savetxt(
        buffer, data, delimiter=",", header=",".join(TRAJECTORY_COLUMNS), comments="", fmt="%.10g"
    )
    return buffer.getvalue()


def read_trajectory_csv(source: str | Path | bytes, *, robot: str, name: str | None = None):
    """Read a trajectory CSV back as a :class:`JointTrajectory` for ``robot``.

    Velocities and accelerations are recovered by finite differences; the samples must be
    equally spaced in time.

    Raises
    ------
    InputFileError
        Wrong columns, non-numeric or non-finite values, uneven or non-increasing times.
    """
    rows, label = _read_rows(source, name)
    header = [c.strip().lower() for c in rows[0]]
    if tuple(header[: len(TRAJECTORY_COLUMNS)]) != TRAJECTORY_COLUMNS:
        raise InputFileError(
            f"{label} does not start with the columns "
            f"{','.join(TRAJECTORY_COLUMNS)}; expected a `teachpath plan` file"
        )
    data = _numbers(rows[1:], list(range(len(TRAJECTORY_COLUMNS))), label)
    if len(data) < 2:
        raise InputFileError(f"{label} has fewer than two samples")
    t = data[:, 0]
    dt = np.diff(t)
    if np.any(dt <= 0) or np.ptp(dt) > 1e-6:
        raise InputFileError(
            f"{label}: the times must increase in equal steps (one controller "
            "period); plan the trajectory again"
        )
    q = data[:, 1:7]
    qd = np.gradient(q, t, axis=0)
    return JointTrajectory(
        robot=robot,
        t_s=t,
        q_rad=q,
        qd_rad_s=qd,
        qdd_rad_s2=np.gradient(qd, t, axis=0),
        tcp_m=data[:, 7:10],
        tcp_rotvec=data[:, 10:13],
        arc_length_m=np.concatenate(
            ([0.0], np.cumsum(np.linalg.norm(np.diff(data[:, 7:10], axis=0), axis=1)))
        ),
        # The file does not say what was requested; its mean speed stands in for it.
        requested_speed_m_s=_mean_speed(data[:, 7:10], t),
    )


def _mean_speed(p, t) -> float:
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)) / max(t[-1] - t[0], 1e-12))


def _read_rows(source, name):
    label = name or ("upload" if isinstance(source, bytes) else str(source))
    if isinstance(source, bytes):
        raw = source
    else:
        try:
            raw = Path(source).read_bytes()
        except (FileNotFoundError, IsADirectoryError):
            raise InputFileError(f"{label} does not exist or is not a file") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputFileError(f"{label} is not a text CSV file") from None
    rows = [r for r in csv.reader(text.splitlines()) if any(c.strip() for c in r)]
    if not rows:
        raise InputFileError(f"{label} is empty")
    return rows, label


def _numbers(body, columns, label) -> FloatArray:
    try:
        data = np.array([[float(row[c]) for c in columns] for row in body], dtype=np.float64)
    except (ValueError, IndexError):
        raise InputFileError(f"{label} has a missing or non-numeric value") from None
    if not np.all(np.isfinite(data)):
        raise InputFileError(f"{label} has NaN or infinite values")
    return data
