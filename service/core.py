"""The small bundle every workflow takes: settings, store, job manager and the live runners.

The workflows (``inputs``, ``reconstructions``, ``trajectories``, ``executions``, ``captures``)
are plain functions of a :class:`Services` and a request; the routers only hand them over. Things
that run in threads of this process (an execution on a real arm, a capture) are kept in
:class:`LiveRunners` so a stop request or the shutdown can reach them.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from service.errors import ApiError, not_found
from service.jobs import JobManager
from service.parse_lane import ParseLane
from service.robot import RobotWatch
from service.settings import Settings
from service.store import ArtifactRow, SessionRow, Store
from service.uploads import UploadBudget

if TYPE_CHECKING:
    from service.arm_runner import ExecutionRunner
    from service.capture_runner import CaptureRunner


@dataclass
class LiveRunners:
    """Runners that live in this process, by id.

    Attributes
    ----------
    executions : dict of str to ExecutionRunner
        Real-arm executions by execution id, while they run.
    execution_jobs : dict of str to str
        Execution id -> job id, for every execution started by this process.
    captures : dict of str to CaptureRunner
        Captures by capture id, while they run.
    event_streams : int
        Open ``/robot/events`` streams.
    """

    executions: dict[str, ExecutionRunner] = field(default_factory=dict)
    execution_jobs: dict[str, str] = field(default_factory=dict)
    captures: dict[str, CaptureRunner] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)
    #: Open ``/robot/events`` streams (changed on the event loop only), and of those, the
    #: ones without the token.
    event_streams: int = 0
    anonymous_streams: int = 0

    def arm_owner(self) -> str | None:
        """The execution that owns the real arm now (call with :attr:`lock` held)."""
        for execution_id, runner in self.executions.items():
            if runner.running:
                return execution_id
        return None

    def stop_all(self) -> None:
        """Stop every arm and capture (at shutdown)."""
        with self.lock:
            executions, captures = list(self.executions.values()), list(self.captures.values())
        for runner in executions:
            runner.stop()
        for capture in captures:
            capture.stop()


@dataclass
class Services:
    """What a workflow needs.

    Attributes
    ----------
    settings : Settings
    store : Store
    jobs : JobManager
    token : str
        The access token every route but ``/health`` checks.
    robot : RobotWatch
        The arm's state, read all the time.
    live : LiveRunners
    uploads : UploadBudget
        The bytes of uploads in flight (capped at ``settings.max_uploads_in_flight_mb``).
    parses : ParseLane
        Where uploads are parsed (``settings.max_parallel_parses`` at once).
    """

    settings: Settings
    store: Store
    jobs: JobManager
    token: str
    robot: RobotWatch
    live: LiveRunners = field(default_factory=LiveRunners)
    uploads: UploadBudget = field(init=False)
    parses: ParseLane = field(init=False)

    def __post_init__(self) -> None:
        self.uploads = UploadBudget(self.settings.max_uploads_in_flight_mb)
        self.parses = ParseLane(self.settings.max_parallel_parses)

    def session(self, session_id: str) -> SessionRow:
        """The session, or a 404."""
        row = self.store.session(session_id)
        if row is None:
            raise not_found("session", session_id)
        return row

    def artifact(self, session_id: str, kind: str, artifact_id: str) -> ArtifactRow:
        """An artifact of a session, or a 404."""
        self.session(session_id)
        row = self.store.artifact(artifact_id, kind=kind, session_id=session_id)
        if row is None:
            raise not_found(kind, artifact_id)
        return row

    def delete_session(self, session_id: str) -> None:
        """Soft-delete a session: it disappears from the API, its data stays on disk. Its
        queued jobs are cancelled, its running ones discard their results and its captures stop
        (their samples are not kept). A session whose execution is running on the arm is not
        deleted (409 ``session_owns_arm``): stop it first; its record must land somewhere."""
        from service.store import now

        self.session(session_id)
        with self.live.lock:
            moving = [
                execution_id
                for execution_id, runner in self.live.executions.items()
                if runner.running
                and self._job_session(self.live.execution_jobs.get(execution_id)) == session_id
            ]
            if moving:
                # Deleting under a running arm would leave its record without a session.
                raise ApiError(
                    409,
                    "session_owns_arm",
                    f"execution {moving[0]} of this session is running on the arm: stop it "
                    f"(POST /executions/{moving[0]}/stop), wait for it to end, then delete the "
                    "session",
                    detail={"execution_id": moving[0]},
                )
            # Under the lock: an execution starting now finds the session deleted.
            self.store.update_session(session_id, deleted_at=now())
        self.jobs.cancel_session(session_id)
        with self.live.lock:
            executions = [
                runner
                for execution_id, runner in self.live.executions.items()
                if self._job_session(self.live.execution_jobs.get(execution_id)) == session_id
            ]
            captures = [
                runner
                for capture_id, runner in self.live.captures.items()
                if (row := self.store.capture(capture_id)) is not None
                and row.session_id == session_id
            ]
        for runner in executions + captures:
            runner.stop()

    def _job_session(self, job_id: str | None) -> str | None:
        job = None if job_id is None else self.store.job(job_id)
        return None if job is None else job.session_id

    def array_path(self, artifact_id: str, suffix: str = "npz") -> str:
        """Where a worker writes the file of a new artifact (absolute)."""
        return str(self.store.data_dir / "arrays" / f"{artifact_id}.{suffix}")

    def record_when_done(
        self,
        session_id: str,
        kind: str,
        artifact_id: str,
        *,
        inputs: dict[str, Any],
        params: dict[str, Any],
        result: Callable[[dict[str, Any]], dict[str, Any]],
    ) -> Callable[[dict[str, Any]], dict[str, Any]]:
        """What a job does with its task's summary when it succeeds: record the artifact whose
        file the worker wrote at :meth:`array_path`, and return the job's ``result(summary)``."""

        def done(summary: dict[str, Any]) -> dict[str, Any]:
            self.store.add_file_artifact(
                artifact_id=artifact_id,
                session_id=session_id,
                kind=kind,
                path=f"arrays/{artifact_id}.npz",
                inputs=inputs,
                params=params,
                summary=summary,
            )
            return result(summary)

        return done

    def close(self) -> None:
        self.live.stop_all()
        self.robot.close()
        self.jobs.shutdown()
        self.store.engine.dispose()
