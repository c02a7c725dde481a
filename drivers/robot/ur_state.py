"""The state of a UR arm through ur_rtde's receive interface and the dashboard server.

Read-only: no control interface is made, so no program is uploaded and nothing can move. The
clients live in a worker process (:mod:`drivers.worker`), made on the first reading and again
after the link breaks; every reading is bounded, and an arm that does not answer is a state
("unreachable") rather than an exception.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from drivers.errors import (
    ConnectionLostError,
    ProtectiveStopError,
    RobotError,
    WorkerError,
)
from drivers.registry import missing_dependency
from drivers.robot.monitor import ROBOT_MODES, SAFETY_MODES, ArmState, RobotMonitor
from drivers.worker import Command, WorkerClient, WorkerLink, WorkerServer

if TYPE_CHECKING:
    from drivers.robot.ur_rtde import URRtdeConfig

#: Bound on one reading (s); connecting is allowed longer.
READ_TIMEOUT_S = 2.0
CONNECT_TIMEOUT_S = 10.0
#: Without a new data package for this long the receive link counts as lost (s).
STALE_AFTER_S = 0.5
#: After the dashboard accepts an unlock, how long the controller may take to report the stop
#: cleared on the receive link (s); the dashboard answers "releasing" before it is done.
UNLOCK_CLEAR_TIMEOUT_S = 3.0


@dataclass(frozen=True)
class ReadState(Command):
    pass


@dataclass(frozen=True)
class UnlockProtectiveStop(Command):
    pass


class URMonitor(RobotMonitor):
    """Reads a UR controller's state (see the module docstring).

    Parameters
    ----------
    config : URRtdeConfig
        The backend's config (host, register range).
    """

    kind = "ur_rtde"

    def __init__(self, config: URRtdeConfig) -> None:
        self.config = config
        self._worker: WorkerClient | None = None

    def _client(self) -> WorkerClient:
        if self._worker is None or not self._worker.alive:
            self._worker = WorkerClient(
                "drivers.robot.ur_state:URStateServer",
                (self.config.host, self.config.upper_range_registers),
                name=f"ur_rtde monitor {self.config.host}",
                fallback=RobotError,
            )
        return self._worker

    def _drop(self) -> None:
        if self._worker is not None:
            self._worker.close(grace_s=0)
        self._worker = None

    def read(self) -> ArmState:
        fresh = self._worker is None
        try:
            reading = self._client().call(
                ReadState(), timeout_s=CONNECT_TIMEOUT_S if fresh else READ_TIMEOUT_S
            )
        except (RobotError, WorkerError) as exc:
            self._drop()  # connect again on the next reading
            return ArmState.unreachable("ur_rtde", f"{self.config.host}: {exc}")
        return ArmState(backend="ur_rtde", reachable=True, **reading)

    def unlock_protective_stop(self) -> None:
        try:
            self._client().call(UnlockProtectiveStop(), timeout_s=CONNECT_TIMEOUT_S)
        except WorkerError as exc:
            self._drop()
            raise ConnectionLostError(f"{self.config.host}: {exc}") from None

    def close(self) -> None:
        self._drop()


class URStateServer(WorkerServer):  # pragma: no cover - runs in the worker process
    """ur_rtde's receive and dashboard clients, in the worker process."""

    def __init__(self, link: WorkerLink, host: str, upper_range_registers: bool) -> None:
        super().__init__(link)
        self.host, self.upper = host, upper_range_registers
        # ur_rtde's clients (no type information), made by connect().
        self.receive: Any = None
        self.dashboard: Any = None

    def handlers(self) -> Mapping[type[Command], Callable[[Any], Any]]:
        return {ReadState: lambda _: self.read(), UnlockProtectiveStop: lambda _: self.unlock()}

    def translate(self, error: Exception) -> Exception:
        if isinstance(error, RuntimeError):  # ur_rtde reports lost connections as RuntimeError
            return ConnectionLostError(f"ur_rtde: {error}")
        return error

    def _connect(self) -> None:
        try:
            import dashboard_client
            import rtde_receive
        except ImportError as exc:
            raise missing_dependency(exc, "the ur_rtde robot monitor") from None
        try:
            self.receive = rtde_receive.RTDEReceiveInterface(
                self.host, use_upper_range_registers=self.upper
            )
            self.dashboard = dashboard_client.DashboardClient(self.host)
            self.dashboard.connect()
        except RuntimeError as exc:
            raise ConnectionLostError(f"cannot reach the controller: {exc}") from None

    def _wait_fresh(self) -> None:
        stamp = self.receive.getTimestamp()
        deadline = time.monotonic() + STALE_AFTER_S
        while self.receive.getTimestamp() == stamp:
            if time.monotonic() > deadline:
                raise ConnectionLostError(f"no new data from the controller for {STALE_AFTER_S} s")
            time.sleep(0.001)

    def read(self) -> dict[str, Any]:
        if self.receive is None:
            self._connect()
        self._wait_fresh()
        r, d = self.receive, self.dashboard
        return {
            "robot_mode": ROBOT_MODES.get(int(r.getRobotMode()), "UNKNOWN"),
            "safety_status": SAFETY_MODES.get(int(r.getSafetyMode()), "UNKNOWN"),
            "protective_stop": bool(r.isProtectiveStopped()),
            "emergency_stop": bool(r.isEmergencyStopped()),
            "remote_control": bool(d.isInRemoteControl()),
            "program_running": bool(d.running()),
            "q_rad": tuple(float(v) for v in r.getActualQ()),
            "tcp_pose": tuple(float(v) for v in r.getActualTCPPose()),
            # What the arm runs with when a plan sets no payload: shown before a run.
            "payload_kg": float(r.getPayload()),
            "payload_cog_m": tuple(float(v) for v in r.getPayloadCog()),
        }

    def unlock(self) -> None:
        if self.dashboard is None:
            self._connect()
        self.dashboard.closeSafetyPopup()
        try:
            self.dashboard.unlockProtectiveStop()
        except RuntimeError as exc:
            # The controller refuses within 5 s of the stop and while its cause persists.
            raise ProtectiveStopError(
                f"the controller refused to unlock the protective stop ({exc}); inspect its "
                "cause, wait at least 5 s after the stop, and unlock again"
            ) from None
        # Answer only once the receive link shows the stop cleared, so the state the caller
        # reads next is the unlocked one (not the last sample from before the release).
        deadline = time.monotonic() + UNLOCK_CLEAR_TIMEOUT_S
        self._wait_fresh()  # a stale link would hold the last (stopped) sample
        while self.receive.isProtectiveStopped():
            if time.monotonic() > deadline:
                raise ProtectiveStopError(
                    "the controller accepted the unlock but still reports a protective stop "
                    f"after {UNLOCK_CLEAR_TIMEOUT_S:g} s: remove its cause and unlock it at the "
                    "teach pendant"
                )
            self._wait_fresh()  # each look at a new sample; a link gone quiet is lost

    def shutdown(self) -> None:
        for client in (self.receive, self.dashboard):
            try:
                if client is not None:
                    client.disconnect()
            except RuntimeError:
                pass
