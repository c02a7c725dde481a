"""Request and response bodies of the REST API."""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

Matrix4 = list[list[float]]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _check_matrix(value: Matrix4 | None) -> Matrix4 | None:
    if value is None:
        return None
    if len(value) != 4 or any(len(row) != 4 for row in value):
        raise ValueError("must be a 4x4 matrix (a list of 4 rows of 4 numbers)")
    if not all(math.isfinite(v) for row in value for v in row):
        raise ValueError("must hold finite numbers")
    from recon.transforms import check_rigid

    check_rigid(value, name="the matrix")
    return value


class ErrorBody(BaseModel):
    code: str
    message: str
    detail: Any = None


class Health(BaseModel):
    status: Literal["ok"]
    version: str
    versions: dict[str, str]
    robot_backends: dict[str, str]
    jobs_running: int


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
    def _tip(cls, value):
        if value is not None and not all(math.isfinite(v) and abs(v) <= 1.0 for v in value):
            raise ValueError("tip_offset_m must be finite and within 1 m of the rigid body")
        return value

    @model_validator(mode="after")
    def _something(self):
        if not self.model_fields_set:
            raise ValueError("name at least one of T_base_tracker, T_scan_tracker, tip_offset_m")
        return self


class PointPair(Strict):
    base: tuple[float, float, float] = Field(..., description="the point in the base frame")
    tracker: tuple[float, float, float] = Field(..., description="the point in the tracker frame")

    @field_validator("base", "tracker")
    @classmethod
    def _finite(cls, value):
        if not all(math.isfinite(v) for v in value):
            raise ValueError("coordinates must be finite numbers")
        return value


class BaseCalibrationIn(Strict):
    # Touching points by hand: tens at most; the fit's outlier search grows with N^3.
    pairs: list[PointPair] = Field(..., min_length=3, max_length=100)
    units: Literal["m", "mm"] = "m"
    tolerance_m: float = Field(1e-3, gt=0, le=0.1)


class SessionOut(BaseModel):
    id: str
    name: str
    created_at: str
    recording_id: str | None
    scan_id: str | None
    T_base_tracker: Matrix4 | None
    T_scan_tracker: Matrix4 | None = None
    tip_offset_m: list[float] | None = None
    calibration_report: dict[str, Any] | None = None


class CalibrationResult(BaseModel):
    session: SessionOut
    result: dict[str, Any]


class ArtifactOut(BaseModel):
    id: str
    session_id: str
    kind: str
    created_at: str
    inputs: dict[str, Any]
    params: dict[str, Any]
    summary: dict[str, Any]
    sha256: str
    size: int
    source_name: str | None


class JobOut(BaseModel):
    id: str
    session_id: str
    kind: str
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    progress: float
    created_at: str | None
    started_at: str | None
    finished_at: str | None
    params: dict[str, Any]
    result: dict[str, Any] | None
    error: dict[str, Any] | None


class ReconstructionCreate(Strict):
    recording_id: str | None = Field(None, description="default: the session's recording")
    scan_id: str | None = Field(None, description="default: the session's scan")
    use_scan: bool = Field(True, description="false: path-only reconstruction")
    radius_m: float = Field(0.008, gt=0, le=0.2)
    alpha: float | Literal["auto"] = "auto"
    beta: float = Field(1.0, ge=0, le=1)
    degree: int = Field(2, ge=1, le=5)
    method: Literal["paper", "anchored"] = "anchored"
    spacing_m: float = Field(0.001, gt=0, le=0.01)
    registration: bool = Field(
        True, description="register the path to the scan (ICP); false trusts the frames as given"
    )
    T_scan_tracker: Matrix4 | None = Field(
        None,
        description="initial guess for registration (or the transform used without it); "
        "default: the session's",
    )

    _matrix = field_validator("T_scan_tracker")(_check_matrix)

    @field_validator("alpha")
    @classmethod
    def _alpha(cls, value):
        if value != "auto" and not (0.0 <= value <= 1.0):
            raise ValueError("alpha must be in [0, 1] or 'auto'")
        return value


class TrajectoryCreate(Strict):
    reconstruction_id: str
    robot: str = Field("ur5e", description="UR model")
    speed_m_s: float = Field(..., gt=0, le=2.0)
    orientation: Literal["auto", "scan", "pen", "fixed"] = "auto"
    lead_deg: float = Field(0.0, ge=-60, le=60)
    tilt_deg: float = Field(0.0, ge=-60, le=60)
    smooth_m: float = Field(0.01, ge=0, le=0.1)
    tcp_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    T_base_tracker: Matrix4 | None = Field(None, description="default: the session's")

    _matrix = field_validator("T_base_tracker")(_check_matrix)

    @field_validator("tcp_offset_m")
    @classmethod
    def _offset(cls, value):
        if not all(math.isfinite(v) and abs(v) <= 1.0 for v in value):
            raise ValueError("tcp_offset_m must be finite and within 1 m")
        return value


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
    confirm: bool = Field(False, description="must be true to move a real arm")


class ReplaySource(Strict):
    kind: Literal["replay"] = "replay"
    recording_id: str
    speed: float | None = Field(
        1.0, gt=0, le=100.0, description="times real time; null: as fast as possible"
    )


class NatNetSourceIn(Strict):
    kind: Literal["natnet"]
    server: str = Field(..., min_length=1, max_length=255, description="Motive's address")
    rigid_body: str = Field(..., min_length=1, max_length=200, description="the pen in Motive")
    local: str = Field("127.0.0.1", description="this machine's address on Motive's network")
    multicast: bool = False
    command_port: int = Field(1510, ge=1, le=65535)
    data_port: int = Field(1511, ge=1, le=65535)
    units: Literal["m", "mm"] = "m"
    timeout_s: float = Field(5.0, gt=0, le=60)


class CaptureCreate(Strict):
    source: ReplaySource | NatNetSourceIn = Field(..., discriminator="kind")

    @field_validator("source", mode="before")
    @classmethod
    def _replay_by_default(cls, value):
        # Before live sources existed, a source was always a replay and named no kind.
        if isinstance(value, dict) and "kind" not in value:
            return {**value, "kind": "replay"}
        return value


class CaptureOut(BaseModel):
    id: str
    session_id: str
    source: dict[str, Any]
    state: str
    created_at: str
    n_samples: int
    recording_id: str | None
    error: str | None
