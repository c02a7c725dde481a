"""Why the real arm was refused: one exception class per reason, each mapped to 409 and a
stable code in :mod:`service.errors`. Raised by the gate (:mod:`service.gate`, which re-exports
them) and by the arm's watch (:mod:`service.robot`: a state that cannot be read); kept apart so
that neither imports the other.
"""

from __future__ import annotations


class RealArmRefused(Exception):
    """The configured arm may not run this trajectory now (the message says what to do).

    ``detail`` carries what the operator's page shows beside the message (distances, ids).
    """

    def __init__(self, message: str, *, detail: dict | None = None) -> None:
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
