"""Work run in the worker processes: parsing uploads, reconstruction, planning, dry runs.

Each task is a frozen dataclass of its arguments whose ``run()`` reads its inputs from array
files, calls the pipeline the command line calls too (:mod:`service.pipelines`), writes its
output with an atomic rename and returns a JSON-able summary. A task never touches the database:
the main process records what it made. Domain errors propagate to the job that ran it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from drivers.files import atomic_path
from recon.params import PIVOT_TOLERANCE_M
from service import pipelines
from service.artifacts import (
    Arrays,
    ExecutionCodec,
    ReconstructionCodec,
    RecordingCodec,
    ScanCodec,
    TrajectoryCodec,
    TrajectorySummary,
)


def save_arrays(path: str | Path, arrays: Arrays) -> None:
    """Write arrays as an ``.npz`` that appears only when complete."""
    with atomic_path(Path(path)) as tmp, tmp.open("wb") as handle:
        np.savez(handle, **arrays)


def load_arrays(path: str | Path) -> Arrays:
    with np.load(path, allow_pickle=False) as data:
        return {key: data[key] for key in data.files}


def recording_summary(recording, fmt: str) -> dict:
    """Size and extent of a recording (see :class:`service.artifacts.RecordingSummary`)."""
    points = np.asarray(recording.points_m)
    t = recording.t_s
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


def scan_summary(scan, fmt: str, *, n_dropped: int = 0, notes=()) -> dict:
    """Size and extent of a scan (see :class:`service.artifacts.ScanSummary`)."""
    points = np.asarray(scan.points_m)
    return {
        "format": fmt,
        "n_points": int(len(points)),
        "n_dropped": int(n_dropped),
        "has_normals": scan.normals is not None,
        "notes": list(notes),
        "bounds_m": [points.min(axis=0).tolist(), points.max(axis=0).tolist()],
    }


@dataclass(frozen=True)
class ParseRecording:
    """An uploaded trace: read, moved to the tip, cleaned, a piece picked.

    ``run()`` returns (arrays, summary).
    """

    content: bytes
    filename: str
    format: str | None = None
    units: str | None = None
    rigid_body: str | None = None
    marker: str | None = None
    tip_offset_m: tuple[float, float, float] | None = None
    piece: int | Literal["all"] | None = None

    def run(self) -> tuple[Arrays, dict]:
        from drivers.tracking.readers import read_trace
        from recon.reconstruct import check_scales

        trace = read_trace(
            self.content,
            name=self.filename,
            fmt=self.format,
            units=self.units,
            rigid_body=self.rigid_body,
            marker=self.marker,
            tip_offset_m=None if self.tip_offset_m is None else np.array(self.tip_offset_m),
            piece=self.piece,
            # The session's offset is for rigid-body recordings; a position-only file holds tip
            # positions already (the summary says the offset was not applied).
            tip_needs_orientations=False,
        )
        recording = trace.recording
        check_scales(recording.points_m, None)
        summary = recording_summary(recording, trace.format)
        summary.update(trace.summary())
        if self.tip_offset_m is not None and not trace.tip_offset_applied:
            summary.setdefault("notes", []).append(
                "the session's tip offset was not applied: the file has positions only (taken "
                "as the pen's tip)"
            )
        return RecordingCodec.encode(recording), summary


@dataclass(frozen=True)
class ParsePivot:
    """A pivot calibration from an uploaded recording. ``run()`` returns its JSON result."""

    content: bytes
    filename: str
    format: str | None = None
    units: str | None = None
    rigid_body: str | None = None
    tolerance_m: float = PIVOT_TOLERANCE_M
    accept_poor_fit: bool = False

    def run(self) -> dict:
        from drivers.tracking.readers import read_raw_trace

        raw = read_raw_trace(
            self.content,
            name=self.filename,
            fmt=self.format,
            units=self.units,
            rigid_body=self.rigid_body,
        )
        outcome = pipelines.pivot(
            raw, tolerance_m=self.tolerance_m, accept_poor_fit=self.accept_poor_fit
        )
        return outcome.as_json()


@dataclass(frozen=True)
class ParseScan:
    """An uploaded scan. ``run()`` returns (arrays, summary)."""

    content: bytes
    filename: str
    format: str | None
    units: str
    options: dict | None = None
    limits: dict | None = None

    def run(self) -> tuple[Arrays, dict]:
        from drivers.scanning.pointcloud import read_scan

        scan_file = read_scan(
            self.content,
            name=self.filename,
            fmt=self.format,
            units=self.units,
            options=self.options,
            limits=self.limits,
        )
        summary = scan_summary(
            scan_file.scan, scan_file.format, n_dropped=scan_file.n_dropped, notes=scan_file.notes
        )
        return ScanCodec.encode(scan_file.scan), summary


@dataclass(frozen=True)
class Reconstruct:
    """Reconstruct a stored recording with a stored scan; write the arrays and a preview.

    ``run()`` returns the reconstruction's summary.
    """

    recording_path: str
    scan_path: str | None
    params: dict
    out_path: str
    preview_path: str
    preview_title: str
    T_scan_tracker_init: list | None = None

    def run(self) -> dict:
        from recon.types import ReconParams

        recording = RecordingCodec.decode(load_arrays(self.recording_path))
        scan = ScanCodec.decode(load_arrays(self.scan_path)) if self.scan_path else None
        outcome = pipelines.reconstruct(
            recording,
            scan,
            params=ReconParams(**self.params),
            T_scan_tracker_init=self.T_scan_tracker_init,
        )
        save_arrays(self.out_path, ReconstructionCodec.encode(outcome.reconstruction))
        outcome.write_preview(self.preview_path, title=self.preview_title)
        return outcome.summary()


@dataclass(frozen=True)
class Plan:
    """Plan a trajectory along a stored reconstruction, with its scan model and transform.

    ``run()`` returns the trajectory's summary.
    """

    reconstruction_path: str
    params: dict
    recon_params: dict
    T_base_tracker: list | None
    out_path: str
    scan_path: str | None = None
    keep_out_boxes: list = ()
    cell_planes: list = ()
    start_from: str = "given"

    def run(self) -> dict:
        from recon.types import PlanParams, ReconParams

        arrays = load_arrays(self.reconstruction_path)
        outcome = pipelines.plan(
            ReconstructionCodec.decode(arrays),
            params=PlanParams(**self.params),
            T_base_tracker=self.T_base_tracker,
            scan_model=ReconstructionCodec.scan_model(arrays),
            recon_params=ReconParams(**self.recon_params),
            scan=ScanCodec.decode(load_arrays(self.scan_path)) if self.scan_path else None,
            keep_out_boxes=self.keep_out_boxes,
            cell_planes=self.cell_planes,
            start_from=self.start_from,
        )
        report = outcome.plan.collision
        clearance = None if report is None else report.clearance_m
        save_arrays(
            self.out_path, TrajectoryCodec.encode(outcome.trajectory, clearance_m=clearance)
        )
        return outcome.summary()


def load_trajectory(path: str | Path, summary: dict):
    """A stored trajectory, with what its summary says it was planned for."""
    return TrajectoryCodec.decode(load_arrays(path), TrajectorySummary.model_validate(summary))


@dataclass(frozen=True)
class DryRun:
    """Execute a stored trajectory on the simulated arm; write the record.

    ``run()`` returns the execution's summary.
    """

    trajectory_path: str
    trajectory_summary: dict
    out_path: str
    mode: str = "servoj"
    tolerance_m: float = 5e-4

    def run(self) -> dict:
        trajectory = load_trajectory(self.trajectory_path, self.trajectory_summary)
        outcome = pipelines.dry_run(trajectory, mode=self.mode, tolerance_m=self.tolerance_m)
        save_arrays(self.out_path, ExecutionCodec.encode(outcome.record))
        return outcome.summary()
