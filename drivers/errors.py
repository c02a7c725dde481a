"""Named failures of the drivers (files, trackers, scanners, robots).

Like ``recon.errors``, these are mapped one-to-one to HTTP statuses and stable codes by
``service/errors.py``, so each class is part of the public contract.
"""

from __future__ import annotations


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
    """No robot backend is registered under that name, or its optional dependency is missing."""
