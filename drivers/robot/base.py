"""The robot backend interface: one lifecycle, one way to run a trajectory, for every arm.

Modelled on python-can's bus interfaces and ros2_control's hardware interfaces: the public methods
live here, check the lifecycle and the arguments, and call a backend's private hooks. Lifecycle
(docs/architecture.md): ``connect()`` reads state and moves nothing, ``enable()`` readies the arm,
then motion, ``disable()``, ``close()`` (idempotent). Motion while not enabled raises.

Backends are registered by name in :data:`BACKENDS` (a :class:`~drivers.registry.Registry`) and
imported lazily (:func:`create_backend`), so a missing optional dependency is an error that names
it, not an import failure of the whole package.
"""

from __future__ import annotations

import enum
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from drivers.errors import (
    ConnectionLostError,
    EmergencyStopError,
    MotionStoppedError,
    NotConnectedError,
    NotEnabledError,
    ProtectiveStopError,
    TrajectoryMismatchError,
    UnknownBackendError,
)
from drivers.registry import Registry
from drivers.robot.clock import Clock, RealClock
from recon import kinematics
from recon.arrays import FloatArray
from recon.trajectory import JointTrajectory
from recon.transforms import pose_from_transform
from recon.waypoints import CoarsePath, coarse_waypoints

#: How far (largest joint difference) the arm may be from a trajectory's first sample.
START_TOLERANCE_RAD = 0.01


class RobotState(enum.Enum):
    DISCONNECTED = "disconnected"
    CONNECTED = "connected"  # state readable, no motion allowed
    ENABLED = "enabled"  # ready to move
    MOVING = "moving"
    PROTECTIVE_STOP = "protective_stop"
    EMERGENCY_STOP = "emergency_stop"


class BackendConfig(BaseModel):
    """Settings shared by every backend; each adds its own and a literal ``kind``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    robot: str = Field("ur5e", description="UR model, e.g. ur5e")
    lookahead_s: float = Field(0.1, ge=0.03, le=0.2, description="servoJ lookahead time")
    gain: float = Field(300.0, ge=100.0, le=2000.0, description="servoJ proportional gain")


@dataclass(frozen=True)
class RobotStatus:
    """What the arm reports.

    Attributes
    ----------
    state : RobotState
    q_rad : ndarray of shape (6,)
    tcp_pose : ndarray of shape (6,)
        Flange pose x, y, z (m), rx, ry, rz (rotation vector), base frame.
    """

    state: RobotState
    q_rad: FloatArray
    tcp_pose: FloatArray


@dataclass(frozen=True)
class ExecutionRecord:
    """What happened while a trajectory ran.

    Attributes
    ----------
    t_s : ndarray of shape (K,)
        Time of each sample since the start (the controller's clock).
    q_planned_rad, q_actual_rad : ndarray of shape (K, 6)
    completed : bool
        All samples were sent and the arm came to rest.
    fault : str or None
        Why it ended early (a stop request, a protective stop, a lost connection).
    tcp_actual : ndarray of shape (K, 6), or None
        The controller's actual TCP pose at each sample (x, y, z, rx, ry, rz; base frame, with
        the TCP it was told), where the backend reads it.
    planned_index : ndarray of shape (K,), int, or None
        Which sample of the trajectory each one was sent as (servoJ streams sample k as record
        k), or planned at that time (movePath); None: sample k was planned sample k.
    realtime : str or None
        How the streaming loop was scheduled (a realtime priority, or why not).
    """

    t_s: FloatArray
    q_planned_rad: FloatArray
    q_actual_rad: FloatArray
    completed: bool
    fault: str | None = None
    tcp_actual: FloatArray | None = None
    planned_index: np.ndarray | None = None
    realtime: str | None = None

    def planned(self) -> np.ndarray:
        """Which planned sample each recorded one belongs to (see ``planned_index``)."""
        if self.planned_index is not None:
            return np.asarray(self.planned_index)
        return np.arange(len(self.t_s))

    def __len__(self) -> int:
        return len(self.t_s)


ProgressCallback = Callable[[float], None]


class RobotBackend(ABC):
    """One robot arm, behind the common lifecycle.

    Parameters
    ----------
    config : BackendConfig
    clock : Clock, optional
        What the backend waits on; a :class:`~drivers.robot.clock.FakeClock` makes simulated
        motion cost no real time.
    """

    kind: ClassVar[str]
    #: Its config model (what :func:`create_backend` takes for it).
    config_class: ClassVar[type[BackendConfig]]
    #: Whether :meth:`set_speed` and :meth:`pause` reach :meth:`execute_path` too (the
    #: controller's speed slider); the streamed :meth:`execute` always takes them.
    speed_override_paths: ClassVar[bool] = False

    def __init__(self, config: BackendConfig, *, clock: Clock | None = None) -> None:
        self.config = config
        self.arm = kinematics.model(config.robot)
        self.clock: Clock = clock or RealClock()
        self._state = RobotState.DISCONNECTED
        self._lock = threading.RLock()
        self._stop_requested = threading.Event()
        #: The TCP the controller was told (:meth:`set_tool`): x, y, z, rx, ry, rz.
        self.tcp_pose = np.zeros(6)
        # The speed override of a streamed execution (see :meth:`set_speed`).
        self._speed_fraction = 1.0
        self._paused = False
        #: The speed fraction the stream last reported it runs at (0: at rest, paused).
        self.speed_now = 1.0

    # -- lifecycle -----------------------------------------------------------------------------

    @property
    def state(self) -> RobotState:
        return self._state

    def connect(self) -> None:
        """Open the connection and read the arm's state; nothing moves. Idempotent."""
        with self._lock:
            if self._state is not RobotState.DISCONNECTED:
                return
            self._connect()
            self._state = RobotState.CONNECTED

    def enable(self) -> None:
        """Make the arm ready to move (power, brakes, control program)."""
        with self._lock:
            self._require_connected()
            if self._state is RobotState.PROTECTIVE_STOP:
                raise ProtectiveStopError(
                    "the arm is in a protective stop: clear its cause and unlock it first"
                )
            if self._state is RobotState.EMERGENCY_STOP:
                raise EmergencyStopError("the emergency stop is engaged: release it first")
            if self._state is RobotState.CONNECTED:
                self._enable()
                self._state = RobotState.ENABLED

    def disable(self) -> None:
        """Stop accepting motion (stopping first if moving); the connection stays open."""
        with self._lock:
            self._require_connected()
            if self._state in (RobotState.ENABLED, RobotState.MOVING):
                self._disable()
                self._state = RobotState.CONNECTED

    def close(self) -> None:
        """Disable and disconnect. Idempotent, and safe after a lost connection."""
        with self._lock:
            if self._state is RobotState.DISCONNECTED:
                return
            try:
                self._close()
            finally:
                self._state = RobotState.DISCONNECTED

    def __enter__(self) -> RobotBackend:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- reading ---------------------------------------------------------------------------------

    def status(self) -> RobotStatus:
        """The arm's current joints and flange pose."""
        with self._lock:
            self._require_connected()
            q = self._read_q()
            return RobotStatus(state=self._state, q_rad=q, tcp_pose=self._flange_pose(q))

    # -- motion ----------------------------------------------------------------------------------

    def move_joints(
        self, q_rad: FloatArray, *, speed_rad_s: float = 0.5, acceleration_rad_s2: float = 1.0
    ) -> None:
        """Move to a joint configuration (UR's moveJ); returns when the arm is there.

        Raises
        ------
        NotEnabledError, ValueError
            Not enabled; joints outside the limits, or a speed or acceleration out of range.
        """
        q = np.asarray(q_rad, dtype=np.float64)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise ValueError(f"q_rad must be 6 finite joint angles, got {q_rad!r}")
        if np.any(q < self.arm.q_min_rad) or np.any(q > self.arm.q_max_rad):
            raise ValueError("q_rad is outside the arm's joint limits")
        if not (0 < speed_rad_s <= float(self.arm.qd_max_rad_s.min())):
            raise ValueError(f"speed_rad_s must be in (0, {self.arm.qd_max_rad_s.min():.2f}]")
        if not (0 < acceleration_rad_s2 <= 10.0):
            raise ValueError("acceleration_rad_s2 must be in (0, 10]")
        with self._lock:
            self._require_enabled()
            self._require_not_stopped()
            self._state = RobotState.MOVING
        try:
            self._move_joints(q, speed_rad_s, acceleration_rad_s2)
        finally:
            self._settle_state()

    def set_tool(
        self,
        tcp_pose: FloatArray,
        *,
        payload_kg: float | None = None,
        payload_cog_m: FloatArray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        """Tell the controller the tool: its TCP in the flange frame (x, y, z, rx, ry, rz, as on
        UR's pendant) and its payload (mass, centre of gravity in the flange frame; a mass of
        None sets none: the installation's payload stays). Before motion: the controller's TCP
        pose readings and its payload compensation follow it.

        Raises
        ------
        NotEnabledError, ValueError
        """
        pose = np.asarray(tcp_pose, dtype=np.float64)
        cog = np.asarray(payload_cog_m, dtype=np.float64)
        if pose.shape != (6,) or not np.all(np.isfinite(pose)) or np.abs(pose[:3]).max() > 1.0:
            raise ValueError(f"tcp_pose must be 6 finite numbers within 1 m, got {tcp_pose!r}")
        if (
            payload_kg is not None and not (0.0 <= payload_kg <= self.arm.payload_kg)
        ) or cog.shape != (3,):
            raise ValueError(
                f"the payload must be 0..{self.arm.payload_kg} kg with a 3-vector centre of "
                f"gravity, got {payload_kg!r}, {payload_cog_m!r}"
            )
        with self._lock:
            self._require_enabled()
            self._set_tool(pose, None if payload_kg is None else float(payload_kg), cog)
            self.tcp_pose = pose

    def execute(
        self,
        trajectory: JointTrajectory,
        *,
        on_progress: ProgressCallback | None = None,
        journal: str | Path | None = None,
    ) -> ExecutionRecord:
        """Stream a trajectory to the arm at the controller rate (servoJ) and record it.

        The arm must be enabled and at the trajectory's first sample (within
        :data:`START_TOLERANCE_RAD`); move it there with :meth:`move_joints` first. A
        :meth:`stop` from another thread ends the run early with a controlled deceleration; the
        record says so. With ``journal``, every sample is also written to that file as it
        arrives (:mod:`drivers.robot.journal`), by the process that talks to the arm.

        Raises
        ------
        NotEnabledError, TrajectoryMismatchError
        ProtectiveStopError, EmergencyStopError, ConnectionLostError
            Raised after the record of what ran up to that point has been kept
            (:attr:`last_record`).
        """
        self._begin(trajectory)
        self.last_record: ExecutionRecord | None = None
        try:
            record = self._execute(trajectory, on_progress, journal)
            self.last_record = record
            return record
        finally:
            self._settle_state()

    def execute_path(
        self,
        trajectory: JointTrajectory,
        *,
        tolerance_m: float = 5e-4,
        blend_m: float = 1e-3,
        on_progress: ProgressCallback | None = None,
        journal: str | Path | None = None,
    ) -> ExecutionRecord:
        """Run a trajectory as a path the controller executes itself (UR's movePath).

        For coarse paths, or links where streaming at the controller rate is not reliable: the
        trajectory is reduced to joint waypoints (:func:`recon.waypoints.coarse_waypoints`,
        every planned TCP sample within ``tolerance_m`` of the joint-space line between them),
        sent as blended moveJ targets, and run by the controller with its own timing. The record
        pairs each actual sample with the planned sample at the same time since the start.
        Preconditions, stop and faults as :meth:`execute`.
        """
        self._begin(trajectory)
        self.last_record = None
        try:
            # Judged on the arm the plan was solved for: its calibration, if it had one.
            path = coarse_waypoints(
                trajectory.arm, trajectory, tolerance_m=tolerance_m, blend_m=blend_m
            )
            # Computing the waypoints takes a moment: a stop that came meanwhile wins (the
            # worker checks again right before it sends the path).
            self._require_not_stopped()
            t_s, q_actual, completed, fault = self._execute_path(path, on_progress, journal)
            planned_index = np.minimum(
                np.searchsorted(trajectory.t_s - trajectory.t_s[0], t_s), len(trajectory) - 1
            )
            record = ExecutionRecord(
                planned_index=planned_index,
                t_s=np.asarray(t_s, dtype=np.float64),
                q_planned_rad=trajectory.q_rad[planned_index],
                q_actual_rad=np.asarray(q_actual, dtype=np.float64).reshape(-1, 6),
                completed=completed,
                fault=fault,
            )
            self.last_record = record
            return record
        finally:
            self._settle_state()

    def _begin(self, trajectory: JointTrajectory) -> None:
        """Check a trajectory against the arm and its state, and mark the arm moving."""
        self._check_trajectory(trajectory)
        with self._lock:
            self._require_enabled()
            self._require_not_stopped()
            q_now = self._read_q()
            gap = float(np.abs(q_now - trajectory.q_rad[0]).max())
            if gap > START_TOLERANCE_RAD:
                raise TrajectoryMismatchError(
                    f"the arm is {np.degrees(gap):.1f} deg (largest joint) from the "
                    "trajectory's start: move it there first (move_joints)"
                )
            self._state = RobotState.MOVING

    def stop(self) -> None:
        """Decelerate to a stop and refuse every later motion of this backend.

        Safe to call from any thread at any time: before :meth:`connect`, while connecting,
        between moves or during one. The request is latched: a stop can never be lost to a
        motion that starts just after it. A new execution takes a new backend (or calls
        :meth:`clear_stop` first).
        """
        self._stop_requested.set()
        self._stop()

    @property
    def stop_requested(self) -> bool:
        """Whether a stop was requested (and not cleared since)."""
        return self._stop_requested.is_set()

    # -- speed override and pause ---------------------------------------------------------------

    def set_speed(self, fraction: float) -> None:
        """Run the streamed execution at ``fraction`` of its planned speed, from now on.

        Any thread, any time; the stream ramps to it within the joints' acceleration limits and
        never runs faster than planned (:mod:`drivers.robot.timescale`). Applies to
        :meth:`execute` (the stream is timed here), and to :meth:`execute_path` where the
        backend says so (:attr:`speed_override_paths`: the controller's speed slider).

        Raises
        ------
        ValueError
            ``fraction`` outside :data:`~drivers.robot.timescale.MIN_SPEED_FRACTION` .. 1.
        """
        from drivers.robot.timescale import MIN_SPEED_FRACTION

        value = float(fraction)
        if not MIN_SPEED_FRACTION <= value <= 1.0:  # NaN too
            raise ValueError(
                f"the speed must be {MIN_SPEED_FRACTION:.0%} to 100 % of the planned speed, "
                f"got {fraction!r}"
            )
        self._speed_fraction = value
        self._send_speed()

    def pause(self) -> None:
        """Bring the streamed execution to rest on its path (a controlled slow-down along it,
        within the acceleration limits); it holds there until :meth:`resume` or a stop."""
        self._paused = True
        self._send_speed()

    def resume(self) -> None:
        """Go on along the path from where :meth:`pause` left it, ramping up to the speed set."""
        self._paused = False
        self._send_speed()

    @property
    def speed_fraction(self) -> float:
        """The speed override set (0..1), whether paused or not."""
        return self._speed_fraction

    @property
    def paused(self) -> bool:
        return self._paused

    @property
    def speed_target(self) -> float:
        """What the stream ramps towards: 0 while paused, else :attr:`speed_fraction`."""
        return 0.0 if self._paused else self._speed_fraction

    def _send_speed(self) -> None:  # noqa: B027 - optional hook
        """Pass :attr:`speed_target` to where the stream runs (a worker process reads it)."""

    def clear_stop(self) -> None:
        """Forget a stop request: only for starting a new execution on the same backend."""
        with self._lock:
            if self._state is RobotState.MOVING:
                raise NotEnabledError("the arm is moving: a stop cannot be cleared now")
            self._stop_requested.clear()
            self._clear_stop()

    def unlock_protective_stop(self) -> None:
        """Clear a protective stop (after its cause is gone); the arm is then enabled again."""
        with self._lock:
            self._require_connected()
            if self._state is RobotState.PROTECTIVE_STOP:
                self._unlock_protective_stop()
                self._state = RobotState.ENABLED

    # -- helpers for subclasses ------------------------------------------------------------------

    def _fault(self, error: Exception) -> None:
        """Record the state a fault leaves the arm in."""
        if isinstance(error, ProtectiveStopError):
            self._state = RobotState.PROTECTIVE_STOP
        elif isinstance(error, EmergencyStopError):
            self._state = RobotState.EMERGENCY_STOP
        elif isinstance(error, ConnectionLostError):
            self._state = RobotState.DISCONNECTED

    def _settle_state(self) -> None:
        with self._lock:
            if self._state is RobotState.MOVING:
                self._state = RobotState.ENABLED

    def _flange_pose(self, q: FloatArray) -> FloatArray:
        return pose_from_transform(kinematics.forward(self.arm, q))

    def _require_connected(self) -> None:
        if self._state is RobotState.DISCONNECTED:
            raise NotConnectedError(f"the {self.kind} robot is not connected: call connect()")

    def _require_not_stopped(self) -> None:
        if self._stop_requested.is_set():
            raise MotionStoppedError(
                "a stop was requested: this execution moves no further (start a new one)"
            )

    def _require_enabled(self) -> None:
        self._require_connected()
        if self._state is RobotState.PROTECTIVE_STOP:
            raise ProtectiveStopError("the arm is in a protective stop: unlock it first")
        if self._state is RobotState.EMERGENCY_STOP:
            raise EmergencyStopError("the emergency stop is engaged: release it first")
        if self._state is RobotState.MOVING:
            raise NotEnabledError("the arm is already moving: wait for it or stop it")
        if self._state is not RobotState.ENABLED:
            raise NotEnabledError("the arm is not enabled: call enable() before moving it")

    def _check_trajectory(self, trajectory: JointTrajectory) -> None:
        if trajectory.robot != self.arm.name:
            raise TrajectoryMismatchError(
                f"the trajectory was planned for a {trajectory.robot}, this arm is a "
                f"{self.arm.name}: plan it again for this arm"
            )
        if len(trajectory) < 2:
            raise TrajectoryMismatchError("the trajectory has fewer than two samples")
        expected = 1.0 / self.arm.control_rate_hz
        if abs(trajectory.period_s - expected) > 1e-6:
            raise TrajectoryMismatchError(
                f"the trajectory is sampled every {trajectory.period_s * 1e3:.3f} ms; this "
                f"controller runs at {self.arm.control_rate_hz:.0f} Hz ({expected * 1e3:.1f} ms)"
            )
        if np.any(trajectory.q_rad < self.arm.q_min_rad) or np.any(
            trajectory.q_rad > self.arm.q_max_rad
        ):
            raise TrajectoryMismatchError("the trajectory leaves the arm's joint limits")

    # -- hooks -----------------------------------------------------------------------------------

    @abstractmethod
    def _connect(self) -> None: ...

    @abstractmethod
    def _enable(self) -> None: ...

    @abstractmethod
    def _disable(self) -> None: ...

    @abstractmethod
    def _close(self) -> None: ...

    @abstractmethod
    def _read_q(self) -> FloatArray: ...

    @abstractmethod
    def _move_joints(self, q: FloatArray, speed: float, acceleration: float) -> None: ...

    @abstractmethod
    def _execute(
        self,
        trajectory: JointTrajectory,
        on_progress: ProgressCallback | None,
        journal: str | Path | None,
    ) -> ExecutionRecord: ...

    @abstractmethod
    def _execute_path(
        self,
        path: CoarsePath,
        on_progress: ProgressCallback | None,
        journal: str | Path | None,
    ) -> tuple[FloatArray, FloatArray, bool, str | None]:
        """Run ``path``; return the sample times (s), actual joints (K, 6), whether it
        completed, and why not."""

    @abstractmethod
    def _set_tool(
        self, tcp_pose: FloatArray, payload_kg: float | None, cog_m: FloatArray
    ) -> None: ...

    @abstractmethod
    def _stop(self) -> None:
        """Decelerate now if moving; called for every stop request, moving or not."""

    def _clear_stop(self) -> None:  # noqa: B027 - optional hook
        """Forget a stop request below the base class (a worker's own flag)."""

    @abstractmethod
    def _unlock_protective_stop(self) -> None: ...


#: Robot backends by name, imported on first use; packages add more through the entry-point
#: group ``teachpath.robot_backends``.
BACKENDS: Registry[type[RobotBackend]] = Registry(
    "robot backend",
    {
        "sim": "drivers.robot.sim:SimBackend",
        "ur_rtde": "drivers.robot.ur_rtde:URRtdeBackend",
    },
    group="teachpath.robot_backends",
    unknown_error=UnknownBackendError,
    base=RobotBackend,
)


def backend_class(kind: str) -> type[RobotBackend]:
    """The backend class registered as ``kind``, imported now.

    Raises
    ------
    UnknownBackendError
        An unknown name (the message lists the known ones).
    MissingDependencyError
        The backend needs a package that is not installed (a subclass of UnknownBackendError).
    """
    return BACKENDS.load(kind)


def backend_config(kind: str, **fields: Any) -> BackendConfig:
    """The config of the backend registered as ``kind``, built from ``fields``.

    Raises
    ------
    UnknownBackendError, MissingDependencyError
        See :func:`backend_class`.
    pydantic.ValidationError
        A field the backend does not take, or a bad value.
    """
    return backend_class(kind).config_class(**fields)


def create_backend(config: BackendConfig, *, clock: Clock | None = None) -> RobotBackend:
    """A backend for ``config``, chosen by its ``kind`` field.

    Raises
    ------
    UnknownBackendError, MissingDependencyError
        See :func:`backend_class`.
    """
    return backend_class(config.kind)(config, clock=clock)  # type: ignore[attr-defined]
