"""A simulated UR arm that behaves like the real one where teachpath can tell.

Same base class, units, blocking behaviour and exceptions as the ``ur_rtde`` backend. Its joints
are integrated, never copied from the command. Servo targets are tracked the way servoJ does it:
the controller buffers them for the lookahead time and follows the buffered stream, so the arm is
behind in time but on the path. Modelled as a delay of ``lookahead_s`` followed by a critically
damped law with feed-forward, ``qdd = qdd_t + 2 w (qd_t - qd) + w^2 (q_t - q)``, ``w = sqrt(gain)``
(gain 300: 17 rad/s), limited by the joints' speed limits and an acceleration a few times the
planning value. (Without the feed-forward the law cuts inside curves: measured 0.95 mm on the
demo path at 0.1 m/s.) Running into a joint position limit is a protective stop, as on the
real arm.

Time comes from an injectable clock: with :class:`~drivers.robot.clock.FakeClock` a minute of
motion runs in a fraction of a second. Faults are injected through :meth:`SimBackend.inject`,
never through magic values.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from drivers.errors import (
    ConnectionLostError,
    EmergencyStopError,
    ProtectiveStopError,
    RobotError,
    RobotTimeoutError,
)
from drivers.robot.base import (
    BackendConfig,
    ExecutionRecord,
    ProgressCallback,
    RobotBackend,
    RobotState,
)
from drivers.robot.clock import Clock
from drivers.robot.journal import JournalWriter
from drivers.robot.monitor import ArmState, RobotMonitor
from drivers.robot.timescale import MAX_PAUSE_S, PlanCursor
from recon import kinematics
from recon.arrays import FloatArray
from recon.motion import trapezoid, trapezoid_duration
from recon.trajectory import JointTrajectory
from recon.transforms import pose_from_transform, transform_from_pose
from recon.waypoints import CoarsePath

#: A home pose: elbow up, tool pointing down, well away from singularities.
HOME_RAD = kinematics.HOME_Q_RAD
#: The simulated joints accelerate at up to this multiple of the planning acceleration.
PHYSICAL_ACCELERATION_FACTOR = 4.0
#: Integration steps per controller period.
SUBSTEPS = 4
#: Progress is reported every this many samples.
PROGRESS_EVERY = 50


class SimConfig(BackendConfig):
    """The simulated arm's settings."""

    kind: Literal["sim"] = "sim"
    q_start_rad: tuple[float, float, float, float, float, float] = Field(
        HOME_RAD, description="joint angles the arm starts at"
    )


@dataclass
class _Fault:
    at_s: float
    error: type[RobotError]
    message: str


class SimBackend(RobotBackend):
    """The simulated arm (see the module docstring)."""

    kind = "sim"
    config_class = SimConfig

    def __init__(self, config: SimConfig, *, clock: Clock | None = None) -> None:
        super().__init__(config, clock=clock)
        self._q = np.array(config.q_start_rad, dtype=np.float64)
        self._qd = np.zeros(6)
        self._t: float | None = None  # time the physics was last advanced to
        self._faults: list[_Fault] = []
        self._stopping = False
        self._omega = float(np.sqrt(config.gain))
        self._acc_max = self.arm.qdd_max_rad_s2 * PHYSICAL_ACCELERATION_FACTOR
        self._dt = 1.0 / self.arm.control_rate_hz
        self._active: RobotError | None = None  # a fault that has happened
        # servoJ's lookahead: targets wait this many periods before the arm follows them.
        self._delay = max(1, int(round(config.lookahead_s / self._dt)))
        self._buffer: list[FloatArray] = []

    # -- fault injection -------------------------------------------------------------------------

    def inject(self, error: type[RobotError], *, after_s: float = 0.0, message: str = "") -> None:
        """Make ``error`` happen ``after_s`` seconds of (clock) time from now.

        Supported: :class:`ProtectiveStopError` (the arm stops; motion fails until
        :meth:`unlock_protective_stop`), :class:`EmergencyStopError`, :class:`ConnectionLostError`
        (every later call fails until reconnecting), :class:`RobotTimeoutError` (the controller
        stops answering).
        """
        supported = (
            ProtectiveStopError,
            EmergencyStopError,
            ConnectionLostError,
            RobotTimeoutError,
        )
        if error not in supported:
            raise ValueError(
                f"cannot inject {error.__name__}; supported: "
                f"{', '.join(e.__name__ for e in supported)}"
            )
        if after_s < 0:
            raise ValueError("after_s must be >= 0")
        default = {
            ProtectiveStopError: "protective stop (injected)",
            EmergencyStopError: "emergency stop (injected)",
            ConnectionLostError: "connection to the controller lost (injected)",
            RobotTimeoutError: "the controller stopped answering (injected)",
        }[error]
        self._faults.append(_Fault(self.clock.now() + after_s, error, message or default))

    # -- hooks -----------------------------------------------------------------------------------

    def _connect(self) -> None:
        if isinstance(self._active, (ConnectionLostError, RobotTimeoutError)):
            self._active = None  # reconnecting clears a lost link
        self._t = self.clock.now()
        self._check_faults()

    def _enable(self) -> None:
        self._advance(self.clock.now(), target=None)

    def _disable(self) -> None:
        self._advance(self.clock.now(), target=None)

    def _close(self) -> None:
        self._t = None

    def _read_q(self) -> FloatArray:
        self._advance(self.clock.now(), target=None)
        return self._q.copy()

    def _unlock_protective_stop(self) -> None:
        if isinstance(self._active, ProtectiveStopError):
            self._active = None
        self._advance(self.clock.now(), target=None)

    def _stop(self) -> None:
        self._stopping = True

    def _clear_stop(self) -> None:
        self._stopping = False

    def _move_joints(self, q: FloatArray, speed: float, acceleration: float) -> None:
        start = self._read_q()
        profile = _synchronised_trapezoid(start, q, speed, acceleration, self._dt)
        t0 = self.clock.now()
        for i, target in enumerate(profile, start=1):
            if self._stop_requested.is_set():
                break
            self.clock.sleep_until(t0 + i * self._dt)
            self._advance(self.clock.now(), target=target)
        # Let the servo settle on the goal.
        for _ in range(int(0.5 / self._dt)):
            if self._stop_requested.is_set() or np.abs(self._qd).max() < 1e-4:
                break
            self.clock.sleep_until(self.clock.now() + self._dt)
            self._advance(self.clock.now(), target=q if not self._stopping else self._q)

    def _set_tool(self, tcp_pose: FloatArray, payload_kg: float | None, cog_m: FloatArray) -> None:
        if payload_kg is not None:  # None: the payload set before stays, as on a controller
            self.payload_kg, self.payload_cog_m = payload_kg, cog_m

    def _execute(
        self,
        trajectory: JointTrajectory,
        on_progress: ProgressCallback | None,
        journal: str | Path | None,
    ) -> ExecutionRecord:
        # Timed here, as the servoJ stream is: the speed override and pause apply.
        cursor = PlanCursor(
            trajectory.q_rad, self._dt, trajectory.arm.qdd_max_rad_s2, self.speed_target
        )
        times, _sent, planned, actual, completed, fault = self._stream(
            cursor, on_progress, journal, override=True
        )
        return self._record(times, trajectory.q_rad[planned], actual, completed, fault, planned)

    def _execute_path(
        self, path: CoarsePath, on_progress: ProgressCallback | None, journal: str | Path | None
    ) -> tuple[FloatArray, FloatArray, bool, str | None]:
        # The controller runs the path itself: joint-space lines between the waypoints at each
        # move's speed, without stopping where a blend is asked for. Fed to the same servo law,
        # which rounds the corners the way blending does. The controller times it: no override.
        cursor = PlanCursor(_path_targets(path, self._dt), self._dt, self.arm.qdd_max_rad_s2)
        times, _, _, actual, completed, fault = self._stream(
            cursor, on_progress, journal, override=False
        )
        return np.array(times), np.array(actual).reshape(-1, 6), completed, fault

    def _stream(
        self,
        cursor: PlanCursor,
        on_progress: ProgressCallback | None,
        journal: str | Path | None = None,
        *,
        override: bool,
    ) -> tuple[
        list[float], list[FloatArray], NDArray[np.int64], list[FloatArray], bool, str | None
    ]:
        """Follow the cursor's targets, one per controller period, as servoJ does; with
        ``override``, at the speed set (:meth:`set_speed`, :meth:`pause`).

        Returns
        -------
        times : list of float
        sent : list of ndarray of shape (6,)
            The targets sent.
        planned : ndarray of shape (K,), int
            The planned sample nearest the cursor at each one.
        actual : list of ndarray of shape (6,)
        completed : bool
        fault : str or None
        """
        n = len(cursor.q_rad)
        t0 = self.clock.now()
        self._stopping = False
        times: list[float] = []
        sent: list[FloatArray] = []
        planned: list[int] = []
        actual: list[FloatArray] = []
        fault: str | None = None
        completed = False
        writer = None if journal is None else JournalWriter(journal, capacity_samples=n)
        T_flange_tcp = transform_from_pose(self.tcp_pose)
        try:
            while True:
                if self._stop_requested.is_set():
                    fault = "stopped on request"
                    break
                if cursor.paused_too_long:
                    fault = f"stopped: paused for longer than {MAX_PAUSE_S / 60:.0f} min"
                    break
                target = cursor.here()
                self.clock.sleep_until(t0 + (len(times) + 1) * self._dt)
                self._advance(self.clock.now(), target=target)
                times.append(self.clock.now() - t0)
                sent.append(target)
                planned.append(cursor.index)
                actual.append(self._q.copy())
                if writer is not None:
                    tcp = pose_from_transform(kinematics.forward(self.arm, self._q) @ T_flange_tcp)
                    writer.add(times[-1], self._q, tcp, plan_s=cursor.plan_time_s)
                self.speed_now = cursor.fraction
                last = cursor.done
                if on_progress is not None and (len(times) % PROGRESS_EVERY == 1 or last):
                    on_progress(cursor.position / max(n - 1, 1))
                if last:
                    completed = True
                    break
                cursor.advance(self.speed_target if override else 1.0)
            # Decelerate (after a stop) or settle on the last sample.
            if self._settle(sent[-1] if completed else None) and completed:
                # Stopped while it settled: the arm braked short of the last sample.
                completed, fault = False, "stopped on request"
        except RobotError as error:
            index = np.array(planned, dtype=int)
            self._record(times, cursor.q_rad[index], actual, False, str(error), index)
            raise
        finally:
            if writer is not None:
                writer.close()
        return times, sent, np.array(planned, dtype=int), actual, completed, fault

    # -- physics ---------------------------------------------------------------------------------

    def _record(
        self,
        times: list[float],
        planned: ArrayLike,
        actual: list[FloatArray],
        completed: bool,
        fault: str | None,
        index: ArrayLike | None = None,
    ) -> ExecutionRecord:
        record = ExecutionRecord(
            t_s=np.array(times),
            q_planned_rad=np.array(planned).reshape(-1, 6),
            q_actual_rad=np.array(actual).reshape(-1, 6),
            completed=completed,
            fault=fault,
            planned_index=None if index is None else np.asarray(index, dtype=int),
        )
        self.last_record = record
        return record

    def _settle(self, goal: FloatArray | None) -> bool:
        """Keep feeding ``goal`` (or brake) until the buffered stream has run out and the arm
        rests; returns whether a stop came while it was still moving towards ``goal`` (the
        arm then braked short of it)."""
        stopped = False
        for i in range(int(1.0 / self._dt)):
            if i > self._delay + 2 and np.abs(self._qd).max() < 1e-5:
                break
            stopped = stopped or self._stopping or self._stop_requested.is_set()
            self.clock.sleep_until(self.clock.now() + self._dt)
            self._advance(self.clock.now(), target=goal)
        return stopped and goal is not None

    def _check_faults(self) -> None:
        now = self.clock.now()
        due = [f for f in self._faults if f.at_s <= now]
        for fault in due:
            self._faults.remove(fault)
            self._active = fault.error(fault.message)
        if self._active is not None:
            error = self._active
            if isinstance(error, ConnectionLostError):
                self._state = RobotState.DISCONNECTED
            self._fault(error)
            raise error

    def _advance(self, t_now: float, *, target: FloatArray | None) -> None:
        """Integrate the joints up to ``t_now`` following ``target`` (None: hold / brake)."""
        if self._t is None:
            raise ConnectionLostError("the simulated arm is not connected")
        stopped = isinstance(self._active, (ProtectiveStopError, EmergencyStopError))
        h = self._dt / SUBSTEPS
        steps = max(int(round((t_now - self._t) / h)), 0)
        braking = stopped or self._stopping or target is None
        if braking:
            self._buffer.clear()
        else:
            self._buffer.append(np.array(target, dtype=np.float64))
            del self._buffer[: -(self._delay + 3)]
        # The followed stream: the target from `delay` periods ago, with feed-forward velocity
        # and acceleration from its neighbours (padded with the oldest while the buffer fills).
        recent = self._buffer[-(self._delay + 3) :]
        recent = [recent[0]] * (self._delay + 3 - len(recent)) + recent if recent else []
        for _ in range(steps):
            if braking or not recent:
                acc = np.clip(-self._qd / h, -self._acc_max, self._acc_max)
            else:
                q_t = recent[0]
                qd_t = (recent[1] - recent[0]) / self._dt
                qdd_t = (recent[2] - 2 * recent[1] + recent[0]) / self._dt**2
                acc = qdd_t + 2 * self._omega * (qd_t - self._qd) + self._omega**2 * (q_t - self._q)
                acc = np.clip(acc, -self._acc_max, self._acc_max)
            self._qd = np.clip(self._qd + acc * h, -self.arm.qd_max_rad_s, self.arm.qd_max_rad_s)
            self._q = self._q + self._qd * h
            outside = (self._q < self.arm.q_min_rad) | (self._q > self.arm.q_max_rad)
            if np.any(outside) and not stopped:
                self._q = np.clip(self._q, self.arm.q_min_rad, self.arm.q_max_rad)
                self._qd[:] = 0.0
                joint = int(np.argmax(outside)) + 1
                self._active = ProtectiveStopError(f"joint {joint} reached its position limit")
                stopped = braking = True
        self._t = self._t + steps * h
        self._check_faults()


def _synchronised_trapezoid(
    start: FloatArray, goal: ArrayLike, speed: float, acceleration: float, dt: float
) -> FloatArray:
    """Joint targets (K, 6) of a moveJ: all joints start and stop together (trapezoidal speed
    of the leading joint)."""
    goal = np.asarray(goal, dtype=np.float64)
    distance = float(np.abs(goal - start).max())
    if distance < 1e-12:
        at_goal: FloatArray = goal[None].copy()
        return at_goal
    fractions = trapezoid_fractions(distance, speed, acceleration, dt)
    targets: FloatArray = start + (goal - start) * fractions[:, None]
    return targets


def trapezoid_fractions(
    distance: float, speed: float, acceleration: float, dt: float
) -> FloatArray:
    """Fractions (K,) of a move of ``distance`` done at each control period ``dt`` (s) with a
    trapezoidal speed profile (``speed`` and ``acceleration`` in distance units per s, s^2;
    triangular when the move is too short to reach ``speed``), from ``dt`` on. The last
    fraction is 1.

    Vectorised: the fake UR controller plans long moves with it inside its control tick.
    """
    if distance < 1e-12:
        return np.ones(1)
    t_total = trapezoid_duration(distance, speed, acceleration)
    t = np.arange(dt, t_total + dt, dt)
    position, _, _ = trapezoid(distance, speed, acceleration, t)
    fractions: FloatArray = position / distance
    return fractions


def _path_targets(path: CoarsePath, dt: float) -> FloatArray:
    """Joint targets every ``dt`` along the waypoints' joint-space polyline, shape (K, 6).

    The path parameter is the leading joint's travel (what moveJ's speed and acceleration
    apply to). Speed is capped per move, ramps at the path's acceleration, and falls to zero at
    waypoints without a blend and at both ends.
    """
    return _path_samples(path, dt)[0]


def _path_samples(path: CoarsePath, dt: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`_path_targets` (K, 6) with the path parameter of each target (K,) and of each
    waypoint (N,) (rad of leading-joint travel), so a caller can tell when a waypoint is
    passed."""
    q = path.q_rad
    length = np.abs(np.diff(q, axis=0)).max(axis=1)  # leading-joint travel per move
    knots = np.concatenate([[0.0], np.cumsum(length)])
    total = float(knots[-1])
    if total < 1e-12:
        return q[-1:].copy(), np.zeros(1), knots
    a = path.acceleration_rad_s2
    s = np.linspace(0.0, total, int(np.clip(total / 1e-4, 2, 20000)) + 1)
    move = np.clip(np.searchsorted(knots, s, side="right") - 1, 0, len(length) - 1)
    cap = path.speed_rad_s[1:][move]
    # Speed limits at the waypoints: 0 unless blended, then the slower of the two moves; made
    # consistent with the acceleration by a forward and a backward pass.
    at_knot = np.zeros(len(knots))
    blended = path.blend_m[1:-1] > 0
    at_knot[1:-1] = np.where(blended, np.minimum(path.speed_rad_s[1:-1], path.speed_rad_s[2:]), 0)
    for k in range(1, len(knots)):
        at_knot[k] = min(at_knot[k], np.sqrt(at_knot[k - 1] ** 2 + 2 * a * length[k - 1]))
    for k in range(len(knots) - 2, -1, -1):
        at_knot[k] = min(at_knot[k], np.sqrt(at_knot[k + 1] ** 2 + 2 * a * length[k]))
    # Within a move only its two waypoints' limits bind.
    from_start = np.sqrt(at_knot[move] ** 2 + 2 * a * (s - knots[move]))
    to_end = np.sqrt(at_knot[move + 1] ** 2 + 2 * a * np.maximum(knots[move + 1] - s, 0.0))
    speed = np.minimum(cap, np.minimum(from_start, to_end))
    # Time at each s: integrate ds / v with the trapezoid rule on the mean speed.
    mean = np.maximum(0.5 * (speed[1:] + speed[:-1]), 1e-9)
    t = np.concatenate([[0.0], np.cumsum(np.diff(s) / mean)])
    s_at = np.interp(np.arange(dt, t[-1] + dt, dt), t, s)
    move_at = np.clip(np.searchsorted(knots, s_at, side="right") - 1, 0, len(length) - 1)
    fraction = np.clip((s_at - knots[move_at]) / np.maximum(length[move_at], 1e-12), 0.0, 1.0)
    return q[move_at] + fraction[:, None] * (q[move_at + 1] - q[move_at]), s_at, knots


class SimMonitor(RobotMonitor):
    """The simulated arm's state: always reachable, running, at its configured start joints
    (a dry run simulates its own arm from the trajectory's first sample)."""

    kind = "sim"

    def __init__(self, config: SimConfig) -> None:
        self.config = config
        self.arm = kinematics.model(config.robot)

    def read(self) -> ArmState:
        q = np.asarray(self.config.q_start_rad, dtype=np.float64)
        return ArmState(
            backend="sim",
            reachable=True,
            robot_mode="SIMULATED",
            safety_status="NORMAL",
            remote_control=True,
            q_rad=tuple(float(v) for v in q),
            tcp_pose=tuple(float(v) for v in pose_from_transform(kinematics.forward(self.arm, q))),
        )

    def unlock_protective_stop(self) -> None:
        """Nothing to unlock: the simulated arm is never stopped between dry runs."""
