"""Request and response bodies of the REST API."""

from __future__ import annotations

import math
import types
from collections.abc import Iterable
from datetime import datetime
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictBool,
    StrictInt,
    StringConstraints,
    field_validator,
    model_validator,
)

from recon.params import Spec, default_of, specs, type_hints
from recon.plan_params import PlanParams, check_tool_spheres
from recon.recon_params import ReconParams
from service.artifacts import (
    ExecutionSummary,
    ReconstructionSummary,
    RecordingSummary,
    ScanSummary,
    TouchesSummary,
    TrajectorySummary,
)

if TYPE_CHECKING:
    from pydantic.fields import FieldInfo

    from drivers.tracking.natnet_source import NatNetConfig
    from drivers.tracking.replay import ReplayConfig

Matrix4 = list[list[float]]


def _iso(value: object) -> object:
    """ISO 8601 in UTC (SQLite returns naive datetimes: they were stored as UTC)."""
    if isinstance(value, datetime):
        from service.store import iso

        return iso(value)
    return value


#: A moment as ISO 8601 text, read from a row's datetime.
Timestamp = Annotated[str | None, BeforeValidator(_iso)]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _check_matrix(value: Matrix4 | None) -> Matrix4 | None:
    if value is None:
        return None
    if len(value) != 4 or any(len(row) != 4 for row in value):
        raise ValueError("must be a 4x4 matrix (a list of 4 rows of 4 numbers)")
    if not all(math.isfinite(v) for row in value for v in row):
        raise ValueError("must hold finite numbers")
    from recon.transforms import check_cell_transform

    check_cell_transform(value, name="the matrix")
    return value


class ErrorBody(BaseModel):
    code: str
    message: str
    detail: Any = None


class Health(BaseModel):
    status: Literal["ok", "degraded"] = Field(
        ...,
        description="degraded: a worker process died and its pool is being replaced, or the "
        "storage failed lately (see problems)",
    )
    version: str
    versions: dict[str, str]
    robot_backends: dict[str, str]
    jobs_running: int | None = Field(None, description="null while the database cannot be read")
    problems: list[str] = Field(
        default_factory=list,
        description="what degrades the service now: worker_pool_replaced, storage_full, "
        "database_busy",
    )


class SessionCreate(Strict):
    name: str = Field("session", min_length=1, max_length=200)


class CalibrationIn(Strict):
    """Calibrations to set; fields left out keep their value, an explicit null clears one."""

    T_base_tracker: Matrix4 | None = Field(None, description="4x4, metres: tracker -> robot base")
    T_scan_tracker: Matrix4 | None = Field(
        None, description="4x4, metres: tracker -> scan (initial guess for registration)"
    )
    tip_offset_m: tuple[float, float, float] | None = Field(
        None, description="the pen's tip in its rigid body's frame, metres"
    )

    _matrix = field_validator("T_base_tracker", "T_scan_tracker")(_check_matrix)

    @field_validator("tip_offset_m")
    @classmethod
    def _tip(cls, value: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        from recon.calibrate import MAX_TIP_OFFSET_M

        if value is None:
            return value
        if not all(math.isfinite(v) for v in value) or math.hypot(*value) > MAX_TIP_OFFSET_M:
            raise ValueError(
                f"tip_offset_m must be finite and within {MAX_TIP_OFFSET_M * 1e3:.0f} mm of the "
                "rigid body (a pen's tip); is it in metres?"
            )
        return value

    @model_validator(mode="after")
    def _something(self) -> CalibrationIn:
        if not self.model_fields_set:
            raise ValueError("name at least one of T_base_tracker, T_scan_tracker, tip_offset_m")
        return self


class PointPair(Strict):
    base: tuple[float, float, float] = Field(..., description="the point in the base frame")
    tracker: tuple[float, float, float] = Field(..., description="the point in the tracker frame")

    @field_validator("base", "tracker")
    @classmethod
    def _finite(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(math.isfinite(v) for v in value):
            raise ValueError("coordinates must be finite numbers")
        return value


class BaseCalibrationIn(Strict):
    # Touching points by hand: tens at most; the fit's outlier search grows with N^3.
    pairs: list[PointPair] = Field(..., min_length=3, max_length=100)
    units: Literal["m", "mm"] = "m"
    tolerance_m: float = Field(1e-3, gt=0, le=0.1)
    accept_poor_fit: StrictBool = Field(
        False,
        description="store the fit even when the pairs disagree by more than the tolerance "
        "(default: refused with 422 poor_fit and the figures)",
    )


class FromRow(BaseModel):
    """A response model read off a database row's attributes."""

    model_config = ConfigDict(from_attributes=True)


class SessionOut(FromRow):
    id: str
    name: str
    created_at: Timestamp
    recording_id: str | None
    scan_id: str | None
    T_base_tracker: Matrix4 | None
    T_scan_tracker: Matrix4 | None = None
    tip_offset_m: list[float] | None = None
    calibration_report: dict[str, Any] | None = None


class BundleImportOut(BaseModel):
    session: SessionOut
    created: bool = Field(description="false: the same session was here already, unchanged")
    n_artifacts: int
    n_files: int = Field(description="files unpacked (0 when nothing changed)")
    n_bytes: int


class CalibrationResult(BaseModel):
    session: SessionOut
    result: dict[str, Any]


class _ArtifactOut(FromRow):
    id: str
    session_id: str
    created_at: Timestamp
    inputs: dict[str, Any]
    params: dict[str, Any]
    sha256: str
    size: int
    source_name: str | None


class RecordingOut(_ArtifactOut):
    kind: Literal["recording"]
    summary: RecordingSummary


class TouchesOut(_ArtifactOut):
    kind: Literal["touches"]
    summary: TouchesSummary


class ScanOut(_ArtifactOut):
    kind: Literal["scan"]
    summary: ScanSummary


_OUTDATED: Any = Field(
    default_factory=list,
    description="what changed in the session since it was made (a new trace, scan, touches or "
    "calibration), in words; empty: made from the session's current inputs",
)


class ReconstructionOut(_ArtifactOut):
    kind: Literal["reconstruction"]
    summary: ReconstructionSummary
    outdated: list[str] = _OUTDATED


class TrajectoryOut(_ArtifactOut):
    kind: Literal["trajectory"]
    summary: TrajectorySummary
    outdated: list[str] = _OUTDATED


class ExecutionOut(_ArtifactOut):
    kind: Literal["execution"]
    summary: ExecutionSummary


#: Any artifact, told apart by its ``kind``.
ArtifactOut = Annotated[
    RecordingOut | TouchesOut | ScanOut | ReconstructionOut | TrajectoryOut | ExecutionOut,
    Field(discriminator="kind"),
]


class JobOut(FromRow):
    id: str
    session_id: str
    kind: str
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    progress: float
    created_at: Timestamp
    started_at: Timestamp
    finished_at: Timestamp
    params: dict[str, Any]
    result: dict[str, Any] | None
    error: dict[str, Any] | None


#: The core's reconstruction parameters a request may set (the others keep their defaults).
RECONSTRUCTION_PARAMS = (
    "radius_m",
    "alpha",
    "beta",
    "degree",
    "method",
    "spacing_m",
    "uncertainty_tolerance_m",
)
#: The core's planning parameters a request may set.
TRAJECTORY_PARAMS = (
    "robot",
    "speed_m_s",
    "orientation",
    "lead_deg",
    "tilt_deg",
    "heading",
    "smooth_m",
    "tcp_offset_m",
    "tcp_pose",
    "start_q_rad",
    "shoulder",
    "elbow",
    "wrist",
    "approach_m",
    "approach_speed_m_s",
    "transit_speed_scale",
    "transit_acceleration_scale",
    "transit_tcp_speed_m_s",
    "return_to_start",
    "payload_kg",
    "payload_cog_m",
    "tool_radius_m",
    "tool_spheres_m",
    "clearance_m",
    "joint_margin_deg",
    "mount_up",
)


#: Most demonstrations a reconstruction fuses.
MAX_DEMONSTRATIONS = 10


class _ReconstructionRequest(Strict):
    """What to reconstruct, and how; the numbers' defaults and bounds are the core's."""

    recording_id: str | None = Field(None, description="default: the session's recording")
    recording_ids: list[Annotated[str, StringConstraints(max_length=32)]] | None = Field(
        None,
        max_length=MAX_DEMONSTRATIONS,
        description="several demonstrations of one path, fused before reconstructing (an "
        "outlier is left out and named); overrides recording_id",
    )
    scan_id: str | None = Field(None, description="default: the session's scan")
    use_scan: bool = Field(True, description="false: path-only reconstruction")
    touches_id: str | None = Field(
        None,
        description="touches registering the scanner; default: the session's newest (not with "
        "registration false, where the frames are trusted as given)",
    )
    use_touches: bool = Field(
        True, description="false: register the scanner from the trace even with touches"
    )
    registration: bool = Field(
        default_of(ReconParams, "register"),
        description="register the path to the scan (ICP); false trusts the frames as given",
    )
    T_scan_tracker: Matrix4 | None = Field(
        None,
        description="initial guess for registration (or the transform used without it); "
        "default: the session's",
    )

    _matrix = field_validator("T_scan_tracker")(_check_matrix)

    def recon_params(self) -> dict[str, Any]:
        """The core's parameters (:class:`recon.recon_params.ReconParams`), checked by the core."""
        params = {name: getattr(self, name) for name in RECONSTRUCTION_PARAMS}
        params["register"] = self.registration
        ReconParams(**params)
        return params


class _TrajectoryRequest(Strict):
    """What to plan; the numbers' defaults and bounds are the core's."""

    reconstruction_id: str
    T_base_tracker: Matrix4 | None = Field(None, description="default: the session's")

    _matrix = field_validator("T_base_tracker")(_check_matrix)

    @field_validator("tool_spheres_m", check_fields=False)
    @classmethod
    def _tool_spheres(cls, value: tuple[float, ...]) -> tuple[float, ...]:
        # Before any lookup: a malformed tool is the request's fault whatever it names.
        check_tool_spheres(tuple(value))
        return value

    def plan_params(self) -> dict[str, Any]:
        """The core's parameters (:class:`recon.plan_params.PlanParams`), checked by the core."""
        return self.plan_params_with({name: getattr(self, name) for name in TRAJECTORY_PARAMS})

    @staticmethod
    def plan_params_with(params: dict[str, Any]) -> dict[str, Any]:
        """``params`` checked by the core (:class:`recon.plan_params.PlanParams`)."""
        PlanParams(**params)
        return params


class ExecutionCreate(Strict):
    trajectory_id: str
    backend: Literal["sim", "ur_rtde"] = "sim"
    mode: Literal["servoj", "movepath"] = Field(
        "servoj",
        description="servoj streams every controller sample; movepath sends coarse blended "
        "waypoints the controller runs itself (a real arm needs a dry run in the same mode)",
    )
    tolerance_m: float = Field(
        5e-4, gt=0, le=0.01, description="movepath: largest TCP deviation from the plan"
    )
    confirm: StrictBool = Field(
        False, description="must be the JSON boolean true to move a real arm"
    )
    approved_sha256: str | None = Field(
        None,
        pattern="^[0-9a-f]{64}$",
        description="the trajectory file's sha256 as the operator approved it (the pendant's "
        "confirmation shows it): a real-arm run is refused (409 approval_mismatch) unless the "
        "stored file is that one; kept in the run's record",
    )
    accept_outdated: StrictBool = Field(
        False,
        description="run a plan made from inputs that are no longer the session's current ones "
        "(its `outdated` list); the run's record keeps what was accepted. Without it such a plan "
        "is refused on a real arm (409 outdated_inputs)",
    )


class ReplaySource(Strict):
    kind: Literal["replay"] = "replay"
    recording_id: str
    speed: float | None = Field(
        1.0, gt=0, le=100.0, description="times real time; null: as fast as possible"
    )

    def source_config(self) -> ReplayConfig:
        """The replay source's configuration (the recording is handed over separately)."""
        from drivers.tracking.replay import ReplayConfig

        return ReplayConfig(speed=self.speed)


class NatNetSourceIn(Strict):
    kind: Literal["natnet"]
    server: str = Field(..., min_length=1, max_length=255, description="Motive's address")
    rigid_body: str = Field(..., min_length=1, max_length=200, description="the pen in Motive")
    local: str = Field(
        "127.0.0.1",
        max_length=15,
        description="this machine's address on Motive's network: one of its interfaces "
        "(loopback included), not the wildcard 0.0.0.0",
    )
    multicast: bool = False
    command_port: int = Field(1510, ge=1, le=65535)
    data_port: int = Field(1511, ge=1, le=65535)
    units: Literal["m", "mm"] = "m"
    timeout_s: float = Field(5.0, gt=0, le=60)

    @field_validator("local")
    @classmethod
    def _local(cls, value: str) -> str:
        from drivers.tracking.natnet_source import check_interface_address

        return check_interface_address(value)

    @field_validator("server")
    @classmethod
    def _server(cls, value: str) -> str:
        from drivers.tracking.natnet_source import check_server_address

        return check_server_address(value)

    def source_config(self) -> NatNetConfig:
        """The NatNet source's configuration: a capture waits for the operator as long as it
        takes (no stall timeout)."""
        from drivers.tracking.natnet_source import NatNetConfig

        return NatNetConfig(**self.model_dump(), stall_timeout_s=None)


class CaptureCreate(Strict):
    source: ReplaySource | NatNetSourceIn = Field(..., discriminator="kind")

    @field_validator("source", mode="before")
    @classmethod
    def _replay_by_default(cls, value: object) -> object:
        # Before live sources existed, a source was always a replay and named no kind.
        if isinstance(value, dict) and "kind" not in value:
            return {**value, "kind": "replay"}
        return value


class PairingIn(Strict):
    """A pairing code typed on a second screen."""

    code: str = Field(
        ...,
        pattern=r"^[0-9]{6}$",
        description="the six digits the server printed, or a signed-in pendant shows",
    )


class PairingOut(BaseModel):
    """The access token, for the screen that gave the right code."""

    token: str


class PairingCodeOut(BaseModel):
    """A new pairing code (the previous one is void)."""

    code: str = Field(..., description="six digits, good for one sign-in")
    expires_in_s: float = Field(..., description="seconds it is good for")


class SpeedIn(Strict):
    """A run's speed override."""

    fraction: float = Field(
        ...,
        ge=0.05,
        le=1.0,
        allow_inf_nan=False,
        description="of the planned speed, 0.05 .. 1 (the pendant shows per cent); the arm "
        "ramps to it within its acceleration limits and never runs faster than planned",
    )


class ResumeIn(Strict):
    """Going on after a pause: the operator approves the run again."""

    confirm: StrictBool = Field(..., description="must be the JSON boolean true")
    approved_sha256: str = Field(
        ...,
        pattern="^[0-9a-f]{64}$",
        description="the running trajectory's sha256, as the resume confirmation shows it",
    )


class RunSpeedOut(BaseModel):
    """A running execution's speed override and pause."""

    execution_id: str
    trajectory_id: str | None = Field(None, description="the trajectory it runs")
    approved_sha256: str | None = Field(
        None, description="its file's sha256 as approved (a resume is approved against it)"
    )
    overridable: bool = Field(
        ..., description="a servoJ run (a movePath is timed by the controller: no override)"
    )
    speed_fraction: float = Field(..., description="the speed set, of the planned speed")
    paused: bool = Field(..., description="a pause was asked (the arm holds on its path)")
    speed_now: float = Field(
        ..., description="the fraction the stream runs at now (0: at rest, paused)"
    )
    moving: bool = Field(..., description="the run is in its motion (not connecting)")


class StopOut(JobOut):
    """The execution's job after the stop request."""

    already_ended: bool = Field(
        ..., description="the execution had ended before the stop (nothing was stopped)"
    )


class RobotOut(BaseModel):
    """The arm now: what the operator's safety bar shows."""

    backend: Literal["sim", "ur_rtde"]
    real_arm: bool
    robot: str
    host: str | None
    reachable: bool
    robot_mode: str
    safety_status: str
    protective_stop: bool
    emergency_stop: bool
    remote_control: bool | None
    program_running: bool
    q_rad: list[float] | None
    joints_m: list[list[float]] | None = Field(
        None,
        description="where the joints are (base frame, m): base, DH frames 1-6 (6: the "
        "flange) from the joints read, and the TCP the controller reports; (8, 3)",
    )
    tcp_pose: list[float] | None = Field(None, description="x, y, z (m), rx, ry, rz; base")
    payload_kg: float | None = Field(
        None,
        description="the controller's active payload (what a plan that sets none runs with)",
    )
    payload_cog_m: list[float] | None = Field(None, description="its centre of gravity, flange")
    error: str | None
    age_s: float | None = Field(None, description="how old the reading is")
    unlock_in_s: float | None = Field(
        None, description="in a protective stop: seconds until the controller allows unlocking"
    )
    owner_execution_id: str | None = Field(None, description="the execution that owns the arm")
    run_speed: RunSpeedOut | None = Field(
        None, description="the owning execution's speed override and pause"
    )
    max_speed_m_s: float = Field(..., description="the server's TCP speed cap on a real arm")
    mount_up: list[float] = Field(
        ..., description="how the arm is mounted: up in its base frame (plans default to it)"
    )


class CellOut(BaseModel):
    """The cell this server plans and runs in: its start-up settings or the edited cell."""

    robot: str
    keep_out_boxes_m: list[list[float]] = Field(
        ..., description="boxes, base frame: x_min, y_min, z_min, x_max, y_max, z_max (m)"
    )
    cell_planes: list[list[float]] = Field(
        ..., description="planes besides the mounting one, base frame: nx, ny, nz, d (n . p >= d)"
    )
    revision: int = Field(
        ...,
        description="changes stored so far (0: never edited); an edit "
        "names the revision it was made from",
    )
    source: str = Field(..., description="the start-up settings, or when it was edited")
    editable: bool = Field(..., description="false while a real-arm execution runs")
    mount_up: list[float]
    arm_kinematics: str = Field(..., description="calibrated from the controller, or nominal")


class CellIn(Strict):
    """This arm's keep-out boxes and planes, as the operator set them."""

    keep_out_boxes_m: list[Any] = Field(
        ...,
        max_length=64,
        description="boxes, base frame: x_min, y_min, z_min, x_max, y_max, z_max (m); at most 32",
    )
    cell_planes: list[Any] = Field(
        ...,
        max_length=64,
        description="planes besides the mounting one, base frame: nx, ny, nz, d (m); the arm "
        "keeps to n . p >= d; at most 16",
    )
    revision: StrictInt = Field(
        ...,
        ge=0,
        le=2**31 - 1,
        description="the revision of the cell this edit was made from (GET /cell)",
    )

    @model_validator(mode="after")
    def _checkable(self) -> CellIn:
        from service.cell import check_shapes

        boxes, planes = check_shapes(self.keep_out_boxes_m, self.cell_planes)
        self.keep_out_boxes_m, self.cell_planes = (
            [list(b) for b in boxes],
            [list(p) for p in planes],
        )
        return self


class CaptureOut(FromRow):
    id: str
    session_id: str
    source: dict[str, Any]
    state: str
    created_at: Timestamp
    n_samples: int
    recording_id: str | None
    error: str | None


# -- request fields generated from the core's parameter declarations (recon.params) ---------------


def _bounded(hint: Any, spec: Spec) -> Any:
    """``hint`` with the spec's bounds on its numbers (inside a union or a tuple too).

    ``hint`` and the result are type expressions read and built at run time (``Annotated``,
    unions, tuples) for pydantic: no static type describes one, hence ``Any``.
    """
    import typing

    if hint in (int, float):
        return Annotated[
            hint,
            Field(ge=spec.ge, gt=spec.gt, le=spec.le, lt=spec.lt, allow_inf_nan=False)
            if hint is float
            else Field(ge=spec.ge, gt=spec.gt, le=spec.le, lt=spec.lt),
        ]
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is tuple:
        return types.GenericAlias(tuple, tuple(_bounded(a, spec) for a in args))
    if args and origin not in (typing.Literal,):
        return typing.Union[tuple(_bounded(a, spec) for a in args)]  # noqa: UP007
    return hint


def param_fields(cls: type[object], names: Iterable[str]) -> dict[str, tuple[Any, FieldInfo]]:
    """Pydantic field definitions for the named parameters of a core dataclass: its type with
    its bounds, its default, and its help, unit and bounds as the description."""
    declared, hints = specs(cls), type_hints(cls)
    fields: dict[str, tuple[Any, FieldInfo]] = {}
    for name in names:
        spec = declared[name]
        bounds = spec.describe()
        unit = f" ({spec.unit})" if spec.unit and not bounds else ""
        description = spec.help + unit + (f"; {bounds}" if bounds else "")
        fields[name] = (
            _bounded(hints[name], spec),
            Field(default_of(cls, name), description=description),
        )
    return fields


def _request_model(
    name: str,
    base: type[BaseModel],
    cls: type[object],
    names: Iterable[str],
    *,
    required: Iterable[str] = (),
) -> type[BaseModel]:
    from pydantic import create_model

    fields = param_fields(cls, names)
    for field_name in required:
        annotation, info = fields[field_name]
        fields[field_name] = (annotation, Field(..., description=info.description))
    # As keywords from a dict, mypy checks each value against every keyword create_model takes
    # (__config__, __module__, ...), not only the field definitions they all are.
    definitions: dict[str, Any] = fields
    return create_model(name, __base__=base, __doc__=base.__doc__, **definitions)


# The two request models with the core's parameters. At run time they are made from the core's
# declarations (types, defaults, bounds, help: one place, recon.params); what a type checker and
# a reader see is declared here, field by field, and tests/service/test_request_models.py
# checks that the two agree (names, types, defaults, which are required).
if TYPE_CHECKING:

    class ReconstructionCreate(_ReconstructionRequest):
        """What to reconstruct, and how; the numbers' defaults and bounds are the core's."""

        radius_m: float = default_of(ReconParams, "radius_m")
        alpha: float | Literal["auto"] = default_of(ReconParams, "alpha")
        beta: float = default_of(ReconParams, "beta")
        degree: int = default_of(ReconParams, "degree")
        method: Literal["paper", "anchored"] = default_of(ReconParams, "method")
        spacing_m: float = default_of(ReconParams, "spacing_m")
        uncertainty_tolerance_m: float = default_of(ReconParams, "uncertainty_tolerance_m")

    class TrajectoryCreate(_TrajectoryRequest):
        """What to plan; the numbers' defaults and bounds are the core's."""

        robot: str = default_of(PlanParams, "robot")
        speed_m_s: float
        orientation: Literal["auto", "scan", "pen", "fixed"] = default_of(PlanParams, "orientation")
        lead_deg: float = default_of(PlanParams, "lead_deg")
        tilt_deg: float = default_of(PlanParams, "tilt_deg")
        heading: Literal["travel", "free"] = default_of(PlanParams, "heading")
        smooth_m: float = default_of(PlanParams, "smooth_m")
        tcp_offset_m: tuple[float, float, float] = default_of(PlanParams, "tcp_offset_m")
        tcp_pose: tuple[float, float, float, float, float, float] = default_of(
            PlanParams, "tcp_pose"
        )
        start_q_rad: tuple[float, float, float, float, float, float] | None = default_of(
            PlanParams, "start_q_rad"
        )
        shoulder: Literal["any", "left", "right"] = default_of(PlanParams, "shoulder")
        elbow: Literal["up", "down", "any"] = default_of(PlanParams, "elbow")
        wrist: Literal["any", "flip", "noflip"] = default_of(PlanParams, "wrist")
        approach_m: float = default_of(PlanParams, "approach_m")
        approach_speed_m_s: float = default_of(PlanParams, "approach_speed_m_s")
        transit_speed_scale: float = default_of(PlanParams, "transit_speed_scale")
        transit_acceleration_scale: float = default_of(PlanParams, "transit_acceleration_scale")
        transit_tcp_speed_m_s: float = default_of(PlanParams, "transit_tcp_speed_m_s")
        return_to_start: bool = default_of(PlanParams, "return_to_start")
        payload_kg: float | None = default_of(PlanParams, "payload_kg")
        payload_cog_m: tuple[float, float, float] = default_of(PlanParams, "payload_cog_m")
        tool_radius_m: float = default_of(PlanParams, "tool_radius_m")
        tool_spheres_m: tuple[float, ...] = default_of(PlanParams, "tool_spheres_m")
        clearance_m: float = default_of(PlanParams, "clearance_m")
        joint_margin_deg: float = default_of(PlanParams, "joint_margin_deg")
        mount_up: tuple[float, float, float] = default_of(PlanParams, "mount_up")

else:
    ReconstructionCreate = _request_model(
        "ReconstructionCreate", _ReconstructionRequest, ReconParams, RECONSTRUCTION_PARAMS
    )
    TrajectoryCreate = _request_model(
        "TrajectoryCreate",
        _TrajectoryRequest,
        PlanParams,
        TRAJECTORY_PARAMS,
        required=("speed_m_s",),
    )
