"""Executions on a real arm (or UR's simulator): one runner thread each, a ur_rtde worker
process underneath.

Dry runs on the simulated arm are ordinary CPU jobs (:class:`service.tasks.DryRun`); this
module is for ``backend="ur_rtde"``. The runner connects, enables, tells the controller the
tool, and runs the planned samples -- the whole motion, from where the arm stands, as it was
dry-run -- and nothing else: there is no move of its own to the start (an arm that is not at the
plan's start is refused). ur_rtde's blocking calls run in the backend's own worker process (see
``drivers.robot.ur_rtde``), so neither this thread nor the event loop can be frozen by a
controller that stops answering.

**A stop wins at any instant.** :meth:`ExecutionRunner.stop` latches the request on the runner
and on its backend (a new backend per execution, so a new execution starts unlatched). It is
checked before connecting, after every step and inside the backend's motion loops; once it is
acknowledged nothing moves any more. The job then ends ``cancelled`` with where it stopped.

Every sample is journalled to a file by the worker process as it arrives, so a crash of the
service keeps what was executed (see :func:`service.executions.recover`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from drivers.errors import MotionStoppedError
from drivers.robot.base import ExecutionRecord, RobotBackend
from drivers.robot.dryrun import reached_phase, stream_lag_s
from recon.arrays import FloatArray
from recon.trajectory import JointTrajectory
from service.errors import error_body, note_storage_fault
from service.store import Store, now

log = logging.getLogger("teachpath.executions")

#: The runner's steps, in order, as the job reports where it is.
STEPS = ("queued", "connecting", "enabling", "setting the tool", "moving")

#: ``(tcp_pose, payload_kg, payload_cog_m)``: the TCP in the flange frame (x, y, z, rx, ry, rz;
#: m and rad), the payload's mass (kg; None: the installation's payload stays) and its centre of
#: gravity (flange frame, m).
Tool = tuple[Sequence[float] | FloatArray, float | None, Sequence[float] | FloatArray]

#: ``record(execution_record, faults, stopped_in)``: stores the execution (its record so far, or
#: None; the faults; where it stopped, None when it completed) and returns the job's result.
Recorder = Callable[[ExecutionRecord | None, list[str], str | None], dict[str, Any]]

_T = TypeVar("_T")


class ExecutionRunner:
    """One execution: a thread that drives ``backend`` through ``trajectory``.

    Parameters
    ----------
    store : Store
    job_id : str
    backend : RobotBackend
        A fresh backend (its stop latch unset).
    trajectory : JointTrajectory
        The whole planned motion.
    record : Recorder
        ``record(execution_record, faults, stopped_in)`` is called once at the end (also after
        a fault or a stop, with the record so far or None) and returns the job's result.
    tool : Tool
        ``(tcp_pose, payload_kg, payload_cog_m)`` told to the controller before motion.
    journal : str
        Where the samples are written as they arrive.
    mode : {"servoj", "movepath"}
    tolerance_m : float
    approved_sha256, trajectory_id : str, optional
        The trajectory's file checksum and id, as approved: a resume after a pause is approved
        against them.
    """

    def __init__(
        self,
        store: Store,
        job_id: str,
        backend: RobotBackend,
        trajectory: JointTrajectory,
        record: Recorder,
        *,
        tool: Tool,
        journal: str,
        mode: str = "servoj",
        tolerance_m: float = 5e-4,
        approved_sha256: str | None = None,
        trajectory_id: str | None = None,
    ) -> None:
        self.store, self.job_id = store, job_id
        #: The trajectory (its id, and its file's checksum the run was approved with): a resume
        #: names the checksum again.
        self.trajectory_id, self.approved_sha256 = trajectory_id, approved_sha256
        self.mode, self.tolerance_m = mode, tolerance_m
        self.backend, self.trajectory, self.record = backend, trajectory, record
        self.tool, self.journal = tool, journal
        self.thread = threading.Thread(target=self._run, name=f"execution {job_id}", daemon=True)
        self._stop = threading.Event()
        self._last_progress = 0.0
        self.step = STEPS[0]

    @property
    def running(self) -> bool:
        """Whether the arm may still be moved by this execution."""
        return self.thread.is_alive() or not self.thread.ident

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        """Latch a stop (any thread, any time) and decelerate the arm if it moves."""
        self._stop.set()
        self.backend.stop()

    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    # -- speed override and pause (a servoJ stream only: a movePath is timed by the controller)

    @property
    def overridable(self) -> bool:
        """Whether this run's speed can be changed and the run paused: a servoJ stream, or a
        movePath on a backend that scales it with the controller's speed slider."""
        return self.mode == "servoj" or self.backend.speed_override_paths

    def set_speed(self, fraction: float) -> None:
        """The run's speed as a fraction of the planned speed (any time before its end).

        Raises
        ------
        ValueError
            Outside 5 % .. 100 %.
        """
        self.backend.set_speed(fraction)

    def pause(self) -> None:
        """Bring the arm to rest on its path; it holds there until :meth:`resume` or a stop."""
        self.backend.pause()

    def resume(self) -> None:
        self.backend.resume()

    def speed_view(self) -> dict[str, Any]:
        """The speed override as the safety bar shows it."""
        backend = self.backend
        return {
            "trajectory_id": self.trajectory_id,
            "approved_sha256": self.approved_sha256,
            "overridable": self.overridable,
            "speed_fraction": backend.speed_fraction,
            "paused": backend.paused,
            "speed_now": round(float(backend.speed_now), 4),
            "moving": self.step == "moving",
        }

    def _progress(self, fraction: float) -> None:
        if fraction - self._last_progress >= 0.01 or fraction >= 1.0:
            self._last_progress = fraction
            self._show_progress(self._shown(fraction))

    @staticmethod
    def _shown(fraction: float) -> float:
        """The job's progress for a share of the samples sent: a tenth for the start (the
        checks, the connection), then the samples."""
        return round(0.1 + 0.9 * fraction, 4)

    def _show_progress(self, progress: float) -> None:
        try:
            self.store.update_job(self.job_id, progress=progress)
        except Exception as error:
            # Progress is for showing: a busy or full database must never end a motion (the
            # samples go to the journal, not to the database).
            log.warning("progress of job %s not stored: %s", self.job_id, error)

    def _next(self, step: str) -> None:
        """Go on to ``step`` unless a stop was requested."""
        if self._stop.is_set():
            raise MotionStoppedError(f"stopped on request before {step}")
        self.step = step

    def _run(self) -> None:
        try:
            self.store.update_job(self.job_id, state="running", progress=0.0, started_at=now())
        except Exception as error:
            log.warning("job %s not marked running: %s", self.job_id, error)
        try:
            final = self._drive()
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
        # Only now is the arm released: a job that has ended owns the arm no more.
        _retrying(
            lambda: self.store.update_job(self.job_id, finished_at=now(), **final),
            f"the end of job {self.job_id}",
        )

    def _drive(self) -> dict[str, Any]:
        """Run the execution; return the job's final fields (state, result, error, progress)."""
        record: ExecutionRecord | None = None
        try:
            self._next("connecting")
            self.backend.connect()
            self._next("enabling")
            self.backend.enable()
            self._next("setting the tool")
            tcp_pose, payload_kg, cog_m = self.tool
            self.backend.set_tool(
                np.asarray(tcp_pose, dtype=np.float64),
                payload_kg=payload_kg,
                payload_cog_m=np.asarray(cog_m, dtype=np.float64),
            )
            self._next("moving")
            self._show_progress(0.1)
            if self.mode == "movepath":
                record = self.backend.execute_path(
                    self.trajectory,
                    tolerance_m=self.tolerance_m,
                    on_progress=self._progress,
                    journal=self.journal,
                )
            else:
                record = self.backend.execute(
                    self.trajectory, on_progress=self._progress, journal=self.journal
                )
            return self._ended(record, [record.fault] if record.fault else [])
        except Exception as error:  # every failure ends the job, with what was recorded
            record = self._with_journal(
                record or getattr(self.backend, "last_record", None), str(error)
            )
            if isinstance(error, MotionStoppedError) or self._stop.is_set():
                return self._ended(record, [str(error)])
            log.warning("execution job %s failed: %s", self.job_id, error)
            result = self._record(record, [str(error)], self.where(record))
            note_storage_fault(self.store.faults, error)  # /health reports it, as for jobs
            return {"state": "failed", "error": error_body(error), "result": result}

    def _ended(self, record: ExecutionRecord | None, faults: list[str]) -> dict[str, Any]:
        """Record the execution; the job succeeded, or was cancelled by a stop.

        One verdict for the job and its record: an execution whose arm arrived and settled on
        its last sample has completed, even when a Stop came in after that (the job and the
        record then both say completed; "cancelled" with a completed record said two things).
        A Stop while the arm still settles is a stop: the backend's record is not completed."""
        completed = record is not None and record.completed
        if not completed:
            record = self._with_journal(record, "; ".join(faults) or "stopped")
        stopped_in = None if completed else self.where(record)
        result = self._record(record, faults, stopped_in)
        return {
            "state": "succeeded" if completed else "cancelled",
            "result": result,
            # Where the arm got to, on the same scale as while it ran (the samples' share
            # alone went back from 63 % to 54 % at a stop).
            "progress": 1.0 if completed else self._shown(self._last_progress),
        }

    def _with_journal(self, record: ExecutionRecord | None, fault: str) -> ExecutionRecord | None:
        """The record, or what the journal holds where it holds more: a fault inside the
        backend (a protective stop, a lost link) can leave no record of the samples its worker
        journalled, and an execution that moved must never be recorded as "before moving"."""
        try:
            from_journal = journal_record(self.trajectory, self.journal, fault)
        except Exception as error:  # an unreadable journal: keep what the backend returned
            log.warning("the journal of job %s cannot be read: %s", self.job_id, error)
            return record
        if from_journal is not None and (record is None or len(from_journal) > len(record)):
            return from_journal
        return record

    def _record(
        self, record: ExecutionRecord | None, faults: list[str], stopped_in: str | None
    ) -> dict[str, Any] | None:
        """Store the execution's record (retried while the database is busy); None if it
        could not be stored, in which case the journal stays for the next start to recover."""
        return _retrying(
            lambda: self.record(record, faults, stopped_in),
            f"the record of job {self.job_id} (its journal is kept for the next start)",
        )

    def where(self, record: ExecutionRecord | None) -> str:
        """Where the execution got to: a step before motion, or the phase the arm was in at
        its last sample (the report's rule: :func:`drivers.robot.dryrun.reached_phase`)."""
        if record is None or len(record) == 0:
            return f"before moving ({self.step})"
        lag_s = stream_lag_s(self.mode, self.backend.config.lookahead_s)
        return reached_phase(self.trajectory, record, lag_s)


#: How long the runner keeps trying to store an execution's end while the database is busy
#: (SQLite waits 30 s per attempt on its own); after that the journal is the record.
RECORD_RETRY_S = 120.0


def _retrying(write: Callable[[], _T], what: str) -> _T | None:
    """``write()``, retried with backoff for :data:`RECORD_RETRY_S`; None if it never took."""
    deadline, pause = time.monotonic() + RECORD_RETRY_S, 0.5
    while True:
        try:
            return write()
        except Exception as error:
            if time.monotonic() + pause > deadline:
                log.error("could not store %s: %s", what, error)
                return None
            log.warning("storing %s failed (%s); retrying in %.1f s", what, error, pause)
            time.sleep(pause)
            pause = min(pause * 2, 10.0)


def journal_record(
    trajectory: JointTrajectory, journal: str | Path, fault: str
) -> ExecutionRecord | None:
    """An execution's record rebuilt from its journal (each actual sample paired with the
    planned sample it was sent towards: the same time, unless the run was slowed or paused),
    or None when the journal is absent or empty.

    Raises
    ------
    InputFileError
        A journal whose complete lines are not samples.
    """
    from drivers.robot.journal import read_journal_with_plan

    if not Path(journal).is_file():
        return None
    t_s, q, tcp, plan_s = read_journal_with_plan(journal)
    if len(t_s) == 0:
        return None
    index = np.clip(np.rint(plan_s / trajectory.period_s), 0, len(trajectory) - 1).astype(int)
    return ExecutionRecord(
        planned_index=index,
        t_s=t_s,
        q_planned_rad=trajectory.q_rad[index],
        q_actual_rad=q,
        completed=False,
        fault=fault,
        tcp_actual=tcp,
    )
