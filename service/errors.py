"""Error responses: one JSON shape, one status and stable code per error class.

Every 4xx/5xx body is ``{"code": ..., "message": ..., "detail": ...}``. Routers raise domain
errors (``recon.errors``, ``drivers.errors``) or :class:`ApiError` and never catch them; this
module turns them into responses. Unexpected exceptions become a 500 with no traceback (it is
logged on the server).
"""

from __future__ import annotations

import errno
import logging
from collections.abc import Iterable, Mapping
from typing import Any, TypedDict

import sqlalchemy.exc
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from drivers import errors as driver_errors
from recon import errors as recon_errors
from service import bundles
from service.store import RecentFaults, RowGoneError, SessionDeletedError, StorageError

#: A 422 lists at most this many problems (a document with 20,000 unknown keys has as many).
MAX_LISTED_PROBLEMS = 20
#: A storage fault (a full disk, a busy database) is answered 503 with this Retry-After (s),
#: and keeps ``/health`` degraded for :data:`STORAGE_FAULT_WINDOW_S` after it was last seen.
STORAGE_RETRY_AFTER_S = 10
STORAGE_FAULT_WINDOW_S = 30.0
log = logging.getLogger("teachpath.service")


def storage_fault(error: BaseException) -> tuple[str, str] | None:
    """``(code, message)`` when ``error`` is the server's storage failing for a while (a full
    disk, a locked database) rather than anything the request did; None otherwise."""
    if isinstance(error, OSError) and error.errno in (errno.ENOSPC, errno.EDQUOT):
        return (
            "storage_full",
            "the server's disk is full: nothing was stored; free space in the data folder and "
            f"retry (in {STORAGE_RETRY_AFTER_S} s)",
        )
    if isinstance(error, sqlalchemy.exc.OperationalError):
        text = str(getattr(error, "orig", error)).lower()
        if "locked" in text or "busy" in text or "could not obtain lock" in text:
            return (
                "database_busy",
                "the database is busy (another process holds it): nothing was changed; retry "
                f"in {STORAGE_RETRY_AFTER_S} s",
            )
    return None


def note_storage_fault(faults: RecentFaults, error: BaseException) -> None:
    """Record in ``faults`` (the store's, for /health) that ``error`` was a storage fault, if it
    was one."""
    fault = storage_fault(error)
    if fault is not None:
        faults.note(fault[0])


class ApiError(Exception):
    """An error of the API itself (not found, conflict, refused), with its status and code.

    ``headers`` go on the response (``Retry-After`` on a 503).
    """

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        detail: dict[str, Any] | None = None,
        headers: Mapping[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.status, self.code, self.message, self.detail = status, code, message, detail
        self.headers = dict(headers or {})


class ErrorJson(TypedDict):
    """Every error response's body (and a failed job's ``error``)."""

    code: str
    message: str
    #: What the client may show beside the message (figures, ids, the problems of a 422).
    detail: Any


def not_found(what: str, ident: str) -> ApiError:
    return ApiError(404, "not_found", f"no {what} {ident!r}")


# Why the real arm was refused: one exception class per reason, each mapped to 409 and a stable
# code in ERROR_MAP below. Raised by the gate (service.gate) and by the arm's watch
# (service.robot: a state that cannot be read); here, where both can import them without
# importing each other.


class RealArmRefused(Exception):
    """The configured arm may not run this trajectory now (the message says what to do).

    ``detail`` carries what the operator's page shows beside the message (distances, ids).
    """

    def __init__(self, message: str, *, detail: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.detail = detail


class NoRobotConfigured(RealArmRefused):
    """No real arm is configured on this server."""


class TrajectoryForAnotherRobot(RealArmRefused):
    """The trajectory was planned for another UR model than the configured arm."""


class ConfirmationRequired(RealArmRefused):
    """The request did not say ``"confirm": true``."""


class SpeedCapExceeded(RealArmRefused):
    """The trajectory's speed is above the server's cap for a real arm."""


class ApprovalMismatch(RealArmRefused):
    """The trajectory file is not the one the operator approved (its checksum differs)."""


class OutdatedInputs(RealArmRefused):
    """The plan was made from inputs that are no longer the session's current ones (a new
    trace, scan, touches or calibration since), and the request did not pick it explicitly."""


class DryRunRequired(RealArmRefused):
    """No passed dry run of this trajectory in this mode (and tolerance) is on record."""


class UnreadableTrajectory(RealArmRefused):
    """The trajectory's summary cannot be read: what it was planned for is unknown."""


class ArmBusy(RealArmRefused):
    """Another execution owns the arm (one real-arm execution at a time)."""


class RobotUnavailable(RealArmRefused):
    """The arm's state cannot be read now: nothing is decided on a state that is not known."""


class ArmInProtectiveStop(RealArmRefused):
    """The arm is in a protective stop: inspect its cause and unlock it first."""


class ArmInEmergencyStop(RealArmRefused):
    """An emergency stop is engaged."""


class ArmNotRunning(RealArmRefused):
    """The arm is not powered on with its brakes released (UR's robot mode is not RUNNING): after
    an emergency stop it is powered off, and no motion can be sent."""


class RemoteControlOff(RealArmRefused):
    """The arm is in local control: the pendant must hand it over (remote control) first."""


class StartMoved(RealArmRefused):
    """The arm is not where the trajectory starts (it was moved since the plan)."""


class SamplesOutsideLimits(RealArmRefused):
    """The samples to be sent break a limit of this arm or this server (joint range, speed,
    acceleration, rest at the ends, the TCP speed cap)."""


class CollidesHere(RealArmRefused):
    """The samples, checked here against this cell, collide or come closer than the margin."""


class CellUnknown(RealArmRefused):
    """What the motion must be checked against cannot be put together (the scan it was planned
    along is missing or cannot be placed): a check that cannot decide refuses."""


#: Domain error class -> (HTTP status, code). Subclasses before their bases.
ERROR_MAP: list[tuple[type[Exception], int, str]] = [
    # Why the real arm was refused: one class per reason (above, raised by the gate).
    (NoRobotConfigured, 409, "no_robot"),
    (TrajectoryForAnotherRobot, 409, "trajectory_mismatch"),
    (ConfirmationRequired, 409, "confirmation_required"),
    (SpeedCapExceeded, 409, "speed_cap"),
    (ApprovalMismatch, 409, "approval_mismatch"),
    (OutdatedInputs, 409, "outdated_inputs"),
    (DryRunRequired, 409, "dry_run_required"),
    (UnreadableTrajectory, 409, "trajectory_unreadable"),
    (ArmBusy, 409, "arm_busy"),
    (RobotUnavailable, 409, "robot_unavailable"),
    (ArmInProtectiveStop, 409, "protective_stop"),
    (ArmInEmergencyStop, 409, "emergency_stop"),
    (ArmNotRunning, 409, "arm_not_running"),
    (RemoteControlOff, 409, "remote_control_off"),
    (StartMoved, 409, "start_moved"),
    (SamplesOutsideLimits, 409, "samples_outside_limits"),
    (CollidesHere, 409, "collides_here"),
    (CellUnknown, 409, "cell_unknown"),
    (RealArmRefused, 409, "real_arm_refused"),
    (recon_errors.UnitsMismatchError, 422, "units_mismatch"),
    (recon_errors.NoOverlapError, 422, "no_overlap"),
    (recon_errors.DegenerateInputError, 422, "degenerate_input"),
    (recon_errors.TouchesInsufficientError, 422, "touches_insufficient"),
    (recon_errors.RegistrationError, 422, "registration_failed"),
    (recon_errors.PoorFitError, 422, "poor_fit"),
    (recon_errors.CollisionError, 422, "collision"),
    (recon_errors.InfeasibleTrajectoryError, 422, "infeasible_trajectory"),
    (recon_errors.ReconError, 422, "reconstruction_failed"),
    # Before UnknownFormatError and UnknownBackendError, which it subclasses: a package missing
    # on the server is the server's fault, not the request's.
    (driver_errors.MissingDependencyError, 501, "missing_dependency"),
    # Before InputFileError: the input may be sound, but it needs more than a configured limit
    # allows (pixels, or the memory or time of its parse); the message names the setting.
    (driver_errors.InputTooLargeError, 413, "input_too_large"),
    (driver_errors.InputFileError, 422, "invalid_file"),
    (driver_errors.UnknownFormatError, 422, "unknown_format"),
    (driver_errors.TrajectoryMismatchError, 409, "trajectory_mismatch"),
    (driver_errors.NotEnabledError, 409, "robot_not_enabled"),
    (driver_errors.NotConnectedError, 409, "robot_not_connected"),
    (driver_errors.MotionStoppedError, 409, "stopped"),
    (driver_errors.ProtectiveStopError, 409, "protective_stop"),
    (driver_errors.EmergencyStopError, 409, "emergency_stop"),
    (driver_errors.ConnectionLostError, 502, "robot_connection_lost"),
    (driver_errors.RobotTimeoutError, 504, "robot_timeout"),
    (driver_errors.UnknownBackendError, 422, "unknown_backend"),
    (driver_errors.UnknownRigidBodyError, 422, "unknown_rigid_body"),
    (driver_errors.TrackerTimeoutError, 504, "tracker_timeout"),
    (driver_errors.TrackerError, 502, "tracker_error"),
    (driver_errors.RobotError, 502, "robot_error"),
    (driver_errors.DriverError, 422, "driver_error"),
    (SessionDeletedError, 409, "session_deleted"),
    (RowGoneError, 404, "not_found"),
    # Before ValueError, which they subclass.
    (bundles.BundleConflictError, 409, "bundle_conflict"),
    (bundles.BundleError, 422, "bundle_invalid"),
    (StorageError, 500, "storage_corrupt"),
    (ValueError, 422, "invalid_value"),
]


def classify(error: BaseException) -> tuple[int, str]:
    """Status and code of an error (500 internal_error for anything unknown)."""
    if isinstance(error, ApiError):
        return error.status, error.code
    fault = storage_fault(error)
    if fault is not None:
        return 503, fault[0]
    for cls, status, code in ERROR_MAP:
        if isinstance(error, cls):
            return status, code
    return 500, "internal_error"


def error_body(error: BaseException) -> ErrorJson:
    """The JSON body for ``error`` (used by job results too)."""
    status, code = classify(error)
    if status == 500 and code == "internal_error":
        return {
            "code": code,
            "message": "internal error; the server log has the details",
            "detail": None,
        }
    fault = storage_fault(error)
    if fault is not None:
        return {"code": fault[0], "message": fault[1], "detail": None}
    detail = getattr(error, "detail", None)
    return {"code": code, "message": str(error), "detail": detail}


#: What FastAPI says of a body it could not read, whatever the reason.
_FASTAPI_PARSE_ERROR = "There was an error parsing the body"


def unparsable(error: StarletteHTTPException) -> str:
    """Why the body of a request refused with the framework's 400 could not be read.

    FastAPI answers 400 when a JSON body is not UTF-8, nests deeper than the parser recurses or
    holds an integer beyond Python's digit limit, and Starlette when a multipart body is
    malformed; a JSON syntax error is a 422 ``invalid_request``, and so are these.
    """
    cause = error.__cause__
    if isinstance(cause, RecursionError):
        return "the request is nested too deeply; send a flatter document"
    if isinstance(cause, UnicodeError):
        return "the request body is not valid UTF-8"
    if isinstance(cause, ValueError):
        # Not Python's advice on raising its limit.
        return f"the request body is not valid JSON: {str(cause).split(';')[0]}"
    if error.detail and error.detail != _FASTAPI_PARSE_ERROR:
        return f"the request body could not be read: {error.detail}"
    return "the request body could not be read"


#: The names pydantic gives the members of a union in an error's location: not fields.
_UNION_MEMBERS = {"float", "int", "str", "bool", "none", "list", "dict", "tuple", "list[float]"}


def _where(loc: Iterable[int | str]) -> str:
    """A validation error's location as the operator typed it: ``alpha``, not
    ``body.alpha.constrained-float`` (the body is implied; the union member tried is noise)."""
    parts = [str(p) for p in loc]
    if parts[:1] == ["body"] and len(parts) > 1:
        parts = parts[1:]
    named = [p for p in parts if p not in _UNION_MEMBERS and "[" not in p and "-" not in p]
    return ".".join(named) or "request"


def _classified(request: Request, error: BaseException) -> int:
    """The status of ``error``; a storage fault is noted in the store's recent faults."""
    status, _ = classify(error)
    if status == 503:
        note_storage_fault(request.app.state.services.store.faults, error)
    return status


def install(app: FastAPI) -> None:
    """Register the handlers on ``app``."""

    def respond(
        status: int, body: ErrorJson, headers: Mapping[str, str] | None = None
    ) -> JSONResponse:
        return JSONResponse(status_code=status, content=body, headers=headers)

    @app.exception_handler(ApiError)
    async def _api(request: Request, error: ApiError) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if error.status == 401 else {}
        headers.update(error.headers)
        return respond(
            error.status,
            {"code": error.code, "message": error.message, "detail": error.detail},
            headers,
        )

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, error: RequestValidationError) -> JSONResponse:
        errors = error.errors()
        problems = [
            {"where": _where(e.get("loc", ())), "problem": e.get("msg")}
            for e in errors[:MAX_LISTED_PROBLEMS]
        ]
        first = problems[0] if problems else {"where": "request", "problem": "invalid"}
        more = len(errors) - len(problems)
        return respond(
            422,
            {
                "code": "invalid_request",
                "message": f"{first['where']}: {first['problem']}"
                + (f" (and {len(errors) - 1} more problems)" if more > 0 else ""),
                "detail": problems,
            },
        )

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, error: StarletteHTTPException) -> JSONResponse:
        if error.status_code == 400:
            # The framework's "error parsing the body": a malformed request like any other.
            return respond(
                422, {"code": "invalid_request", "message": unparsable(error), "detail": None}
            )
        code = {404: "not_found", 405: "method_not_allowed"}.get(error.status_code, "http_error")
        return respond(
            error.status_code, {"code": code, "message": str(error.detail), "detail": None}
        )

    async def _domain(request: Request, error: Exception) -> JSONResponse:
        status = _classified(request, error)
        if status >= 500:
            log.error("error while serving %s %s: %s", request.method, request.url.path, error)
        headers = {"Retry-After": str(STORAGE_RETRY_AFTER_S)} if status == 503 else None
        return respond(status, error_body(error), headers)

    async def _storage_or_internal(request: Request, error: Exception) -> JSONResponse:
        # An OSError or a database error is the server's: a full disk or a busy database is a
        # named 503 to retry; anything else a 500 (logged with its traceback).
        if storage_fault(error) is not None:
            return await _domain(request, error)
        log.exception("error while serving %s %s", request.method, request.url.path)
        return respond(500, error_body(error))

    app.add_exception_handler(OSError, _storage_or_internal)
    app.add_exception_handler(sqlalchemy.exc.OperationalError, _storage_or_internal)

    # Each mapped class gets its own handler: Starlette re-raises whatever reaches the
    # catch-all handler below after answering (it is for server errors).
    for cls, _status, _code in ERROR_MAP:
        app.add_exception_handler(cls, _domain)

    @app.exception_handler(RecursionError)
    async def _too_deep(request: Request, error: RecursionError) -> JSONResponse:
        # A JSON document nested thousands deep exhausts any recursive reader or validator.
        return respond(
            422,
            {
                "code": "invalid_request",
                "message": "the request is nested too deeply; send a flatter document",
                "detail": None,
            },
        )

    @app.exception_handler(Exception)
    async def _any(request: Request, error: Exception) -> JSONResponse:
        status = _classified(request, error)
        if status >= 500:
            log.exception("error while serving %s %s", request.method, request.url.path)
        return respond(status, error_body(error))
