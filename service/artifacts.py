"""Artifacts by kind: one codec each (domain object <-> arrays on disk) and typed summaries.

An artifact is an immutable product of a session (a recording, a scan, a reconstruction, a
trajectory, an execution) stored as one ``.npz`` of arrays plus a JSON summary in the database.
Everything that writes or reads those arrays goes through the codec of its kind, so the names of
the arrays live here only; everything that reads a summary goes through its model, so the OpenAPI
spec says what each kind reports and a reader (the real-arm gate) works on typed fields.

Summaries written by earlier versions lack newer fields: every field added later has a default,
and readers that must decide something from a summary (see :mod:`service.gate`) refuse when a
field they need is missing.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from recon.arrays import FloatArray
from recon.inputs import Recording, Scan
from recon.paths import ReconstructedPath, SpeedDrop
from recon.results import PER_POINT_FIELDS
from recon.trajectory import SAMPLE_FIELDS, JointTrajectory

if TYPE_CHECKING:
    from drivers.robot.base import ExecutionRecord
    from recon.recon_params import ReconParams
    from recon.results import Reconstruction
    from recon.scan_model import ScanModel

Arrays = dict[str, np.ndarray]

KindName = Literal["recording", "touches", "scan", "reconstruction", "trajectory", "execution"]

#: Artifact kinds and the prefix of their ids.
ID_PREFIX: dict[str, str] = {
    "recording": "rec",
    "touches": "tch",
    "scan": "scn",
    "reconstruction": "rcn",
    "trajectory": "trj",
    "execution": "exe",
}


def _present(arrays: Mapping[str, np.ndarray | None]) -> Arrays:
    """The arrays that exist (optional fields are simply not stored)."""
    return {name: value for name, value in arrays.items() if value is not None}


# -- codecs ----------------------------------------------------------------------------------------


class RecordingCodec:
    """A recording: pen-tip positions (tracker frame, m), times (s), orientations (xyzw); a
    synthetic one (the demo, a scene) also keeps the curve it was traced from (``truth_m``,
    tracker frame), so that a replay can say whether a change made it better or worse."""

    kind: ClassVar[str] = "recording"

    @staticmethod
    def encode(recording: Recording, *, truth_m: FloatArray | None = None) -> Arrays:
        return _present(
            {
                "points_m": np.asarray(recording.points_m),
                "t_s": recording.t_s,
                "orientations_xyzw": recording.orientations_xyzw,
                "piece": recording.piece if recording.n_pieces > 1 else None,
                "truth_m": None if truth_m is None else np.asarray(truth_m, dtype=np.float64),
            }
        )

    @staticmethod
    def truth(arrays: Arrays) -> FloatArray | None:
        """The ground truth of a synthetic recording, shape (G, 3), tracker frame; None for a
        real one (or one whose truth is not a finite curve)."""
        truth = arrays.get("truth_m")
        if truth is None or truth.ndim != 2 or truth.shape[1] != 3 or len(truth) < 2:
            return None
        return truth if np.isfinite(truth).all() else None

    @staticmethod
    def decode(arrays: Arrays) -> Recording:
        return Recording(
            points_m=arrays["points_m"],
            t_s=arrays.get("t_s"),
            orientations_xyzw=arrays.get("orientations_xyzw"),
            piece=arrays.get("piece"),
        )


class ScanCodec:
    """A scan: points (scan frame, m) and optional normals."""

    kind: ClassVar[str] = "scan"

    @staticmethod
    def encode(scan: Scan) -> Arrays:
        return _present({"points_m": np.asarray(scan.points_m), "normals": scan.normals})

    @staticmethod
    def decode(arrays: Arrays) -> Scan:
        return Scan(points_m=arrays["points_m"], normals=arrays.get("normals"))


#: Key prefix of the scan model's arrays stored beside a reconstruction.
SCAN_MODEL_PREFIX = "scan_model."
#: Key of the reconstruction's parameters (JSON text in a 0-d array: no pickle needed).
PARAMS_KEY = "params_json"


class ReconstructionCodec:
    """A reconstruction: per-point arrays, the ``T_scan_tracker`` and the parameters it used, and
    its scan model.

    The scan model (the cropped scan's structure in the scan frame) is stored so that planning
    reuses it with the same transform instead of registering and analysing the scan again. The
    service stores these arrays as the artifact; ``teachpath reconstruct`` writes them beside its
    CSV (``OUT.npz``) so that ``teachpath plan`` does the same.
    """

    kind: ClassVar[str] = "reconstruction"

    @staticmethod
    def encode(recon: Reconstruction) -> Arrays:
        """Arrays of a :class:`recon.results.Reconstruction`."""
        arrays = {name: getattr(recon, name) for name in PER_POINT_FIELDS}
        arrays["T_scan_tracker"] = recon.T_scan_tracker
        arrays[PARAMS_KEY] = np.array(json.dumps(dataclasses.asdict(recon.params)))
        if recon.scan_model is not None:
            for name, value in recon.scan_model.to_arrays().items():
                arrays[SCAN_MODEL_PREFIX + name] = value
        return _present(arrays)

    @staticmethod
    def per_point(arrays: Arrays) -> Arrays:
        """The per-point arrays only (what the CSV holds)."""
        return {name: arrays[name] for name in PER_POINT_FIELDS if name in arrays}

    @staticmethod
    def decode(arrays: Arrays) -> ReconstructedPath:
        """What planning needs: points, modes, pen orientations, the transform used."""
        T = arrays.get("T_scan_tracker")
        return ReconstructedPath(
            points_m=arrays["points_m"],
            mode=arrays["mode"],
            orientations_xyzw=arrays.get("orientations_xyzw"),
            T_scan_tracker=None if T is None or T.shape != (4, 4) else T,
            piece=arrays.get("piece"),
        )

    @staticmethod
    def recon_params(arrays: Arrays) -> ReconParams | None:
        """The parameters the reconstruction ran with, or None (stored by an older version)."""
        from recon.recon_params import ReconParams

        if PARAMS_KEY not in arrays:
            return None
        return ReconParams(**json.loads(str(arrays[PARAMS_KEY])))

    @staticmethod
    def scan_model(arrays: Arrays) -> ScanModel | None:
        """The stored scan model, or None (no scan was used)."""
        from recon.scan_model import ScanModel

        part = {
            name[len(SCAN_MODEL_PREFIX) :]: value
            for name, value in arrays.items()
            if name.startswith(SCAN_MODEL_PREFIX)
        }
        return ScanModel.from_arrays(part) if part else None


#: The sample arrays of a trajectory.
TRAJECTORY_FIELDS = SAMPLE_FIELDS


class TrajectoryCodec:
    """A timed joint trajectory on the controller's grid (base frame)."""

    kind: ClassVar[str] = "trajectory"

    @staticmethod
    def encode(trajectory: JointTrajectory, *, clearance_m: FloatArray | None = None) -> Arrays:
        """The samples, their phases, and (when the plan was checked) the smallest clearance
        of the arm and tool to the cell per sample (m)."""
        arrays = {name: getattr(trajectory, name) for name in TRAJECTORY_FIELDS}
        return _present({**arrays, "phase": trajectory.phase, "clearance_m": clearance_m})

    @staticmethod
    def decode(arrays: Arrays, summary: TrajectorySummary) -> JointTrajectory:
        """The trajectory; what it was planned for (the arm and its calibration) comes from
        its summary.

        Raises
        ------
        ValueError
            The summary's calibration is not one.
        """
        from recon.kinematics import DHCalibration

        calibration = summary.calibration
        return JointTrajectory(
            robot=summary.robot,
            calibration=None if calibration is None else DHCalibration.from_dict(calibration),
            requested_speed_m_s=summary.requested_speed_m_s,
            speed_drops=tuple(SpeedDrop(**d.model_dump()) for d in summary.speed_drops),
            phase=arrays.get("phase"),
            **{name: arrays[name] for name in TRAJECTORY_FIELDS},
        )


@dataclass(frozen=True)
class ExecutionSamples:
    """What an execution recorded, sample by sample (empty when it never moved).

    Attributes
    ----------
    t_s : ndarray of shape (K,)
    q_planned_rad, q_actual_rad : ndarray of shape (K, 6)
    """

    t_s: FloatArray
    q_planned_rad: FloatArray
    q_actual_rad: FloatArray


class ExecutionCodec:
    """An execution's samples (dry run or real arm: the same arrays)."""

    kind: ClassVar[str] = "execution"

    @staticmethod
    def encode(record: ExecutionRecord | None) -> Arrays:
        """Arrays of a :class:`drivers.robot.base.ExecutionRecord` (or None: nothing ran)."""
        if record is None or len(record) == 0:
            return {}
        return {
            "t_s": record.t_s,
            "q_planned_rad": record.q_planned_rad,
            "q_actual_rad": record.q_actual_rad,
        }

    @staticmethod
    def decode(arrays: Arrays) -> ExecutionSamples | None:
        if "t_s" not in arrays:
            return None
        return ExecutionSamples(arrays["t_s"], arrays["q_planned_rad"], arrays["q_actual_rad"])


# -- typed summaries -------------------------------------------------------------------------------


class _Summary(BaseModel):
    # Older rows may hold keys a summary has since dropped: keep them rather than fail to show
    # the artifact at all.
    model_config = ConfigDict(extra="allow")


Vector3 = tuple[float, float, float]
Matrix4 = list[list[float]]


class RecordingSummary(_Summary):
    """What an upload, a capture or the demo recorded, and what cleaning did to it.

    Reader-specific facts (the Motive rigid body, units, take name, ...) appear as extra keys.
    """

    format: str
    n_samples: int
    length_m: float
    duration_s: float | None = None
    has_orientations: bool = False
    bounds_m: list[Vector3] | None = Field(None, description="lower and upper corner, metres")
    rate_hz: float | None = None
    piece: int | Literal["all"] | None = Field(
        None, description="the piece kept of a trace split by long dropouts, or all of them"
    )
    n_pieces: int | None = None
    gaps: dict[str, Any] | None = None
    gap_report: list[str] = Field(default_factory=list)
    tip_offset_applied: bool = False
    notes: list[str] = Field(default_factory=list)


class TouchesSummary(RecordingSummary):
    """A touch recording: the recording's summary and the tip's rests found in it."""

    n_touches: int = Field(..., description="rests of the tip of 0.3 s or more")
    touches_m: list[Vector3] = Field(..., description="each rest's mean tip position")
    touch_spread_m: list[float] = Field(
        default_factory=list, description="RMS of the tip about each rest's mean"
    )


class ScanSummary(_Summary):
    format: str
    n_points: int
    n_dropped: int = 0
    dropped_because: str | None = Field(None, description="why the reader left them out")
    has_normals: bool = False
    notes: list[str] = Field(default_factory=list)
    bounds_m: list[Vector3] | None = None


class SegmentSummary(BaseModel):
    start: int
    stop: int
    kind: Literal["edge", "surface", "path"]
    edge_fraction: float = Field(..., description="share of the segment its chosen edge runs along")
    edge_distance_m: float | None = Field(
        None, description="how far the trace ran from its edge (median; null: no edge)"
    )
    next_edge_m: float | None = Field(
        None, description="how far the next candidate edge lay from it (median; null: none)"
    )
    fallen_back: float = Field(
        0.0, description="share of its points where the scan's evidence failed (the trace kept)"
    )


class RegistrationSummary(BaseModel):
    T_scan_tracker: Matrix4
    rmse_m: float
    fitness: float
    n_pairs: int
    target: Literal["edge", "surface", "touches"]
    constrained_dof: int
    path_moved_mean_m: float | None = Field(
        None, description="how far the path's points moved from the initial placement (mean)"
    )
    path_moved_max_m: float | None = Field(None, description="the same, at most")
    path_moved_off_feature_median_m: float | None = Field(
        None,
        description="the part of a point's move toward or away from the feature it was "
        "registered to (the surface's normal, across the edge), median over the path; the rest "
        "slid along it",
    )
    reason: str = Field("", description="why this target was chosen")
    alternative: dict[str, Any] | None = Field(
        None, description="the other target's figures, when it was tried too"
    )


class CornerSummary(BaseModel):
    index: int = Field(..., description="the resampled point where the trace turns")
    angle_deg: float
    split: bool
    reason: str
    point_m: Vector3 | None = Field(
        None, description="where both segments end (tracker frame), when the scan placed it"
    )


class DemonstrationSummary(BaseModel):
    used: bool
    reversed: bool
    mean_offset_m: float | None = Field(
        None, description="mean distance from the others' median (null: it overlapped none)"
    )
    roughness_m: float
    reason: str = ""


class ReconstructionSummary(_Summary):
    n_points: int
    modes: dict[str, int] = Field(..., description="points per mode: path, surface, edge, ...")
    reasons: dict[str, int] = Field(
        default_factory=dict,
        description="points per reason where the scan's evidence failed or an edge was continued",
    )
    mean_displacement_m: float
    max_displacement_m: float
    segments: list[SegmentSummary]
    n_pieces: int = Field(1, description="the trace's pieces, reconstructed apart")
    T_scan_tracker: Matrix4 | None = Field(
        None, description="the transform used: registered, else the given one; null: no scan"
    )
    registration: RegistrationSummary | None = None
    corners: list[CornerSummary] = Field(
        default_factory=list, description="every sharp turn of the trace, split or not, and why"
    )
    demonstrations: list[DemonstrationSummary] = Field(
        default_factory=list, description="how each fused demonstration entered"
    )
    uncertainty_mean_m: float | None = Field(
        None, description="1-sigma uncertainty across the path, mean over the points"
    )
    uncertainty_max_m: float | None = Field(None, description="the same, at most")
    notes: list[str] = Field(default_factory=list)


class SpeedDropSummary(BaseModel):
    start_m: float
    end_m: float
    min_speed_m_s: float
    cause: str


def as_core_params(
    params: dict[str, Any], overrides: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Stored parameters (JSON: sequences came back as lists) as the parameter classes
    (:class:`recon.plan_params.PlanParams`, ``ReconParams``) take them, tuples.

    Parameters
    ----------
    params : dict
        As stored with an artifact.
    overrides : dict, optional
        Values that replace the stored ones.

    Returns
    -------
    dict
    """
    merged = {**params, **(overrides or {})}
    return {k: tuple(v) if isinstance(v, list) else v for k, v in merged.items()}


class TrajectorySummary(_Summary):
    move_to_start_of: str | None = Field(
        None,
        description="a move of its own from where the arm was to this plan's start (no traced "
        "path): the plan it leads to",
    )
    robot: str
    requested_speed_m_s: float
    duration_s: float
    n_samples: int
    rate_hz: float
    path_length_m: float = Field(..., description="traced length (not the lifts between pieces)")
    n_pieces: int = Field(1, description="process runs: the arm lifts between the trace's pieces")
    tool_axis_from: str
    ik_branch: int
    min_limit_margin_rad: float
    min_wrist_singularity: float
    min_elbow_singularity: float
    min_shoulder_margin_m: float
    speed_drops: list[SpeedDropSummary] = Field(default_factory=list)
    T_scan_tracker: Matrix4 | None = Field(
        None, description="the scan's transform the tool axis was taken with (no new ICP)"
    )
    phase_durations_s: dict[str, float] = Field(
        default_factory=dict, description="seconds per phase: transit, approach, process, ..."
    )
    phase_max_tcp_speed_m_s: dict[str, float] = Field(
        default_factory=dict, description="the fastest TCP speed of each phase (m/s)"
    )
    start_q_rad: list[float] | None = Field(None, description="where the motion starts")
    goal_q_rad: list[float] | None = Field(
        None, description="a move to a plan's start: where it ends (that plan's first joints)"
    )
    start_from: str | None = Field(None, description="arm, home or given")
    configuration: str | None = Field(None, description="the IK configuration kept, in words")
    approach_m: float | None = None
    tcp_pose: list[float] | None = Field(None, description="x, y, z (m), rx, ry, rz: flange")
    payload_kg: float | None = None
    payload_cog_m: list[float] | None = None
    T_base_tracker: Matrix4 | None = None
    min_clearance_m: float | None = Field(
        None, description="closest approach of the arm and tool to the cell (null: not checked)"
    )
    checks: list[str] = Field(default_factory=list, description="the checks the plan passed")
    teachpath: str | None = Field(None, description="the version that planned it")
    report: list[str] = Field(default_factory=list)
    kinematics: str | None = Field(
        None, description="the kinematic model the joints were solved with, in words"
    )
    calibration: dict[str, Any] | None = Field(
        None,
        description="the arm's own kinematics calibration it was planned with (offsets to UR's "
        "DH parameters, as the controller's calibration.conf); null: UR's nominal model",
    )

    #: What a trajectory file's metadata line holds besides robot, rate and speed.
    FILE_KEYS: ClassVar[tuple[str, ...]] = (
        "teachpath",
        "duration_s",
        "phase_durations_s",
        "start_q_rad",
        "start_from",
        "configuration",
        "approach_m",
        "n_pieces",
        "tcp_pose",
        "payload_kg",
        "payload_cog_m",
        "T_base_tracker",
        "T_scan_tracker",
        "min_clearance_m",
        "checks",
        "kinematics",
    )

    def file_meta(self) -> dict[str, Any]:
        """The metadata line of the trajectory's CSV (see :mod:`drivers.export`)."""
        return {key: getattr(self, key) for key in self.FILE_KEYS}


class ExecutionSummary(_Summary):
    """One shape for every execution: a dry run on the simulated arm or a run on a real one.

    Numbers that could not be measured (nothing moved) are null, never NaN.
    """

    backend: Literal["sim", "ur_rtde"]
    dry_run: bool
    robot: str
    mode: Literal["servoj", "movepath"]
    tolerance_m: float
    completed: bool
    faults: list[str]
    n_samples: int
    duration_s: float | None = None
    planned_duration_s: float | None = None
    max_path_deviation_m: float | None = None
    max_lag_m: float | None = None
    max_joint_error_rad: float | None = None
    min_limit_margin_rad: float | None = None
    min_wrist_singularity: float | None = None
    min_elbow_singularity: float | None = None
    requested_speed_m_s: float | None = None
    mean_speed_m_s: float | None = None
    speed_drops: list[SpeedDropSummary] = Field(default_factory=list)
    phase_durations_s: dict[str, float] = Field(
        default_factory=dict, description="planned seconds per phase"
    )
    executed_phase_durations_s: dict[str, float] = Field(
        default_factory=dict, description="seconds recorded per phase (where it got to)"
    )
    max_deviation_by_phase_m: dict[str, float] = Field(
        default_factory=dict, description="largest distance from the planned TCP path, per phase"
    )
    stopped_in: str | None = Field(
        None, description="where a stopped or failed execution got to (a phase or a step)"
    )
    max_period_s: float | None = Field(
        None, description="servoJ on a real arm: the longest time between two samples sent"
    )
    period_overruns: int | None = Field(
        None, description="servoJ on a real arm: periods over 1.25 times the controller's"
    )
    realtime: str | None = Field(
        None, description="the streaming loop's scheduling (realtime priority, or why not)"
    )
    report: list[str] = Field(default_factory=list)


SUMMARY_MODELS: dict[str, type[_Summary]] = {
    "recording": RecordingSummary,
    "touches": TouchesSummary,
    "scan": ScanSummary,
    "reconstruction": ReconstructionSummary,
    "trajectory": TrajectorySummary,
    "execution": ExecutionSummary,
}


def summary_of(kind: str, summary: dict[str, Any]) -> _Summary:
    """The typed summary of a stored artifact (raises pydantic's ValidationError if it does not
    fit its kind's model)."""
    return SUMMARY_MODELS[kind].model_validate(summary)


AnySummary = Annotated[
    RecordingSummary
    | TouchesSummary
    | ScanSummary
    | ReconstructionSummary
    | TrajectorySummary
    | ExecutionSummary,
    Field(description="the summary of the artifact's kind"),
]


def check_stored(kind: str, arrays: Arrays, summary: dict[str, Any]) -> None:
    """Raise if ``arrays`` and ``summary`` are not what an artifact of ``kind`` holds (its
    summary model and its codec): for files that come from elsewhere (an imported bundle).

    Raises
    ------
    ValueError
        Including pydantic's ValidationError, and KeyError for a missing array (as ValueError).
    """
    typed = summary_of(kind, summary)
    try:
        if kind in ("recording", "touches"):
            RecordingCodec.decode(arrays)
        elif kind == "scan":
            ScanCodec.decode(arrays)
        elif kind == "reconstruction":
            ReconstructionCodec.decode(arrays)
        elif kind == "trajectory":
            assert isinstance(typed, TrajectorySummary)  # SUMMARY_MODELS["trajectory"]
            TrajectoryCodec.decode(arrays, typed)
        elif kind == "execution":
            ExecutionCodec.decode(arrays)
        else:
            raise ValueError(f"unknown artifact kind {kind!r}")
    except KeyError as exc:
        raise ValueError(f"the arrays lack {exc}") from None
