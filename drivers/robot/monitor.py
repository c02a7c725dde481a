"""What the arm is doing right now, read without taking control of it.

A :class:`RobotMonitor` reads the arm's state for the operator's safety bar and for the checks
that need the arm's joints (a plan starts where the arm is; an execution refuses to start if the
arm was moved away since). It never moves the arm and never starts a program: the ur_rtde monitor
uses only RTDE's receive interface and the dashboard server, in a worker process of its own (as
every ur_rtde client here, since its constructors hold the GIL while they wait on the network).

Monitors are registered by backend name, like the backends themselves.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

from drivers.errors import UnknownBackendError
from drivers.registry import Registry

#: UR robot modes (RTDE ``robot_mode``), by number.
ROBOT_MODES = {
    -1: "NO_CONTROLLER",
    0: "DISCONNECTED",
    1: "CONFIRM_SAFETY",
    2: "BOOTING",
    3: "POWER_OFF",
    4: "POWER_ON",
    5: "IDLE",
    6: "BACKDRIVE",
    7: "RUNNING",
    8: "UPDATING_FIRMWARE",
}
#: UR safety modes (RTDE ``safety_mode``), by number.
SAFETY_MODES = {
    1: "NORMAL",
    2: "REDUCED",
    3: "PROTECTIVE_STOP",
    4: "RECOVERY",
    5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP",
    7: "ROBOT_EMERGENCY_STOP",
    8: "VIOLATION",
    9: "FAULT",
    10: "VALIDATE_JOINT_ID",
    11: "UNDEFINED_SAFETY_MODE",
    12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
    13: "SYSTEM_THREE_POSITION_ENABLING_STOP",
}


@dataclass(frozen=True)
class ArmState:
    """One reading of the arm.

    Attributes
    ----------
    backend : str
        "sim" or "ur_rtde".
    reachable : bool
        Whether the reading came from the arm (False: ``error`` says why; the rest is unknown).
    robot_mode : str
        UR's robot mode ("RUNNING", "POWER_OFF", ...; "SIMULATED" for the sim).
    safety_status : str
        UR's safety mode ("NORMAL", "PROTECTIVE_STOP", "ROBOT_EMERGENCY_STOP", ...).
    protective_stop, emergency_stop : bool
    remote_control : bool or None
        Whether the arm takes commands from the network (None: unknown).
    program_running : bool
        A program runs on the controller (ur_rtde's control script counts).
    q_rad : tuple of 6 floats, or None
    tcp_pose : tuple of 6 floats, or None
        The active TCP, base frame: x, y, z (m), rx, ry, rz (rotation vector).
    payload_kg : float or None
        The controller's active payload (its installation's, or the last one set).
    payload_cog_m : tuple of 3 floats, or None
        Its centre of gravity, flange frame.
    error : str or None
    """

    backend: str
    reachable: bool
    robot_mode: str = "UNKNOWN"
    safety_status: str = "UNKNOWN"
    protective_stop: bool = False
    emergency_stop: bool = False
    remote_control: bool | None = None
    program_running: bool = False
    q_rad: tuple[float, ...] | None = None
    tcp_pose: tuple[float, ...] | None = None
    payload_kg: float | None = None
    payload_cog_m: tuple[float, ...] | None = None
    error: str | None = None

    @classmethod
    def unreachable(cls, backend: str, error: str) -> ArmState:
        return cls(backend=backend, reachable=False, error=error)


class RobotMonitor(ABC):
    """Reads an arm's state; never moves it. ``close()`` is idempotent."""

    kind: str

    @abstractmethod
    def read(self) -> ArmState:
        """The arm's state now (an unreachable arm is a state, not an exception)."""

    @abstractmethod
    def unlock_protective_stop(self) -> None:
        """Ask the controller to unlock a protective stop.

        Raises
        ------
        ProtectiveStopError
            The controller refused (within 5 s of the stop, or while its cause persists).
        ConnectionLostError
            The arm cannot be reached.
        """

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the connection."""


#: Monitors by backend name, imported on first use.
MONITORS: Registry[type[RobotMonitor]] = Registry(
    "robot monitor",
    {
        "sim": "drivers.robot.sim:SimMonitor",
        "ur_rtde": "drivers.robot.ur_state:URMonitor",
    },
    group="teachpath.robot_monitors",
    unknown_error=UnknownBackendError,
    base=RobotMonitor,
)


def create_monitor(config: Any) -> RobotMonitor:
    """The monitor of the backend ``config`` names (a backend's own config)."""
    # Every registered monitor takes its backend's config (checked by the monitors' tests); the
    # abstract base does not say so, since each takes its own config class.
    monitor_class: Any = MONITORS.load(config.kind)
    monitor: RobotMonitor = monitor_class(config)
    return monitor
