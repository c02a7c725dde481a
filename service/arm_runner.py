"""Executions on a real arm (or UR's simulator): one runner thread each, a ur_rtde worker
process underneath.

Dry runs on the simulated arm are ordinary CPU jobs (:class:`service.tasks.DryRun`); this
module is for ``backend="ur_rtde"``. The runner connects, enables, moves to the trajectory's
start, streams it and records what happened; ``stop()`` decelerates the arm. ur_rtde's
blocking calls run in the backend's own worker process (see ``drivers.robot.ur_rtde``), so
neither this thread nor the event loop can be frozen by a controller that stops answering.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from drivers.robot.base import RobotBackend
from recon.types import JointTrajectory
from service.errors import error_body
from service.store import Store, now

log = logging.getLogger("teachpath.executions")

#: Speed and acceleration of the move to the trajectory's start.
APPROACH_SPEED_RAD_S = 0.3
APPROACH_ACCELERATION_RAD_S2 = 0.5


class ExecutionRunner:
    """One execution: a thread that drives ``backend`` through ``trajectory``.

    ``record(execution_record, faults, duration_s)`` is called when it ends (also after a fault,
    with the record so far or None) and returns the job's result.
    """

    def __init__(
        self,
        store: Store,
        job_id: str,
        backend: RobotBackend,
        trajectory: JointTrajectory,
        record: Callable,
        *,
        mode: str = "servoj",
        tolerance_m: float = 5e-4,
    ) -> None:
        self.store, self.job_id = store, job_id
        self.mode, self.tolerance_m = mode, tolerance_m
        self.backend, self.trajectory, self.record = backend, trajectory, record
        self.thread = threading.Thread(target=self._run, name=f"execution {job_id}", daemon=True)
        self._last_progress = 0.0

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self.backend.stop()

    def _progress(self, fraction: float) -> None:
        if fraction - self._last_progress >= 0.01 or fraction >= 1.0:
            self._last_progress = fraction
            self.store.update_job(self.job_id, progress=round(0.1 + 0.9 * fraction, 4))

    def _run(self) -> None:
        self.store.update_job(self.job_id, state="running", progress=0.0, started_at=now())
        record = None
        started = time.monotonic()
        try:
            self.backend.connect()
            self.backend.enable()
            self.backend.move_joints(
                self.trajectory.q_rad[0],
                speed_rad_s=APPROACH_SPEED_RAD_S,
                acceleration_rad_s2=APPROACH_ACCELERATION_RAD_S2,
            )
            self.store.update_job(self.job_id, progress=0.1)
            if self.mode == "movepath":
                record = self.backend.execute_path(
                    self.trajectory, tolerance_m=self.tolerance_m, on_progress=self._progress
                )
            else:
                record = self.backend.execute(self.trajectory, on_progress=self._progress)
            faults = [record.fault] if record.fault else []
            result = self.record(record, faults, time.monotonic() - started)
            state = "succeeded" if record.completed else "cancelled"
            self.store.update_job(
                self.job_id,
                state=state,
                result=result,
                finished_at=now(),
                progress=1.0 if record.completed else self._last_progress,
            )
        except Exception as error:  # every failure ends the job, with what was recorded
            log.warning("execution job %s failed: %s", self.job_id, error)
            try:
                result = self.record(
                    record or getattr(self.backend, "last_record", None),
                    [str(error)],
                    time.monotonic() - started,
                )
            except Exception:
                log.exception("could not record the execution of job %s", self.job_id)
                result = None
            self.store.update_job(
                self.job_id,
                state="failed",
                error=error_body(error),
                result=result,
                finished_at=now(),
            )
        finally:
            closing = time.monotonic()
            try:
                self.backend.close()
            except Exception:
                log.exception(
                    "closing the robot after job %s took %.1f s and failed",
                    self.job_id,
                    time.monotonic() - closing,
                )
