"""Result files users open elsewhere (CSV): reconstructions and trajectories.

A trajectory file starts with one comment line, ``# teachpath: {...}``: a JSON object saying what
it is (the robot it was planned for, the controller rate, the requested speed, the TCP and
payload, the configuration, the checks the plan passed, the teachpath version). Commands that
read it back refuse a file planned for another arm.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.errors import InputFileError, TrajectoryMismatchError
from drivers.files import atomic_path, csv_rows
from recon.arrays import FloatArray, piece_labels
from recon.paths import Phase, ReconstructedPath
from recon.results import PER_POINT_FIELDS, PointMode, PointReason, Reconstruction
from recon.trajectory import JointTrajectory

QUATERNION_COLUMNS = ("qx", "qy", "qz", "qw")
#: Columns of a trajectory file (the contract of ``teachpath plan``).
TRAJECTORY_COLUMNS = ("t", "q0", "q1", "q2", "q3", "q4", "q5", "x", "y", "z", "rx", "ry", "rz")

#: Columns after x, y, z, t and the quaternion, in order (the CSV contract of ``teachpath
#: reconstruct``): the per-point diagnostics of a reconstruction.
DIAGNOSTIC_COLUMNS = PER_POINT_FIELDS[PER_POINT_FIELDS.index("displacement_m") :]
#: printf formats of the diagnostic columns that are not numbers to 9 digits.
DIAGNOSTIC_FORMATS = {
    "mode": "%s",
    "reason": "%s",
    "segment": "%d",
    "n_path": "%d",
    "n_surface": "%d",
    "piece": "%d",
}


def write_reconstruction_csv(path: str | Path, recon: Reconstruction) -> None:
    """Write a reconstruction: ``x,y,z`` (metres), ``t`` and the pen's ``qx,qy,qz,qw`` if known,
    then per-point diagnostics. The file appears only when complete."""
    arrays = {name: getattr(recon, name) for name in PER_POINT_FIELDS}
    with atomic_path(path) as tmp:
        tmp.write_text(reconstruction_csv_text(arrays))


def reconstruction_csv_text(arrays: dict[str, Any]) -> str:
    """The CSV of a reconstruction from its arrays (the fields of :class:`Reconstruction`).

    ``mode`` is written as a word (path, surface, edge, unchanged); NaN residuals (no such fit)
    as empty cells. ``uncertainty_m`` is each point's 1-sigma uncertainty across the path;
    ``reason`` a word where the scan's evidence failed (``far_from_trace``, ``no_feature``, ...),
    or an edge was continued past its end (``continued``), empty elsewhere.
    """
    labels = {int(m): m.label for m in PointMode}
    reason_labels = {int(r): r.label for r in PointReason}
    n = len(arrays["points_m"])
    t, q = arrays.get("t_s"), arrays.get("orientations_xyzw")
    # Reconstructions stored before they were kept have no piece (one piece) and no uncertainty
    # (empty cells).
    values = {
        **arrays,
        "mode": np.array([labels[int(m)] for m in arrays["mode"]], dtype=object),
        "piece": np.zeros(n, np.int64) if arrays.get("piece") is None else arrays["piece"],
        "uncertainty_m": (
            np.full(n, np.nan) if arrays.get("uncertainty_m") is None else arrays["uncertainty_m"]
        ),
        # Why the scan was not used where the segment claimed it ("" where it was), or that an
        # edge was continued past its end; empty for reconstructions stored before it was kept.
        "reason": np.array(
            [""] * n
            if arrays.get("reason") is None
            else [reason_labels.get(int(r), str(int(r))) for r in arrays["reason"]],
            dtype=object,
        ),
    }
    # (header, values, printf format) per column, in the file's order.
    columns = [(axis, arrays["points_m"][:, k], "%.9g") for k, axis in enumerate("xyz")]
    if t is not None:
        columns.append(("t", t, "%.9g"))
    if q is not None:
        columns += [(name, q[:, k], "%.9g") for k, name in enumerate(QUATERNION_COLUMNS)]
    columns += [
        (name, values[name], DIAGNOSTIC_FORMATS.get(name, "%.9g")) for name in DIAGNOSTIC_COLUMNS
    ]
    return csv_table(columns)


def csv_table(columns: list[tuple[str, np.ndarray, str]]) -> str:
    """A CSV table (header line, then rows) from columns of ``(name, values (N,), printf
    format)``, formatted as one block: one printf over the whole table (per-number formatting
    in Python and the csv module took 0.35 s for 10k reconstruction rows, this 0.09 s).
    A non-finite number is an empty cell; ``%d`` columns are written as integers.
    """
    n = len(columns[0][1]) if columns else 0
    cells: list[Any] = [None] * (n * len(columns))
    formats = []
    for k, (_, values, fmt) in enumerate(columns):
        values = np.asarray(values)
        if fmt == "%d":
            values = values.astype(np.int64)
        elif values.dtype.kind == "f" and not np.isfinite(values).all():
            # This column alone cell by cell: empty where there is no number.
            values = np.array(
                [fmt % v if np.isfinite(v) else "" for v in values.tolist()], dtype=object
            )
            fmt = "%s"
        cells[k :: len(columns)] = values.tolist()
        formats.append(fmt)
    row = ",".join(formats) + "\n"
    return ",".join(name for name, _, _ in columns) + "\n" + (row * n) % tuple(cells)


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
    _meta, rows, label = _read_rows(source, name)
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
    piece = None
    if "piece" in header:
        labels = _numbers(body, [header.index("piece")], label)[:, 0]
        try:
            if not np.all(labels == np.round(labels)):
                raise ValueError("piece numbers must be whole")
            piece = piece_labels(labels.astype(np.int64), len(labels))
        except ValueError as exc:
            raise InputFileError(f"{label}: column piece: {exc}") from None
    return ReconstructedPath(
        points_m=points, mode=modes, orientations_xyzw=orientations, piece=piece
    )


#: How a teachpath file's metadata line starts (a comment to CSV readers: pandas takes
#: ``comment="#"``, numpy.loadtxt skips it by default).
META_PREFIX = "# teachpath: "


def write_trajectory_csv(
    path: str | Path, trajectory: JointTrajectory, *, meta: dict[str, Any] | None = None
) -> None:
    """``t,q0..q5`` (s, rad), the planned TCP ``x,y,z,rx,ry,rz`` (m, rotation vector, base
    frame) and the ``phase`` of each sample, one row per controller period, after a metadata
    line (robot, rate, what was planned and checked). The file appears only when complete."""
    with atomic_path(path) as tmp:
        tmp.write_text(trajectory_csv_text(trajectory, meta=meta))


def trajectory_csv_text(trajectory: JointTrajectory, *, meta: dict[str, Any] | None = None) -> str:
    """The CSV of a trajectory (see :func:`write_trajectory_csv`).

    Parameters
    ----------
    trajectory : JointTrajectory
    meta : dict, optional
        What else the file should say (the plan's summary: TCP, configuration, checks, ...);
        ``robot``, ``rate_hz`` and ``requested_speed_m_s`` come from the trajectory.
    """
    labels = np.array([p.label for p in Phase], dtype=object)[trajectory.phases]
    numbers = np.column_stack(
        [trajectory.t_s, trajectory.q_rad, trajectory.tcp_m, trajectory.tcp_rotvec]
    )
    head = {
        **(meta or {}),
        "kind": "trajectory",
        "robot": trajectory.robot,
        "rate_hz": 1.0 / trajectory.period_s if len(trajectory) > 1 else None,
        "requested_speed_m_s": trajectory.requested_speed_m_s,
        # The joints are right for this calibration only: the file says which.
        "calibration": None if trajectory.calibration is None else trajectory.calibration.as_dict(),
    }
    columns = [(name, numbers[:, k], "%.10g") for k, name in enumerate(TRAJECTORY_COLUMNS)]
    columns.append(("phase", labels, "%s"))
    return META_PREFIX + json.dumps(head, allow_nan=False) + "\n" + csv_table(columns)


@dataclass(frozen=True)
class TrajectoryFile:
    """A trajectory read back from its CSV, with what the file says about it.

    Attributes
    ----------
    trajectory : JointTrajectory
    meta : dict
        The metadata line (empty for a file written before it existed).
    """

    trajectory: JointTrajectory
    meta: dict[str, Any]


def read_trajectory_csv(
    source: str | Path | bytes, *, robot: str | None = None, name: str | None = None
) -> TrajectoryFile:
    """Read a trajectory CSV back, for the robot it was planned for.

    Velocities and accelerations are recovered by finite differences; the samples must be
    equally spaced in time, at the robot's controller rate.

    Parameters
    ----------
    robot : str, optional
        The arm it is to run on; a file planned for another one is refused. Default: the one
        the file names (a file that names none: UR5e).

    Raises
    ------
    InputFileError
        Wrong columns, non-numeric or non-finite values, uneven or non-increasing times.
    TrajectoryMismatchError
        The file was planned for another arm, or its samples are not at the arm's rate.
    """
    from recon.kinematics import DHCalibration, model

    meta, rows, label = _read_rows(source, name)
    planned_for = meta.get("robot")
    if robot is not None and planned_for is not None and robot.lower() != planned_for:
        raise TrajectoryMismatchError(
            f"{label} was planned for a {planned_for}, not a {robot.lower()}: plan it again for "
            "that arm, or run it on the arm it was planned for"
        )
    robot = (robot or planned_for or "ur5e").lower()
    arm = model(robot)
    calibration = None
    if meta.get("calibration") is not None:
        try:
            calibration = DHCalibration.from_dict(meta["calibration"])
        except ValueError as exc:
            raise InputFileError(
                f"{label}: the calibration it names is not one ({exc}); plan it again"
            ) from None
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
    if abs(dt[0] * arm.control_rate_hz - 1.0) > 1e-3:
        raise TrajectoryMismatchError(
            f"{label} is sampled every {dt[0] * 1e3:.3f} ms; the {robot}'s controller runs at "
            f"{arm.control_rate_hz:.0f} Hz: it was planned for another arm"
        )
    phase = None
    if "phase" in header:
        by_label = {p.label: int(p) for p in Phase}
        column = header.index("phase")
        try:
            phase = np.array([by_label[r[column].strip()] for r in rows[1:]], dtype=np.int8)
        except (KeyError, IndexError) as exc:
            raise InputFileError(
                f"{label} has an unknown phase {exc}; expected one of {', '.join(by_label)}"
            ) from None
    q = data[:, 1:7]
    qd = np.gradient(q, t, axis=0)
    requested = meta.get("requested_speed_m_s")
    trajectory = JointTrajectory(
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
        # A file that does not say what was requested: its mean speed stands in for it.
        requested_speed_m_s=float(requested) if requested else _mean_speed(data[:, 7:10], t),
        phase=phase,
        calibration=calibration,
    )
    return TrajectoryFile(trajectory=trajectory, meta=meta)


def _mean_speed(p: FloatArray, t: FloatArray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)) / max(t[-1] - t[0], 1e-12))


def _read_rows(
    source: str | Path | bytes, name: str | None
) -> tuple[dict[str, Any], list[list[str]], str]:
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
    lines = text.splitlines()
    meta: dict[str, Any] = {}
    if lines and lines[0].startswith(META_PREFIX):
        try:
            meta = json.loads(lines[0][len(META_PREFIX) :])
        except json.JSONDecodeError:
            raise InputFileError(
                f"{label}: its first line is a damaged teachpath header; write the file again"
            ) from None
        if not isinstance(meta, dict):
            raise InputFileError(f"{label}: its teachpath header is not a JSON object")
        lines = lines[1:]
    rows = [r for r in csv_rows(lines, label) if any(c.strip() for c in r)]
    if not rows:
        raise InputFileError(f"{label} is empty")
    return meta, rows, label


def _numbers(body: list[list[str]], columns: list[int], label: str) -> FloatArray:
    try:
        data = np.array([[float(row[c]) for c in columns] for row in body], dtype=np.float64)
    except (ValueError, IndexError):
        raise InputFileError(f"{label} has a missing or non-numeric value") from None
    if not np.all(np.isfinite(data)):
        raise InputFileError(f"{label} has NaN or infinite values")
    return data
