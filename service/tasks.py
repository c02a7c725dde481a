"""Work run in the worker processes: parsing uploads, reconstruction, planning, dry runs.

Each task is a frozen dataclass of its arguments whose ``run()`` reads its inputs from array
files, calls the pipeline the command line calls too (:mod:`service.pipelines`), writes its
output with an atomic rename and returns a JSON-able summary. A task never touches the database:
the main process records what it made. Domain errors propagate to the job that ran it.

An upload is parsed one step further away: the worker hands it to a child process of its own
under a memory and a time limit (:func:`parse_in_child`, through
:func:`drivers.isolation.run_isolated`), so that a file that makes its reader allocate without
bound or run forever (a header declaring 10^9 points, a bomb nobody has thought of yet) costs
that child, never the worker or the machine: it is an :class:`~drivers.errors.InputTooLargeError`
naming the limit and its setting. The child runs the ``parse_*`` functions of
:mod:`service.parsing`, a module that imports little (a child pays for its imports at every
upload); what is checked after the read (a trace's units) is checked here, in the worker.
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from drivers.errors import InputTooLargeError, ResourceLimitError
from drivers.isolation import Limits, Usage, run_isolated
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
from service.parsing import SUMMARY_KEY
from service.parsing import load_arrays as load_arrays  # used by the executions, the command line
from service.parsing import recording_summary as recording_summary  # used by captures, the demo
from service.parsing import save_arrays as save_arrays
from service.parsing import scan_summary as scan_summary

if TYPE_CHECKING:
    from recon.trajectory import JointTrajectory

# -- uploads, parsed in a child process of their own -----------------------------------------------


@dataclass(frozen=True)
class ParseLimits:
    """Bounds of the child process an upload is parsed in, and the settings that set them.

    The defaults are the service's (:class:`service.settings.Settings`); the setting names
    appear in the message of an upload refused at a bound.

    Attributes
    ----------
    time_s : float
        Wall time of the child, interpreter start included.
    memory_mb : float
        Its address space (MiB).
    time_setting, memory_setting : str
    """

    time_s: float = 300.0
    memory_mb: float = 4096.0
    time_setting: str = "TEACHPATH_MAX_SCAN_DECODE_S"
    memory_setting: str = "TEACHPATH_MAX_PARSE_MEMORY_MB"

    def isolation(self) -> Limits:
        """The :class:`drivers.isolation.Limits` of these bounds."""
        return Limits(
            time_s=self.time_s,
            memory_bytes=int(self.memory_mb * 2**20),
            time_setting=self.time_setting,
            memory_setting=self.memory_setting,
            background=True,  # below the server, as the job pool's workers are
        )


def parse_in_child(
    target: str,
    content: bytes,
    filename: str,
    kwargs: dict[str, Any],
    limits: ParseLimits,
    *,
    out_path: str | None = None,
    on_usage: Callable[[Usage], None] | None = None,
) -> tuple[Arrays, dict[str, Any]]:
    """Run the parse function ``target`` of :mod:`service.parsing` on ``content`` in a child
    process.

    The content goes to a temporary file the child reads (not through its stdin); the child
    returns its summary as JSON under :data:`SUMMARY_KEY`, and its arrays, or writes them to
    ``out_path`` itself (then they never pass through this process nor the caller's: a 24 MB
    float PLY is 48 MB of points).

    Parameters
    ----------
    target : str
        Name of a ``parse_*`` function of :mod:`service.parsing`, called as
        ``f(path, filename, **kwargs, out_path=out_path)``.
    content : bytes
    filename : str
        The upload's (sanitised) name: its suffix picks the format, and messages name it.
    kwargs : dict
        The reader's arguments (plain values).
    limits : ParseLimits
    out_path : str, optional
        Where the child writes the artifact's arrays (an ``.npz``, complete or absent).
    on_usage : callable, optional
        Given the child's :class:`~drivers.isolation.Usage` (peak memory, time) when it ends.

    Returns
    -------
    tuple of (dict of arrays, dict)
        The arrays of the artifact (empty if written to ``out_path``) and its summary.

    Raises
    ------
    InputTooLargeError
        The child needed more memory or time than ``limits`` allow.
    InputFileError, ValueError, ...
        What the reader raised (an unreadable file, wrong options), or a crash of the child
        (:class:`~drivers.errors.ReaderCrashError`).
    """
    bounds = limits.isolation()
    with tempfile.TemporaryDirectory(prefix="teachpath-upload-") as tmp:
        path = Path(tmp) / "upload"
        path.write_bytes(content)
        try:
            arrays = run_isolated(
                f"service.parsing:{target}",
                (str(path), filename),
                {**kwargs, "out_path": out_path},
                limits=bounds,
                what=f"reading {filename}",
                on_usage=on_usage,
            )
        except ResourceLimitError as exc:
            # The child's own bounds (an error from a reader's inner child names no setting).
            if type(exc) is not ResourceLimitError or exc.setting not in (
                bounds.time_setting,
                bounds.memory_setting,
            ):
                raise
            raise InputTooLargeError(
                f"{exc}; send a smaller or simpler file, or raise {exc.setting} on the server",
                limit=exc.limit,
                value=exc.value,
                setting=exc.setting,
            ) from None
    summary: dict[str, Any] = json.loads(str(arrays.pop(SUMMARY_KEY)))
    return arrays, summary


@dataclass(frozen=True)
class ParseRecording:
    """An uploaded trace: read, moved to the tip, cleaned, a piece picked.

    ``run()`` returns (arrays, summary); the parse runs in a child
    (:func:`service.parsing.parse_recording`), which checks the units and writes the arrays to
    ``out_path`` if given (then ``run()`` returns no arrays).

    Raises
    ------
    UnitsMismatchError
        A path too large to be in metres (nothing is written).
    """

    content: bytes
    filename: str
    format: str | None = None
    units: str | None = None
    rigid_body: str | None = None
    marker: str | None = None
    tip_offset_m: tuple[float, float, float] | None = None
    piece: int | Literal["all"] | None = None
    parse_limits: ParseLimits = ParseLimits(time_setting="TEACHPATH_MAX_TRACE_PARSE_S")
    out_path: str | None = None
    #: ``touches``: a touch recording, whose rests are found and summarised
    #: (:func:`service.parsing.parse_touches`); ``recording``: a trace.
    kind: Literal["recording", "touches"] = "recording"

    def run(self, on_usage: Callable[[Usage], None] | None = None) -> tuple[Arrays, dict[str, Any]]:
        kwargs = {
            "format": self.format,
            "units": self.units,
            "rigid_body": self.rigid_body,
            "marker": self.marker,
            "tip_offset_m": self.tip_offset_m,
            "piece": self.piece,
        }
        return parse_in_child(
            "parse_touches" if self.kind == "touches" else "parse_recording",
            self.content,
            self.filename,
            kwargs,
            self.parse_limits,
            out_path=self.out_path,
            on_usage=on_usage,
        )


@dataclass(frozen=True)
class ParsePivot:
    """A pivot calibration from an uploaded recording. ``run()`` returns its JSON result; the
    parse runs in a child (:func:`service.parsing.parse_pivot`)."""

    content: bytes
    filename: str
    format: str | None = None
    units: str | None = None
    rigid_body: str | None = None
    parse_limits: ParseLimits = ParseLimits(time_setting="TEACHPATH_MAX_TRACE_PARSE_S")
    tolerance_m: float = PIVOT_TOLERANCE_M
    accept_poor_fit: bool = False

    def run(self, on_usage: Callable[[Usage], None] | None = None) -> dict[str, Any]:
        kwargs = {"format": self.format, "units": self.units, "rigid_body": self.rigid_body}
        _, result = parse_in_child(
            "parse_pivot", self.content, self.filename, kwargs, self.parse_limits, on_usage=on_usage
        )
        # Judged here, not in the child: the refusal's figures (its detail) stay with it.
        pipelines.refuse_poor_pivot(result, self.tolerance_m, self.accept_poor_fit)
        return result


@dataclass(frozen=True)
class ParseScan:
    """An uploaded scan. ``run()`` returns (arrays, summary); the parse runs in a child
    (:func:`service.parsing.parse_scan`).

    ``limits`` bound the reader's resource options (``max_unpacked_mb``, ``max_pixels``, ...)
    and ``limit_names`` name the settings behind them; ``parse_limits`` bound the child, which
    writes the arrays to ``out_path`` if given (then ``run()`` returns no arrays).
    """

    content: bytes
    filename: str
    format: str | None
    units: str
    options: dict[str, Any] | None = None
    limits: dict[str, float] | None = None
    limit_names: dict[str, str] | None = None
    parse_limits: ParseLimits = ParseLimits()
    out_path: str | None = None

    def run(self, on_usage: Callable[[Usage], None] | None = None) -> tuple[Arrays, dict[str, Any]]:
        kwargs = {
            "format": self.format,
            "units": self.units,
            "options": self.options,
            "limits": self.limits,
            "limit_names": self.limit_names,
        }
        return parse_in_child(
            "parse_scan",
            self.content,
            self.filename,
            kwargs,
            self.parse_limits,
            out_path=self.out_path,
            on_usage=on_usage,
        )


@dataclass(frozen=True)
class Reconstruct:
    """Reconstruct a stored recording with a stored scan; write the arrays and a preview.

    ``run()`` returns the reconstruction's summary.
    """

    recording_paths: tuple[str, ...]
    scan_path: str | None
    params: dict[str, Any]
    out_path: str
    preview_path: str
    preview_title: str
    T_scan_tracker_init: list[list[float]] | None = None
    #: A touch recording: the scanner is registered by it rather than by the trace.
    touches_path: str | None = None

    def run(self) -> dict[str, Any]:
        from recon.recon_params import ReconParams

        recordings = [RecordingCodec.decode(load_arrays(p)) for p in self.recording_paths]
        scan = ScanCodec.decode(load_arrays(self.scan_path)) if self.scan_path else None
        touches = (
            RecordingCodec.decode(load_arrays(self.touches_path)) if self.touches_path else None
        )
        outcome = pipelines.reconstruct(
            recordings if len(recordings) > 1 else recordings[0],
            scan,
            params=ReconParams(**self.params),
            T_scan_tracker_init=self.T_scan_tracker_init,
            touches=touches,
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
    params: dict[str, Any]
    recon_params: dict[str, Any]
    T_base_tracker: list[list[float]] | None
    out_path: str
    scan_path: str | None = None
    keep_out_boxes: Sequence[Sequence[float]] = ()
    cell_planes: Sequence[Sequence[float]] = ()
    start_from: str = "given"
    #: The arm's own kinematics calibration (``DHCalibration.as_dict()``); None: nominal.
    calibration: dict[str, Any] | None = None

    def run(self) -> dict[str, Any]:
        from recon.kinematics import DHCalibration
        from recon.plan_params import PlanParams
        from recon.recon_params import ReconParams

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
            calibration=None if self.calibration is None else DHCalibration.from_dict(
                self.calibration
            ),
        )  # fmt: skip
        report = outcome.plan.collision
        clearance = None if report is None else report.clearance_m
        save_arrays(
            self.out_path, TrajectoryCodec.encode(outcome.trajectory, clearance_m=clearance)
        )
        return outcome.summary()


@dataclass(frozen=True)
class MoveToStart:
    """Plan a move from where the arm is to a stored plan's start, checked against the cell the
    plan is checked against. ``run()`` returns the move's trajectory summary.

    Attributes
    ----------
    target_path, target_summary, target_id
        The plan's arrays file, summary and id.
    reconstruction_path : str or None
        The plan's reconstruction (where it placed the scan), if stored.
    params : dict
        :class:`recon.plan_params.PlanParams` of the plan, ``start_q_rad`` where the arm stands.
    q_from_rad : list of 6 floats
        Where the arm stands.
    out_path : str
        Where the move's arrays are written.
    scan_path : str or None
    T_base_tracker : list or None
        The plan's tracker-to-base transform (4x4).
    keep_out_boxes, cell_planes : list
        The cell in force.
    start_from : str
        "arm" or "home".
    calibration : dict or None
        The arm's kinematics calibration (``DHCalibration.as_dict()``).
    """

    target_path: str
    target_summary: dict[str, Any]
    target_id: str
    reconstruction_path: str | None
    params: dict[str, Any]
    q_from_rad: list[float]
    out_path: str
    scan_path: str | None = None
    T_base_tracker: list[list[float]] | None = None
    keep_out_boxes: Sequence[Sequence[float]] = ()
    cell_planes: Sequence[Sequence[float]] = ()
    start_from: str = "arm"
    calibration: dict[str, Any] | None = None

    def run(self) -> dict[str, Any]:
        from recon.kinematics import DHCalibration
        from recon.plan_params import PlanParams

        T_scan_tracker = None
        if self.reconstruction_path is not None:
            T_scan_tracker = ReconstructionCodec.decode(
                load_arrays(self.reconstruction_path)
            ).T_scan_tracker
        outcome = pipelines.move_to_start(
            self.q_from_rad,
            load_trajectory(self.target_path, self.target_summary),
            target_id=self.target_id,
            target_summary=self.target_summary,
            params=PlanParams(**self.params),
            scan=ScanCodec.decode(load_arrays(self.scan_path)) if self.scan_path else None,
            T_scan_tracker=T_scan_tracker,
            T_base_tracker=self.T_base_tracker,
            keep_out_boxes=self.keep_out_boxes,
            cell_planes=self.cell_planes,
            start_from=self.start_from,
            calibration=None if self.calibration is None else DHCalibration.from_dict(
                self.calibration
            ),
        )  # fmt: skip
        report = outcome.move.collision
        save_arrays(
            self.out_path,
            TrajectoryCodec.encode(
                outcome.trajectory, clearance_m=None if report is None else report.clearance_m
            ),
        )
        return outcome.summary()


def load_trajectory(path: str | Path, summary: dict[str, Any]) -> JointTrajectory:
    """A stored trajectory, with what its summary says it was planned for."""
    return TrajectoryCodec.decode(load_arrays(path), TrajectorySummary.model_validate(summary))


@dataclass(frozen=True)
class DryRun:
    """Execute a stored trajectory on the simulated arm; write the record.

    ``run()`` returns the execution's summary.
    """

    trajectory_path: str
    trajectory_summary: dict[str, Any]
    out_path: str
    mode: str = "servoj"
    tolerance_m: float = 5e-4

    def run(self) -> dict[str, Any]:
        trajectory = load_trajectory(self.trajectory_path, self.trajectory_summary)
        outcome = pipelines.dry_run(trajectory, mode=self.mode, tolerance_m=self.tolerance_m)
        save_arrays(self.out_path, ExecutionCodec.encode(outcome.record))
        return outcome.summary()
