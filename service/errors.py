"""Error responses: one JSON shape, one status and stable code per error class.

Every 4xx/5xx body is ``{"code": ..., "message": ..., "detail": ...}``. Routers raise domain
errors (``recon.errors``, ``drivers.errors``) or :class:`ApiError` and never catch them; this
module turns them into responses. Unexpected exceptions become a 500 with no traceback (it is
logged on the server).
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from drivers import errors as driver_errors
from recon import errors as recon_errors
from service import bundles, gate
from service.store import SessionDeletedError, StorageError

#: A 422 lists at most this many problems (a document with 20,000 unknown keys has as many).
MAX_LISTED_PROBLEMS = 20
log = logging.getLogger("teachpath.service")


class ApiError(Exception):
    """An error of the API itself (not found, conflict, refused), with its status and code.

    ``headers`` go on the response (``Retry-After`` on a 503).
    """

    def __init__(
        self, status: int, code: str, message: str, detail=None, headers: dict | None = None
    ) -> None:
        super().__init__(message)
        self.status, self.code, self.message, self.detail = status, code, message, detail
        self.headers = dict(headers or {})


def not_found(what: str, ident: str) -> ApiError:
    return ApiError(404, "not_found", f"no {what} {ident!r}")


#: Domain error class -> (HTTP status, code). Subclasses before their bases.
ERROR_MAP: list[tuple[type[Exception], int, str]] = [
    # Why the real arm was refused: one class per reason (service/gate.py).
    (gate.NoRobotConfigured, 409, "no_robot"),
    (gate.TrajectoryForAnotherRobot, 409, "trajectory_mismatch"),
    (gate.ConfirmationRequired, 409, "confirmation_required"),
    (gate.SpeedCapExceeded, 409, "speed_cap"),
    (gate.DryRunRequired, 409, "dry_run_required"),
    (gate.UnreadableTrajectory, 409, "trajectory_unreadable"),
    (gate.ArmBusy, 409, "arm_busy"),
    (gate.RobotUnavailable, 409, "robot_unavailable"),
    (gate.ArmInProtectiveStop, 409, "protective_stop"),
    (gate.ArmInEmergencyStop, 409, "emergency_stop"),
    (gate.RemoteControlOff, 409, "remote_control_off"),
    (gate.StartMoved, 409, "start_moved"),
    (gate.SamplesOutsideLimits, 409, "samples_outside_limits"),
    (gate.CollidesHere, 409, "collides_here"),
    (gate.CellUnknown, 409, "cell_unknown"),
    (gate.RealArmRefused, 409, "real_arm_refused"),
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
    # Before ValueError, which they subclass.
    (bundles.BundleConflictError, 409, "bundle_conflict"),
    (bundles.BundleError, 422, "bundle_invalid"),
    (StorageError, 500, "storage_corrupt"),
    (ValueError, 422, "invalid_value"),
]


def classify(error: Exception) -> tuple[int, str]:
    """Status and code of an error (500 internal_error for anything unknown)."""
    if isinstance(error, ApiError):
        return error.status, error.code
    for cls, status, code in ERROR_MAP:
        if isinstance(error, cls):
            return status, code
    return 500, "internal_error"


def error_body(error: Exception) -> dict:
    """The JSON body for ``error`` (used by job results too)."""
    status, code = classify(error)
    if status == 500 and code == "internal_error":
        return {
            "code": code,
            "message": "internal error; the server log has the details",
            "detail": None,
        }
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


def install(app: FastAPI) -> None:
    """Register the handlers on ``app``."""

    def respond(status: int, body: dict, headers: dict | None = None) -> JSONResponse:
        return JSONResponse(status_code=status, content=body, headers=headers)

    @app.exception_handler(ApiError)
    async def _api(request: Request, error: ApiError):
        headers = {"WWW-Authenticate": "Bearer"} if error.status == 401 else {}
        headers.update(error.headers)
        return respond(
            error.status,
            {"code": error.code, "message": error.message, "detail": error.detail},
            headers,
        )

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, error: RequestValidationError):
        errors = error.errors()
        problems = [
            {"where": ".".join(str(p) for p in e.get("loc", ())), "problem": e.get("msg")}
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
    async def _http(request: Request, error: StarletteHTTPException):
        if error.status_code == 400:
            # The framework's "error parsing the body": a malformed request like any other.
            return respond(
                422, {"code": "invalid_request", "message": unparsable(error), "detail": None}
            )
        code = {404: "not_found", 405: "method_not_allowed"}.get(error.status_code, "http_error")
        return respond(
            error.status_code, {"code": code, "message": str(error.detail), "detail": None}
        )

    async def _domain(request: Request, error: Exception):
        status, _ = classify(error)
        if status >= 500:
            log.error("error while serving %s %s: %s", request.method, request.url.path, error)
        return respond(status, error_body(error))

    # Each mapped class gets its own handler: Starlette re-raises whatever reaches the
    # catch-all handler below after answering (it is for server errors).
    for cls, _status, _code in ERROR_MAP:
        app.add_exception_handler(cls, _domain)

    @app.exception_handler(RecursionError)
    async def _too_deep(request: Request, error: RecursionError):
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
    async def _any(request: Request, error: Exception):
        status, _ = classify(error)
        if status >= 500:
            log.exception("error while serving %s %s", request.method, request.url.path)
        return respond(status, error_body(error))
