"""The arm as the service sees it: its state, read all the time, and who owns it.

A thread polls the configured arm's monitor (:mod:`drivers.robot.monitor`: the simulated arm,
or a real one through ur_rtde's read-only clients) every ``robot_poll_s``. The latest reading
feeds ``GET /robot`` and its event stream, is where a plan starts from (the arm's joints at
planning time), and is what a real-arm execution checks before it starts: an arm moved away
from the plan's start, an arm in a protective stop, or an arm whose state is not known
(unreachable, or a reading older than :data:`FRESH_S`) refuses the execution.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.robot.base import BackendConfig, backend_config
from drivers.robot.monitor import ArmState, RobotMonitor, create_monitor
from recon.arrays import FloatArray
from service.errors import RobotUnavailable
from service.settings import Settings

if TYPE_CHECKING:
    from recon.kinematics import URModel

log = logging.getLogger("teachpath.robot")


def ur_rtde_config(settings: Settings, robot: str | None = None) -> BackendConfig:
    """The ur_rtde backend's settings for the arm at ``settings.ur_host`` (the monitor's, each
    run's and a recovered run's: one place).

    Parameters
    ----------
    settings : Settings
    robot : str, optional
        The arm's model when it is not ``settings.ur_robot`` (a recovered run's plan's).
    """
    return backend_config(
        "ur_rtde",
        host=settings.ur_host or "unknown",
        robot=robot or settings.ur_robot,
        watchdog_hz=settings.ur_watchdog_hz,
        stale_after_s=settings.ur_stale_after_s,
        rt_priority=settings.ur_rt_priority,
    )


#: A reading older than this does not count as the arm's state (s).
FRESH_S = 2.0
#: UR controllers refuse to unlock a protective stop sooner than this after it (s).
UNLOCK_AFTER_S = 5.0


@dataclass(frozen=True)
class Reading:
    """The latest reading and when it was taken.

    Attributes
    ----------
    state : ArmState
    at : float
        ``time.monotonic()`` of the reading.
    protective_stop_since : float or None
        ``time.monotonic()`` when the current protective stop was first seen.
    """

    state: ArmState
    at: float
    protective_stop_since: float | None

    @property
    def age_s(self) -> float:
        return time.monotonic() - self.at

    @property
    def fresh(self) -> bool:
        return self.state.reachable and self.age_s <= FRESH_S


class RobotWatch:
    """Polls the arm's monitor in a thread of its own.

    Parameters
    ----------
    settings : Settings
        ``ur_host`` set: the real arm; otherwise the simulated one at ``home_q_rad``.
    monitor : RobotMonitor, optional
        Instead of the one the settings name (tests).
    """

    def __init__(self, settings: Settings, monitor: RobotMonitor | None = None) -> None:
        self.settings = settings
        self.backend = "ur_rtde" if settings.ur_host else "sim"
        if monitor is None:
            if settings.ur_host:
                config = ur_rtde_config(settings)
            else:
                config = backend_config(
                    "sim", robot=settings.ur_robot, q_start_rad=tuple(settings.home_q_rad)
                )
            monitor = create_monitor(config)
        self.monitor = monitor
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        # One reading at a time: the monitor's link serves one command at a time, and a
        # reading asked for while another runs is the one after it (fresh for the asker).
        self._reading_lock = threading.Lock()
        self._reading = Reading(ArmState.unreachable(self.backend, "not read yet"), 0.0, None)
        self._version = 0
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, name="robot watch", daemon=True)
        # The arm's kinematic model, made on the first view with joints.
        self._arm: URModel | None = None

    def _joint_positions_m(self, state: ArmState) -> list[list[float]] | None:
        """Where the arm's joints are now (base frame, m), for the pendant's live arm: base, the
        DH frames 1..6 (6: the flange) from the joints read, then the TCP the controller
        reports. Shape (8, 3) as nested lists; (7, 3) without a TCP; None without joints."""
        if state.q_rad is None:
            return None
        from recon import kinematics

        if self._arm is None:
            arm = kinematics.model(self.settings.ur_robot)
            calibration = self.settings.arm_calibration
            self._arm = (
                arm if calibration is None else kinematics.with_calibration(arm, calibration)
            )
        q = np.asarray(state.q_rad, dtype=np.float64)
        if q.shape != (6,) or not np.isfinite(q).all():
            return None
        points = kinematics.joint_frames(self._arm, q)[:, :3, 3]
        if state.tcp_pose is not None and np.isfinite(state.tcp_pose[:3]).all():
            points = np.vstack([points, np.asarray(state.tcp_pose[:3], dtype=np.float64)])
        joints_m: list[list[float]] = np.round(points, 5).tolist()
        return joints_m

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._closing.set()
        self._thread.join(timeout=5)
        self.monitor.close()

    # -- reading ---------------------------------------------------------------------------------

    def _run(self) -> None:
        while not self._closing.is_set():
            self.poll()
            self._closing.wait(self.settings.robot_poll_s)

    def poll(self) -> Reading:
        """Read the arm now (the thread does this every ``robot_poll_s``)."""
        with self._reading_lock:
            return self._poll()

    def _poll(self) -> Reading:
        try:
            state = self.monitor.read()
        except Exception as exc:  # a monitor must not take the watch down; it reports why
            log.exception("reading the arm failed")
            state = ArmState.unreachable(self.backend, f"reading the arm failed: {exc}")
        with self._changed:
            previous = self._reading
            since = None
            if state.protective_stop:
                since = previous.protective_stop_since or time.monotonic()
            self._reading = Reading(state, time.monotonic(), since)
            if asdict(state) != asdict(previous.state):
                self._version += 1
                self._changed.notify_all()
            return self._reading

    def latest(self) -> Reading:
        with self._lock:
            return self._reading

    @property
    def version(self) -> int:
        """How many times the state has changed (a plain read: for the event loop, which must
        not wait on the watch's lock)."""
        return self._version

    def wait_change(self, version: int, timeout_s: float) -> tuple[int, Reading]:
        """Block until the state differs from ``version`` (or the timeout); returns the new
        version and reading."""
        with self._changed:
            if self._version == version:
                self._changed.wait(timeout_s)
            return self._version, self._reading

    def fresh(self) -> Reading:
        """The latest reading if it is fresh, else a new one (which may say unreachable)."""
        reading = self.latest()
        return reading if reading.fresh else self.poll()

    def unlock_protective_stop(self) -> None:
        """Ask the arm to unlock its protective stop (see :meth:`RobotMonitor.unlock...`)."""
        with self._reading_lock:
            self.monitor.unlock_protective_stop()
        self.poll()

    def view(self, owner: str | None) -> dict[str, Any]:
        """The state for the API (see :class:`service.schemas.RobotOut`)."""
        reading = self.latest()
        state = reading.state
        can_unlock_in = None
        if reading.protective_stop_since is not None:
            can_unlock_in = max(
                0.0, UNLOCK_AFTER_S - (time.monotonic() - reading.protective_stop_since)
            )
        return {
            **asdict(state),
            "q_rad": None if state.q_rad is None else list(state.q_rad),
            "joints_m": self._joint_positions_m(state),
            "tcp_pose": None if state.tcp_pose is None else list(state.tcp_pose),
            "payload_cog_m": None if state.payload_cog_m is None else list(state.payload_cog_m),
            "real_arm": self.backend != "sim",
            "robot": self.settings.ur_robot,
            "host": self.settings.ur_host,
            "age_s": round(reading.age_s, 3) if reading.at else None,
            "unlock_in_s": None if can_unlock_in is None else round(can_unlock_in, 2),
            "owner_execution_id": owner,
            "max_speed_m_s": self.settings.max_speed_m_s,
            "mount_up": list(self.settings.mount_up),
        }


def start_joints(watch: RobotWatch, settings: Settings) -> tuple[FloatArray, str]:
    """Where a plan starts when the request does not say: the real arm's joints now, or the
    simulated arm's home. Returns (joints, "arm" | "home").

    Raises
    ------
    RobotUnavailable
        A real arm is configured but its joints cannot be read now.
    """
    if watch.backend == "sim":
        return np.asarray(settings.home_q_rad, dtype=np.float64), "home"
    reading = watch.fresh()
    if not reading.fresh or reading.state.q_rad is None:
        raise RobotUnavailable(
            f"the arm's joints cannot be read ({reading.state.error or 'no fresh reading'}): "
            "a plan starts where the arm is; give start_q_rad, or connect the arm"
        )
    return np.asarray(reading.state.q_rad, dtype=np.float64), "arm"
