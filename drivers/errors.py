"""Named failures of the drivers (files, trackers, scanners, robots), and how they cross processes.

Like ``recon.errors``, these are mapped one-to-one to HTTP statuses and stable codes by
``service/errors.py``, so each class is part of the public contract.

Several adapters run code in a child process (:mod:`drivers.isolation`, :mod:`drivers.worker`,
the NatNet receiver). An error raised there comes back as its class name and message, and
:func:`error_from_wire` turns the name back into a class through :data:`WIRE_ERRORS`, an explicit
table: nothing received from a child is ever imported or unpickled as an exception.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from recon import errors as _recon_errors


def clipped(text: str, limit: int = 80) -> str:
    """``text`` for a message: whole up to ``limit`` characters, else cut to that with "..." (a
    damaged file's line or value may be megabytes long)."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


class DriverError(Exception):
    """Base class of every failure to talk to the outside world."""


class InputFileError(DriverError):
    """A file that is missing, unreadable, or not what its format promises."""


class UnknownFormatError(DriverError):
    """No reader is registered for the file's suffix or the requested format."""


class RobotError(DriverError):
    """A robot refused, failed or could not be reached."""


class NotConnectedError(RobotError):
    """A call that needs a connection was made before connect() or after close()."""


class NotEnabledError(RobotError):
    """Motion was requested while the arm is not enabled (call enable() first)."""


class MotionStoppedError(RobotError):
    """A stop was requested for this execution: no further motion (start a new execution)."""


class ProtectiveStopError(RobotError):
    """The arm is in a protective stop; clear the cause and unlock it before moving again."""


class EmergencyStopError(RobotError):
    """The emergency stop is engaged; release it on the robot before anything else."""


class ConnectionLostError(RobotError):
    """The connection to the controller broke; reconnect before going on."""


class RobotTimeoutError(RobotError):
    """The controller did not answer within the time allowed."""


class TrajectoryMismatchError(RobotError):
    """The trajectory does not fit this arm (another model, rate, or start far from the arm)."""


class TrackerError(DriverError):
    """A tracker failed or broke off (a receiver that died, a malformed stream)."""


class TrackerTimeoutError(TrackerError):
    """The tracker did not answer, or stopped streaming, within the time allowed."""


class UnknownRigidBodyError(TrackerError):
    """The requested rigid body is not among those the tracker streams."""


class UnknownBackendError(DriverError):
    """No robot backend or tracker source is registered under that name."""


class MissingDependencyError(UnknownBackendError, UnknownFormatError):
    """An adapter needs a Python package that is not installed; the message names what to install.

    A subclass of both :class:`UnknownBackendError` and :class:`UnknownFormatError`, which the
    registries raised for a missing dependency before there was a class of its own, so code that
    catches either keeps working.

    Attributes
    ----------
    module : str or None
        The module that could not be imported.
    package : str or None
        What to install (a pip requirement).
    """

    def __init__(self, message: str, *, module: str | None = None, package: str | None = None):
        super().__init__(message)
        self.module = module
        self.package = package


class ResourceLimitError(InputFileError):
    """Reading an input needed more time or memory than its limit allows.

    Raised by :func:`drivers.isolation.run_isolated` (and by readers that reword its message); a
    subclass of :class:`InputFileError` because the input is what made the reader need that much.

    Attributes
    ----------
    limit : {"time", "memory"} or None
        Which limit was hit.
    value : float or None
        The limit (seconds, or bytes of address space).
    setting : str or None
        The name of the setting or option that sets the limit.
    """

    def __init__(
        self,
        message: str,
        *,
        limit: str | None = None,
        value: float | None = None,
        setting: str | None = None,
    ) -> None:
        super().__init__(message)
        self.limit = limit
        self.value = value
        self.setting = setting

    @property
    def detail(self) -> dict[str, Any] | None:
        """The limit as data (the ``detail`` of an error response), or None if unknown (an error
        that crossed from a child process keeps its message only)."""
        if self.limit is None and self.setting is None:
            return None
        return {"limit": self.limit, "value": self.value, "setting": self.setting}


class InputTooLargeError(ResourceLimitError):
    """An input that needs more than a limit someone configured allows: pixels, memory or time.

    Unlike a plain :class:`ResourceLimitError` (a limit scaled to the file, which only a damaged
    file reaches), the input may be sound and the limit a choice: the message names the limit and
    the setting or option that sets it. The service answers 413.

    Attributes
    ----------
    limit : {"time", "memory", "pixels", "unpacked"} or None
    value : float or None
        The limit (seconds, bytes of address space, pixels, or bytes unpacked from a zip).
    setting : str or None
    """


class ReaderCrashError(InputFileError):
    """A reader's child process died without an answer (a signal, or an exit of native code).

    Native parsers (ezc3d, librealsense) crash on some damaged files; the input is blamed, and the
    calling process lives on.

    Attributes
    ----------
    signal_name : str or None
        The signal that ended the child ("SIGSEGV"), or None if it exited by itself.
    exit_code : int or None
        Its exit status, if it exited by itself.
    output_tail : str
        The last lines the child wrote to stdout or stderr (native libraries report there).
    """

    def __init__(
        self,
        message: str,
        *,
        signal_name: str | None = None,
        exit_code: int | None = None,
        output_tail: str = "",
    ) -> None:
        super().__init__(message)
        self.signal_name = signal_name
        self.exit_code = exit_code
        self.output_tail = output_tail


class WorkerError(DriverError):
    """A worker process (:class:`drivers.worker.WorkerClient`) failed to answer.

    Adapters re-raise these as their own kind (a robot's :class:`RobotTimeoutError` or
    :class:`ConnectionLostError`), with advice that fits the device.
    """


class WorkerTimeoutError(WorkerError):
    """The worker did not answer a command within its bound; it has been ended."""


class WorkerLostError(WorkerError):
    """The worker process is gone (it died, or the client was closed)."""


#: The error classes that may cross a process boundary, by class name: every class of this
#: module and of ``recon.errors``, and ValueError (the convention for a bad argument). Listed
#: one by one so that what a child may make this process raise is plain to see (a test checks
#: that no class of either module is missing).
WIRE_ERRORS: dict[str, type[Exception]] = {
    cls.__name__: cls
    for cls in (
        ValueError,
        DriverError,
        InputFileError,
        ResourceLimitError,
        InputTooLargeError,
        ReaderCrashError,
        UnknownFormatError,
        UnknownBackendError,
        MissingDependencyError,
        RobotError,
        NotConnectedError,
        NotEnabledError,
        MotionStoppedError,
        ProtectiveStopError,
        EmergencyStopError,
        ConnectionLostError,
        RobotTimeoutError,
        TrajectoryMismatchError,
        TrackerError,
        TrackerTimeoutError,
        UnknownRigidBodyError,
        WorkerError,
        WorkerTimeoutError,
        WorkerLostError,
        _recon_errors.ReconError,
        _recon_errors.DegenerateInputError,
        _recon_errors.NoOverlapError,
        _recon_errors.UnitsMismatchError,
        _recon_errors.RegistrationError,
        _recon_errors.TouchesInsufficientError,
        _recon_errors.PoorFitError,
        _recon_errors.InfeasibleTrajectoryError,
        _recon_errors.CollisionError,
    )
}

#: Messages longer than this are cut before they cross (a runaway message is not a report).
_WIRE_MESSAGE_CHARS = 4000


def error_to_wire(error: BaseException) -> tuple[str, str]:
    """The class name and message of ``error``, as sent from a child process.

    Parameters
    ----------
    error : BaseException

    Returns
    -------
    tuple of (str, str)
        ``(class name, message)``, the message at most a few thousand characters.
    """
    message = str(error)
    if len(message) > _WIRE_MESSAGE_CHARS:
        message = message[:_WIRE_MESSAGE_CHARS] + " [...]"
    return type(error).__name__, message


def error_from_wire(
    name: str,
    message: str,
    *,
    fallback: Callable[[str], Exception] = DriverError,
    table: dict[str, type[Exception]] | None = None,
) -> Exception:
    """The exception a child process reported, rebuilt in this one.

    Parameters
    ----------
    name, message : str
        What :func:`error_to_wire` sent.
    fallback : exception class, or callable taking a message
        Used for a class name not in the table; its message then names the original class.
    table : dict, optional
        Allowed classes by name; default :data:`WIRE_ERRORS`.

    Returns
    -------
    Exception
        An instance of the named class with the same message, or of ``fallback``.
    """
    cls = (WIRE_ERRORS if table is None else table).get(name)
    if cls is None:
        return fallback(f"{name}: {message}")
    return cls(message)
