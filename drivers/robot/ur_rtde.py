"""A real UR arm (or UR's simulator) through ur_rtde, from a dedicated worker process.

ur_rtde's constructors and blocking calls hold the Python GIL while they wait on the network: a
controller that does not answer would freeze every thread of the calling process. So the
client lives in a worker process started for this backend (:class:`drivers.worker.WorkerClient`
serving :class:`URRtdeServer`); the parent sends it typed commands (:class:`Connect`,
:class:`MoveJ`, :class:`Execute`, ...) and waits for each answer with a bound
(:class:`~drivers.errors.RobotTimeoutError`, and the worker is killed). Errors come back as
their ``drivers.errors`` class. A stop request is the worker's stop event, which the server
checks every control period, so it works while the worker is busy streaming.

Execution streams the trajectory with servoJ at the controller rate (initPeriod/waitPeriod) and
records the actual joints every period; :meth:`~drivers.robot.base.RobotBackend.execute_path`
sends coarse blended moveJ waypoints as one movePath instead. Stopping decelerates with
servoStop / stopJ.

The speed override and pause reach both: the servoJ stream is retimed here
(:mod:`drivers.robot.timescale`); a movePath is scaled by the controller's speed slider
(RTDEIOInterface.setSpeedSlider, 0 to pause), never above the slider as the run found it, and
the slider is put back when the run ends.

Enabling does not power the arm on or release its brakes unless ``power_on`` is set: on a shop
floor that is the operator's decision, at the teach pendant.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from drivers.errors import (
    ConnectionLostError,
    EmergencyStopError,
    NotEnabledError,
    ProtectiveStopError,
    RobotError,
    RobotTimeoutError,
    WorkerError,
    WorkerLostError,
    WorkerTimeoutError,
)
from drivers.registry import missing_dependency
from drivers.robot.base import (
    BackendConfig,
    ExecutionRecord,
    ProgressCallback,
    RobotBackend,
    RobotState,
)
from drivers.robot.clock import Clock
from drivers.robot.journal import JournalWriter
from drivers.robot.timescale import MAX_PAUSE_S, PlanCursor
from drivers.worker import Command, WorkerClient, WorkerLink, WorkerServer
from recon.arrays import FloatArray
from recon.trajectory import JointTrajectory
from recon.waypoints import CoarsePath

#: UR robot modes (RTDE robot_mode) and safety modes used here.
ROBOT_MODE_IDLE = 5
ROBOT_MODE_RUNNING = 7
#: Bound on powering on and releasing the brakes (s).
POWER_ON_TIMEOUT_S = 25.0
SAFETY_MODE_NORMAL = 1
#: Progress is reported every this many samples.
PROGRESS_EVERY = 50
#: A movePath run reports where it is and its speed at least this often (s), paused too.
PATH_REPORT_S = 0.2
#: Without new data from the controller for this long, the link counts as lost (ur_rtde itself
#: gives up on a socket after 2.5 s of silence).
STALE_AFTER_S = 0.5
#: Bound on the control script starting after an upload (s).
SCRIPT_START_TIMEOUT_S = 5.0
#: The RTDE watchdog's frequency between motions: the arm rests, and the control script may
#: idle that long (100 s) between jobs before the controller stops it (the next job's enable
#: starts it again).
IDLE_WATCHDOG_HZ = 0.01
#: How long close() lets the worker disconnect its clients before it is killed (s).
CLOSE_GRACE_S = 2.0
#: The arm rests on a target when within this (rad) and slower than this (rad/s).
SETTLED_RAD = 1e-4
SETTLED_RAD_S = 1e-3
#: Attempts at reading joints and pose from one packet (a packet lands every 2-8 ms).
SAMPLE_READS = 3


class URRtdeConfig(BackendConfig):
    """Settings of the ur_rtde backend."""

    kind: Literal["ur_rtde"] = "ur_rtde"
    host: str = Field(..., description="controller address")
    connect_timeout_s: float = Field(10.0, gt=0, description="bound on connecting")
    command_timeout_s: float = Field(5.0, gt=0, description="bound on a non-motion command")
    motion_margin_s: float = Field(
        10.0,
        gt=0,
        description="motion may take this much longer than planned before it counts as hung",
    )
    motion_slack: float = Field(
        0.25,
        ge=0,
        le=10,
        description="and this fraction of the planned time on top (a client that falls behind "
        "the controller's clock stretches a long stream)",
    )
    power_on: bool = Field(False, description="enable() powers on and releases the brakes")
    upper_range_registers: bool = Field(False, description="use RTDE registers 24-47")
    stop_deceleration_rad_s2: float = Field(4.0, gt=0, le=40.0)
    # Half a second: a worker that stalls that long is hung (the servo loop's longest period
    # measured 11 ms), and a busy machine's scheduling hiccups stay well inside it.
    watchdog_hz: float = Field(
        2.0,
        ge=0.5,
        le=100.0,
        description="during a motion the controller's own RTDE watchdog stops the program when "
        "this process has written nothing for 1/watchdog_hz s (a hung or killed worker: the "
        "controller runs movePath and moveJ on its own); between motions it is relaxed",
    )
    stale_after_s: float = Field(
        STALE_AFTER_S,
        gt=0,
        le=5.0,
        description="a run stops (servoStop) and fails when the controller's state has not "
        "changed for this long: the link counts as lost",
    )
    rt_priority: int = Field(
        80,
        ge=0,
        le=99,
        description="realtime priority (SCHED_FIFO) of the servoJ loop and of ur_rtde's own "
        "threads while streaming; 0: normal priority. Without the privilege the run goes on "
        "at normal priority and its record says so",
    )


# -- the commands the worker serves --------------------------------------------------------------


@dataclass(frozen=True)
class Connect(Command):
    """Open the receive and dashboard links (and the control link if the arm runs)."""


@dataclass(frozen=True)
class Enable(Command):
    """Power on if allowed, release the brakes, start the control script."""


@dataclass(frozen=True)
class Disable(Command):
    """Stop the control script."""


@dataclass(frozen=True)
class Close(Command):
    """Stop motion and the control script before the worker ends."""


@dataclass(frozen=True)
class ReadQ(Command):
    """The actual joints (rad), from a data package newer than the command."""


@dataclass(frozen=True)
class Unlock(Command):
    """Clear a protective stop and restart the control script."""


@dataclass(frozen=True)
class MoveJ(Command):
    """moveJ to ``q`` (rad) at ``speed`` (rad/s) and ``acceleration`` (rad/s^2)."""

    q: list[float]
    speed: float
    acceleration: float


class _RealtimePriority(contextlib.AbstractContextManager["_RealtimePriority"]):
    """The streaming thread at a realtime priority (SCHED_FIFO) while it streams, as ur_rtde's
    examples run their servo loops; put back after. ``status`` says what it got: a system
    without the privilege (CAP_SYS_NICE, or a container without it) streams at normal
    priority and the execution's record says so."""

    def __init__(self, priority: int) -> None:
        self.priority, self.status = priority, "normal priority (not asked)"
        self._before: tuple[int, os.sched_param] | None = None

    def __enter__(self) -> _RealtimePriority:
        if self.priority <= 0:
            return self
        if not hasattr(os, "sched_setscheduler"):
            self.status = "normal priority (no realtime scheduling on this system)"
            return self
        try:
            self._before = (os.sched_getscheduler(0), os.sched_getparam(0))
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.priority))
            self.status = f"realtime priority {self.priority} (SCHED_FIFO)"
        except OSError as exc:
            self._before = None
            self.status = (
                f"normal priority: realtime priority {self.priority} refused ({exc.strerror}; "
                "give the service CAP_SYS_NICE)"
            )
        return self

    def __exit__(self, *exc: object) -> None:
        if self._before is not None:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, *self._before)


@dataclass(frozen=True)
class Execute(Command):
    """Stream ``q_rows`` (K lists of 6 joints, rad) with servoJ every ``period_s``, at the speed
    the client's dial sets (:mod:`drivers.robot.timescale`, within ``qdd_max`` rad/s^2 per
    joint); with a ``journal`` path, write every sample there as it is taken."""

    q_rows: list[list[float]]
    period_s: float
    qdd_max: list[float]
    journal: str | None = None


@dataclass(frozen=True)
class SetTool(Command):
    """The TCP (x, y, z, rx, ry, rz in the flange frame) and the payload (kg, centre of
    gravity in the flange frame, m)."""

    tcp_pose: list[float]
    payload_kg: float | None  # None: not set (the installation's stays)
    cog_m: list[float]


@dataclass(frozen=True)
class MovePath(Command):
    """Blended moveJ waypoints as one movePath (samples journalled as in :class:`Execute`)."""

    q_rows: list[list[float]]
    speeds: list[float]
    acceleration: float
    blends: list[float]
    journal: str | None = None


class URRtdeBackend(RobotBackend):
    """A UR controller through ur_rtde (see the module docstring)."""

    kind = "ur_rtde"
    config_class = URRtdeConfig
    config: URRtdeConfig
    speed_override_paths = True  # movePath through the controller's speed slider

    def __init__(self, config: URRtdeConfig, *, clock: Clock | None = None) -> None:
        super().__init__(config, clock=clock)
        self._worker: WorkerClient | None = None

    # -- the worker ------------------------------------------------------------------------------

    def _start_worker(self) -> None:
        self._worker = WorkerClient(
            "drivers.robot.ur_rtde:URRtdeServer",
            (self.config.model_dump(),),
            name=f"ur_rtde {self.config.host}",
            fallback=RobotError,
        )
        self._send_speed()

    def _send_speed(self) -> None:
        worker = self._worker
        if worker is not None:
            worker.dial.value = self.speed_target

    def _kill_worker(self) -> None:
        # Without its worker the backend has no link: it must be connect()ed again (the base
        # class only marks ConnectionLostError so; a timeout leaves the link just as dead).
        self._state = RobotState.DISCONNECTED
        if self._worker is not None:
            self._worker.close(grace_s=0)
        self._worker = None

    def _call(
        self,
        command: Command,
        *,
        timeout_s: float | None = None,
        on_progress: Callable[[Any], None] | None = None,
        quiet_s: float | None = None,
    ) -> Any:
        if self._worker is None:
            raise ConnectionLostError("no connection to the controller: connect() first")
        timeout = self.config.command_timeout_s if timeout_s is None else timeout_s
        try:
            return self._worker.call(
                command, timeout_s=timeout, on_progress=on_progress, quiet_s=quiet_s
            )
        except WorkerTimeoutError:
            self._kill_worker()  # the client has ended it; the link is gone with it
            raise RobotTimeoutError(
                f"the controller at {self.config.host} did not answer {command.label()} within "
                f"{timeout:.1f} s; check the network and the arm, then reconnect"
            ) from None
        except WorkerLostError:
            self._kill_worker()
            raise ConnectionLostError("the ur_rtde worker stopped unexpectedly") from None
        except WorkerError as exc:
            raise RobotError(str(exc)) from None
        except RobotError as error:
            self._fault(error)
            if isinstance(error, ConnectionLostError):
                # The worker's ur_rtde may still hold the controller's RTDE input
                # registers, which a new connection then cannot claim (IN_USE).
                self._kill_worker()
            raise

    # -- hooks -----------------------------------------------------------------------------------

    def _connect(self) -> None:
        self._kill_worker()  # a worker left from a lost link must not hold the registers
        self._start_worker()
        try:
            self._call(Connect(), timeout_s=self.config.connect_timeout_s)
        except Exception:  # a missing ur_rtde too: no worker is left behind
            self._kill_worker()
            raise

    def _enable(self) -> None:
        # Powering on, releasing the brakes and starting the control script.
        bound = POWER_ON_TIMEOUT_S + self.config.connect_timeout_s
        self._call(Enable(), timeout_s=max(self.config.command_timeout_s, bound))

    def _disable(self) -> None:
        self._call(Disable())

    def _close(self) -> None:
        worker = self._worker
        if worker is not None:
            try:
                self._call(Close())
            except RobotError:
                pass  # closing anyway
        if self._worker is not None:
            # Let the worker disconnect its clients (the controller frees the registers at
            # once), then end it whatever it does.
            self._worker.close(grace_s=CLOSE_GRACE_S)
        self._kill_worker()

    def _motion_bound_s(self, planned_s: float) -> float:
        """How long a motion planned to take ``planned_s`` may run before it counts as hung."""
        return planned_s * (1.0 + self.config.motion_slack) + self.config.motion_margin_s

    def _read_q(self) -> FloatArray:
        return np.array(self._call(ReadQ()), dtype=np.float64)

    def _move_joints(self, q: FloatArray, speed: float, acceleration: float) -> None:
        distance = float(np.abs(q - self._read_q()).max())
        expected = distance / speed + speed / acceleration
        self._call(
            MoveJ(list(map(float, q)), speed, acceleration),
            timeout_s=self._motion_bound_s(expected),
        )

    def _set_tool(self, tcp_pose: FloatArray, payload_kg: float | None, cog_m: FloatArray) -> None:
        self._call(SetTool(list(map(float, tcp_pose)), payload_kg, list(map(float, cog_m))))

    def _execute(
        self,
        trajectory: JointTrajectory,
        on_progress: ProgressCallback | None,
        journal: str | Path | None,
    ) -> ExecutionRecord:
        last = max(len(trajectory) - 1, 1)

        def progress(report: tuple[float, float]) -> None:
            position, self.speed_now = report
            if on_progress is not None:
                on_progress(position / last)

        try:
            times, actual, tcp, planned, completed, fault, realtime = self._call(
                Execute(
                    trajectory.q_rad.tolist(),
                    trajectory.period_s,
                    trajectory.arm.qdd_max_rad_s2.tolist(),
                    None if journal is None else str(journal),
                ),
                timeout_s=self._motion_bound_s(trajectory.duration_s),
                on_progress=progress,
                # Slowed or paused, a run takes longer than planned: the stream reports every
                # PROGRESS_EVERY periods, paused too, and silence beyond the margin is a hang.
                quiet_s=self._motion_bound_s(0.0),
            )
        except RobotError:
            self.last_record = ExecutionRecord(
                np.zeros(0), np.zeros((0, 6)), np.zeros((0, 6)), False, "interrupted"
            )
            raise
        planned_index = np.asarray(planned, dtype=int).reshape(-1)
        return ExecutionRecord(
            t_s=np.array(times),
            planned_index=planned_index,
            q_planned_rad=trajectory.q_rad[planned_index],
            q_actual_rad=np.array(actual).reshape(-1, 6),
            completed=completed,
            fault=fault,
            tcp_actual=np.array(tcp).reshape(-1, 6),
            realtime=realtime,
        )

    def _execute_path(
        self, path: CoarsePath, on_progress: ProgressCallback | None, journal: str | Path | None
    ) -> tuple[FloatArray, FloatArray, bool, str | None]:
        def progress(report: tuple[int, float]) -> None:
            position, self.speed_now = report
            if on_progress is not None:
                on_progress(position / len(path))

        # The controller's own timing may run longer than the plan (it stops where it cannot
        # blend): allow the slowest move profile on top of the margin.
        lead = np.abs(np.diff(path.q_rad, axis=0)).max(axis=1)
        expected_s = float(
            np.sum(lead / path.speed_rad_s[1:] + path.speed_rad_s[1:] / path.acceleration_rad_s2)
        )
        try:
            times, actual, completed, fault = self._call(
                MovePath(
                    path.q_rad.tolist(),
                    path.speed_rad_s.tolist(),
                    path.acceleration_rad_s2,
                    path.blend_m.tolist(),
                    None if journal is None else str(journal),
                ),
                timeout_s=self._motion_bound_s(expected_s),
                on_progress=progress,
                # Slowed or paused by the speed slider, a path takes longer than planned: the
                # worker reports every PATH_REPORT_S, paused too; silence beyond the margin is
                # a hang.
                quiet_s=self._motion_bound_s(0.0),
            )
        except RobotError:
            self.last_record = ExecutionRecord(
                np.zeros(0), np.zeros((0, 6)), np.zeros((0, 6)), False, "interrupted"
            )
            raise
        return np.array(times), np.array(actual).reshape(-1, 6), completed, fault

    def _stop(self) -> None:
        worker = self._worker
        if worker is not None:
            worker.stop_event.set()

    def _clear_stop(self) -> None:
        worker = self._worker
        if worker is not None:
            worker.stop_event.clear()

    def _unlock_protective_stop(self) -> None:
        self._call(Unlock(), timeout_s=max(self.config.command_timeout_s, 10.0))


# -- the child process ---------------------------------------------------------------------------


class _SpeedSlider:  # pragma: no cover - runs in the worker process
    """The controller's speed slider during a movePath run: the run's speed override, never
    above the slider as the run found it (the operator may have turned it down on the teach
    pendant), and put back as found when the run ends.

    Parameters
    ----------
    io : rtde_io.RTDEIOInterface
    found : float
        The slider's value at the start (RTDE target_speed_fraction, 0..1).
    """

    def __init__(self, io: Any, found: float) -> None:
        self.io = io
        self.found = min(max(found, 0.0), 1.0) if found == found else 1.0  # NaN: untouched
        self.wanted = self.found
        self.sent: float | None = None

    def follow(self, override: float) -> None:
        """Set the slider to ``override`` (0..1, 0: pause) within what it was found at."""
        self.wanted = min(self.found, max(float(override), 0.0))
        if self.wanted != self.sent:
            if not self.io.setSpeedSlider(self.wanted):
                raise ConnectionLostError("the controller refused the speed slider; reconnect")
            self.sent = self.wanted

    def share(self, receive: Any) -> float:
        """The controller's speed scaling now, as a share of the slider as found: what the
        override reads (1 when the run goes at the speed it would have gone without it; a
        pendant's slider turned down before the run is the operator's, shown on the pendant)."""
        scaling = float(receive.getSpeedScaling())
        return min(scaling / self.found, 1.0) if self.found > 0 else 0.0

    def restore(self) -> None:
        """The slider as the run found it (only if this run changed it)."""
        if self.sent is not None and self.sent != self.found:
            self.io.setSpeedSlider(self.found)


class URRtdeServer(WorkerServer):  # pragma: no cover - runs in the worker process
    """The ur_rtde clients, in the worker process; one method per command.

    Parameters
    ----------
    link : WorkerLink
    config : dict
        The backend's :class:`URRtdeConfig`, dumped.
    """

    def __init__(self, link: WorkerLink, config: dict[str, Any]) -> None:
        super().__init__(link)
        self.config = config
        self.stop_event = link.stop_event
        # ur_rtde's RTDEControlInterface, RTDEReceiveInterface and DashboardClient once
        # connected (None before): a compiled library without type information, hence Any.
        self.control: Any = None
        self.receive: Any = None
        self.dashboard: Any = None
        self.io: Any = None  # RTDEIOInterface: the speed slider, for movePath runs

    def handlers(self) -> Mapping[type[Command], Callable[[Any], Any]]:
        return {
            Connect: lambda _: self.connect(),
            Enable: lambda _: self.enable(),
            Disable: lambda _: self.disable(),
            Close: lambda _: self.close(),
            ReadQ: lambda _: self.read_q(),
            Unlock: lambda _: self.unlock(),
            MoveJ: lambda c: self.move_j(c.q, c.speed, c.acceleration),
            SetTool: lambda c: self.set_tool(c.tcp_pose, c.payload_kg, c.cog_m),
            Execute: lambda c: self.execute(c.q_rows, c.period_s, c.qdd_max, c.journal),
            MovePath: lambda c: self.move_path(
                c.q_rows, c.speeds, c.acceleration, c.blends, c.journal
            ),
        }

    def translate(self, error: Exception) -> Exception:
        if isinstance(error, RuntimeError):  # ur_rtde reports lost connections as RuntimeError
            return ConnectionLostError(f"ur_rtde: {error}")
        return error

    def connect(self) -> None:
        """The receive and dashboard links; the control link too if the arm is running.

        ur_rtde's control interface uploads its script and waits for it to run, which a
        powered-off arm never does: for such an arm it is made by :meth:`enable`, after the
        arm is powered on.
        """
        try:
            import dashboard_client
            import rtde_receive
        except ImportError as exc:
            raise missing_dependency(exc, "the ur_rtde robot backend") from None
        host = self.config["host"]
        try:
            self.receive = rtde_receive.RTDEReceiveInterface(
                host,
                use_upper_range_registers=self.config["upper_range_registers"],
                rt_priority=int(self.config["rt_priority"]),
            )
            self.dashboard = dashboard_client.DashboardClient(host)
            self.dashboard.connect()
        except RuntimeError as exc:
            raise ConnectionLostError(
                f"cannot connect to the controller at {host}: {exc}"
            ) from None
        self._wait_fresh()
        if self.receive.getRobotMode() == ROBOT_MODE_RUNNING:
            self._connect_control()

    def _connect_control(self) -> None:
        import rtde_control

        host = self.config["host"]
        flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        if host != "127.0.0.1":
            # ur_rtde only skips its remote-control query for 127.0.0.1; local mode is the
            # operator's choice, checked by the dashboard below instead.
            flags |= rtde_control.RTDEControlInterface.FLAG_DISABLE_REMOTE_CONTROL_CHECK
        if self.config["upper_range_registers"]:
            flags |= rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
        try:
            # ur_rtde's own threads at the same realtime priority (0: its default).
            self.control = rtde_control.RTDEControlInterface(
                host, -1.0, flags, 50002, int(self.config["rt_priority"])
            )
        except RuntimeError as exc:
            raise ConnectionLostError(
                f"cannot start ur_rtde's control script at {host}: {exc}"
            ) from None

    def _check_fresh(self) -> None:
        """The receive thread can die while isConnected() still says yes and the getters return
        the last values: watch the controller's timestamp instead."""
        stamp = self.receive.getTimestamp()
        now = time.monotonic()
        if stamp != getattr(self, "_last_stamp", None):
            self._last_stamp, self._last_fresh = stamp, now
        elif now - getattr(self, "_last_fresh", now) > self._stale_after_s():
            self.control.servoStop(self.config["stop_deceleration_rad_s2"])
            raise ConnectionLostError(
                f"no new data from the controller for {self._stale_after_s()} s; reconnect"
            )

    def _stale_after_s(self) -> float:
        return float(self.config.get("stale_after_s", STALE_AFTER_S))

    def _safety(self) -> None:
        if self.receive.isEmergencyStopped():
            raise EmergencyStopError("the emergency stop is engaged")
        if self.receive.isProtectiveStopped():
            raise ProtectiveStopError("the arm is in a protective stop")

    def _wait_fresh(self) -> None:
        """Wait for a data package newer than the call (one control period, 2-8 ms): the
        getters keep returning the last values after the controller stops answering."""
        stamp = self.receive.getTimestamp()
        deadline = time.monotonic() + self._stale_after_s()
        while self.receive.getTimestamp() == stamp:
            if time.monotonic() > deadline:
                raise ConnectionLostError(
                    f"no new data from the controller for {self._stale_after_s()} s; reconnect",
                )
            time.sleep(0.001)

    def _refused(self) -> None:
        """A command was refused: a safety stop (which stops the control script) is the likely
        cause and is reported as such; otherwise the caller reports a lost script."""
        try:
            self._wait_fresh()
        except ConnectionLostError:
            pass  # no fresh data either: the caller's connection error stands
        self._safety()

    def read_q(self) -> list[float]:
        self._wait_fresh()
        self._safety()
        return list(self.receive.getActualQ())

    def enable(self) -> None:
        self._safety()
        if self.receive.getRobotMode() != ROBOT_MODE_RUNNING:
            if not self.config["power_on"]:
                raise NotEnabledError(
                    "the arm is not running: power it on and release "
                    "the brakes at the teach pendant (or set power_on)",
                )
            deadline = time.monotonic() + POWER_ON_TIMEOUT_S
            if self.receive.getRobotMode() < ROBOT_MODE_IDLE:
                self.dashboard.powerOn()
                # The controller boots the arm before it takes a brake release.
                self._wait_for_mode(ROBOT_MODE_IDLE, deadline)
            self.dashboard.brakeRelease()
            self._wait_for_mode(ROBOT_MODE_RUNNING, deadline)
        if self.control is None:
            self._connect_control()
        self._ensure_script_running()

    def _wait_for_mode(self, mode: int, deadline: float) -> None:
        """Wait until the robot mode is at least ``mode`` (UR's modes count up from power off
        through idle to running), or fail at ``deadline``."""
        while self.receive.getRobotMode() < mode:
            if time.monotonic() > deadline:
                raise NotEnabledError(
                    f"the arm did not reach robot mode {mode} within {POWER_ON_TIMEOUT_S:.0f} s "
                    f"of powering on (mode {self.receive.getRobotMode()}); check the pendant",
                )
            self._safety()
            time.sleep(0.05)

    def _ensure_script_running(self) -> None:
        """(Re)start ur_rtde's control script if it is not running, and wait until it is.

        reuploadScript() returns as soon as the script is sent, before the controller reports
        it running; a command sent in between is refused (moveJ returns False).
        """
        if self.control.isProgramRunning():
            return
        self.control.reuploadScript()
        deadline = time.monotonic() + SCRIPT_START_TIMEOUT_S
        while not self.control.isProgramRunning():
            if time.monotonic() > deadline:
                raise NotEnabledError(
                    f"the control script did not start within {SCRIPT_START_TIMEOUT_S} s "
                    "(is the arm in remote control, powered and free of safety stops?)",
                )
            time.sleep(0.01)

    def disable(self) -> None:
        if self.control is not None:
            self.control.stopScript()

    def unlock(self) -> None:
        self.dashboard.closeSafetyPopup()
        try:
            self.dashboard.unlockProtectiveStop()
        except RuntimeError as exc:
            # The controller refuses within 5 s of the stop (and while its cause persists);
            # that is still a protective stop, not a lost link.
            raise ProtectiveStopError(
                f"the controller refused to unlock the protective stop ({exc}); inspect its "
                "cause, wait at least 5 s after the stop, and unlock again",
            ) from None
        # A protective stop stops the control script: once the controller reports the stop
        # cleared, start the script again so the next move is not refused.
        deadline = time.monotonic() + SCRIPT_START_TIMEOUT_S
        while self.receive.isProtectiveStopped():
            if time.monotonic() > deadline:
                raise ProtectiveStopError(
                    "the protective stop did not clear: remove its cause and unlock it at the "
                    "teach pendant",
                )
            time.sleep(0.01)
        self._ensure_script_running()

    def _watchdog(self, frequency_hz: float) -> None:
        """Set the controller's RTDE watchdog (ur_rtde's setWatchdog: the control script's
        ``rtde_set_watchdog`` on its command register, action "stop"). Every command and
        :meth:`_kick` feeds it."""
        if not self.control.setWatchdog(frequency_hz):
            self._refused()
            raise ConnectionLostError("the controller refused setWatchdog; reconnect")

    @contextlib.contextmanager
    def _watched(self) -> Iterator[None]:
        """The watchdog at ``watchdog_hz`` for one motion, relaxed to
        :data:`IDLE_WATCHDOG_HZ` after it (the arm rests; the script may idle between jobs)."""
        self._watchdog(float(self.config["watchdog_hz"]))
        try:
            yield
        finally:
            try:
                self.control.setWatchdog(IDLE_WATCHDOG_HZ)
            except RuntimeError:
                pass  # the link is gone: the controller's watchdog stops the script itself

    def _kick(self) -> None:
        self.control.kickWatchdog()

    def move_j(self, q: list[float], speed: float, acceleration: float) -> None:
        self._safety()
        if self.stop_event.is_set():
            return  # a stop came before the command: nothing is sent
        with self._watched():
            if self.stop_event.is_set():
                return  # a stop came while the watchdog was set: the move is never sent
            if not self.control.moveJ(q, speed, acceleration, True):
                self._refused()
                raise ConnectionLostError(
                    "the controller refused moveJ (is the control script running?); reconnect",
                )
            while self.control.getAsyncOperationProgressEx().isAsyncOperationRunning():
                if self.stop_event.is_set():
                    self.control.stopJ(self.config["stop_deceleration_rad_s2"])
                    return
                self._safety()
                self._kick()
                time.sleep(0.01)

    def set_tool(self, tcp_pose: list[float], payload_kg: float | None, cog_m: list[float]) -> None:
        self._safety()
        if not self.control.setTcp(tcp_pose):
            self._refused()
            raise ConnectionLostError("the controller refused setTcp; reconnect")
        if payload_kg is not None and not self.control.setPayload(payload_kg, cog_m):
            self._refused()
            raise ConnectionLostError("the controller refused setPayload; reconnect")

    def execute(
        self,
        q_rows: list[list[float]],
        period_s: float,
        qdd_max: list[float],
        journal: str | None = None,
    ) -> tuple[list[float], list[list[float]], list[list[float]], list[int], bool, str | None, str]:
        dial = self.link.dial
        cursor = PlanCursor(
            np.asarray(q_rows, dtype=np.float64),
            period_s,
            qdd_max,
            start_fraction=1.0 if dial is None else dial.value,
        )
        with contextlib.ExitStack() as stack:
            # Mapped up front for a run at half the planned speed: the loop's journal write is
            # a memory store. A run slowed further or paused maps more as it goes, doubling:
            # one period then takes longer (measured 4 ms to 60,000 rows, 11 ms to 300,000),
            # well within servoJ's lookahead.
            writer = (
                None
                if journal is None
                else stack.enter_context(JournalWriter(journal, capacity_samples=2 * len(q_rows)))
            )
            realtime = stack.enter_context(
                _RealtimePriority(int(self.config.get("rt_priority", 0)))
            )
            stack.enter_context(self._watched())  # every servoJ feeds it
            return (*self._stream(cursor, writer), realtime.status)

    def _stream(
        self, cursor: PlanCursor, writer: JournalWriter | None
    ) -> tuple[list[float], list[list[float]], list[list[float]], list[int], bool, str | None]:
        """servoJ the cursor's position every period, advancing it at the dial's speed."""
        lookahead, gain = self.config["lookahead_s"], self.config["gain"]
        period_s = cursor.period_s
        times, actual, tcp, planned, fault, completed = [], [], [], [], None, False
        start = time.monotonic()
        dial = self.link.dial
        while True:
            if self.stop_event.is_set():
                fault = "stopped on request"
                break
            if cursor.paused_too_long:
                fault = f"stopped: paused for longer than {MAX_PAUSE_S / 60:.0f} min"
                break
            q = cursor.here().tolist()
            t_cycle = self.control.initPeriod()
            # Positional only: ur_rtde's binding names these arguments arg0..arg5.
            if not self.control.servoJ(q, 0.0, 0.0, period_s, lookahead, gain):
                self.control.servoStop(self.config["stop_deceleration_rad_s2"])
                self._refused()
                raise ConnectionLostError(
                    "the controller refused servoJ (the control script stopped); reconnect",
                )
            times.append(time.monotonic() - start)
            planned.append(cursor.index)
            q_now, tcp_now = self._sample()
            actual.append(q_now)
            tcp.append(tcp_now)
            if writer is not None:
                writer.add(times[-1], actual[-1], tcp[-1], plan_s=cursor.plan_time_s)
            self._check_fresh()
            if self.receive.isProtectiveStopped():
                fault = "protective stop"
                break
            if len(times) % PROGRESS_EVERY == 1:
                self.link.progress((cursor.position, cursor.fraction))
            if cursor.done:
                break
            cursor.advance(dial.value if dial is not None else 1.0)
            self.control.waitPeriod(t_cycle)
        if cursor.done and fault is None:
            completed = True
            cut_short = self._hold(cursor.here().tolist(), period_s)
            # The hold ends early on a safety stop or a Stop: then the arm did not arrive.
            if self.receive.isProtectiveStopped():
                completed, fault = False, "protective stop"
            elif cut_short:
                completed, fault = False, "stopped on request"
        self.control.servoStop(self.config["stop_deceleration_rad_s2"])
        if completed:
            self._safety()
        self.link.progress((cursor.position, cursor.fraction))
        if fault == "protective stop":
            raise ProtectiveStopError("protective stop during execution")
        return times, actual, tcp, planned, completed, fault

    def _sample(self) -> tuple[list[float], list[float]]:
        """The actual joints and TCP pose from one RTDE packet.

        The receive interface updates in its own thread between two getter calls; a journal
        line whose pose belongs to the next packet contradicts its joints (seen: 0.2 mm at
        speed). Re-read until the joints are the same on both sides of the pose read.
        """
        q_before = list(self.receive.getActualQ())
        for _ in range(SAMPLE_READS):
            tcp = list(self.receive.getActualTCPPose())
            q_after = list(self.receive.getActualQ())
            if q_after == q_before:
                break
            q_before = q_after
        return q_after, tcp

    def _hold(self, q: list[float], period_s: float) -> bool:
        """Keep servoing the last sample until the arm rests on it; returns whether a stop
        request ended it before (the arm then brakes short of the sample).

        servoJ follows its targets a lookahead behind; a servoStop right after the last sample
        would brake the arm short of it (measured on the fake controller: 15 mrad on the
        contract test's line). Bounded by the lookahead plus half a second; a stop request or a
        protective stop ends it early.
        """
        lookahead, gain = self.config["lookahead_s"], self.config["gain"]
        for _ in range(int((lookahead + 0.5) / period_s)):
            if self.stop_event.is_set():
                return True
            if self.receive.isProtectiveStopped():
                return False
            t_cycle = self.control.initPeriod()
            if not self.control.servoJ(q, 0.0, 0.0, period_s, lookahead, gain):
                self._refused()
                raise ConnectionLostError(
                    "the controller refused servoJ on the last sample (the control script "
                    "stopped); reconnect",
                )
            error = np.abs(np.asarray(self.receive.getActualQ()) - q).max()
            if error < SETTLED_RAD and np.abs(self.receive.getActualQd()).max() < SETTLED_RAD_S:
                return False
            self.control.waitPeriod(t_cycle)
        return False

    def move_path(
        self,
        q_rows: list[list[float]],
        speeds: list[float],
        acceleration: float,
        blends: list[float],
        journal: str | None = None,
    ) -> tuple[list[float], list[list[float]], bool, str | None]:
        """Run blended moveJ waypoints as one controller-side path (ur_rtde movePath)."""
        with contextlib.ExitStack() as stack:
            writer = None if journal is None else stack.enter_context(JournalWriter(journal))
            return self._move_path(q_rows, speeds, acceleration, blends, writer)

    def _move_path(
        self,
        q_rows: list[list[float]],
        speeds: list[float],
        acceleration: float,
        blends: list[float],
        writer: JournalWriter | None,
    ) -> tuple[list[float], list[list[float]], bool, str | None]:
        import rtde_control

        self._safety()
        path = rtde_control.Path()
        for q, speed, blend in zip(q_rows, speeds, blends, strict=True):
            path.addEntry(
                rtde_control.PathEntry(
                    rtde_control.PathEntry.MoveJ,
                    rtde_control.PathEntry.PositionJoints,
                    [*q, speed, acceleration, blend],
                )
            )
        if self.stop_event.is_set():
            # A stop came while the path was built or sent here: the command is never sent.
            return [], [], False, "stopped on request"
        slider = _SpeedSlider(self._io(), float(self.receive.getTargetSpeedFraction()))
        try:
            with self._watched():
                return self._follow_path(path, q_rows, writer, slider)
        finally:
            slider.restore()

    def _io(self) -> Any:
        """ur_rtde's RTDEIOInterface (the speed slider), connected on first use: its
        constructor blocks this process for a moment, never the service's."""
        if self.io is None:
            import rtde_io

            try:
                self.io = rtde_io.RTDEIOInterface(
                    self.config["host"], False, self.config["upper_range_registers"]
                )
            except RuntimeError as exc:
                raise ConnectionLostError(
                    f"cannot reach the controller's speed slider at {self.config['host']}: {exc}"
                ) from None
        return self.io

    def _follow_path(
        self,
        path: Any,
        q_rows: list[list[float]],
        writer: JournalWriter | None,
        slider: _SpeedSlider,
    ) -> tuple[list[float], list[list[float]], bool, str | None]:
        """Send the path and sample the arm until it ends, kicking the watchdog: the
        controller runs the path on its own, and stops it when this process goes quiet. The
        client's dial (speed override, 0 while paused) goes to the controller's speed slider,
        which scales the path along its own way."""
        if self.stop_event.is_set():
            # A stop came while the watchdog was set: the path is never sent.
            return [], [], False, "stopped on request"
        if not self.control.movePath(path, True):
            self._refused()
            raise ConnectionLostError(
                "the controller refused movePath (the control script stopped); reconnect",
            )
        times, actual, tcp, fault, completed = [], [], [], None, False
        start = time.monotonic()
        period_s = 1.0 / 125.0  # sampling the actual joints; the controller runs the path
        reported, reported_at = -1, start
        dial = self.link.dial
        paused_since: float | None = None
        while True:
            slider.follow(1.0 if dial is None else dial.value)
            status = self.control.getAsyncOperationProgressEx()
            times.append(time.monotonic() - start)
            q_now, tcp_now = self._sample()
            actual.append(q_now)
            tcp.append(tcp_now)
            if writer is not None:
                writer.add(times[-1], actual[-1], tcp[-1])
            self._check_fresh()
            if not status.isAsyncOperationRunning():
                completed = True
                break
            if self.stop_event.is_set():
                self.control.stopJ(self.config["stop_deceleration_rad_s2"])
                fault = "stopped on request"
                break
            if self.receive.isProtectiveStopped():
                raise ProtectiveStopError("protective stop during the path")
            now = time.monotonic()
            paused_since = None if slider.wanted > 0 else (paused_since or now)
            if paused_since is not None and now - paused_since > MAX_PAUSE_S:
                self.control.stopJ(self.config["stop_deceleration_rad_s2"])
                fault = f"stopped: paused for longer than {MAX_PAUSE_S / 60:.0f} min"
                break
            if status.progress() != reported or now - reported_at > PATH_REPORT_S:
                reported, reported_at = status.progress(), now
                self.link.progress((max(reported, 0), slider.share(self.receive)))
            self._kick()
            time.sleep(period_s)
        done_at = len(q_rows) if completed else max(reported, 0)
        self.link.progress((done_at, slider.share(self.receive)))
        return times, actual, completed, fault

    def close(self) -> None:
        if self.control is not None:
            self.control.servoStop(self.config["stop_deceleration_rad_s2"])
            self.control.stopScript()

    def shutdown(self) -> None:
        for client in (self.control, self.receive, self.io):
            if client is not None:
                try:
                    client.disconnect()
                except RuntimeError:
                    pass
        if self.dashboard is not None:
            try:
                self.dashboard.disconnect()
            except RuntimeError:
                pass
