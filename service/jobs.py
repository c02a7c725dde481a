"""Jobs: CPU work in a pool of worker processes, never on the event loop.

A job is a row in the database (queued, running, succeeded, failed, cancelled; progress 0..1;
result or error) and, while it runs, a future of a process pool (spawn context: Open3D and numpy
hold the GIL for long stretches, and a separate process keeps the event loop answering). The
main process records each finished job's result. A job that was queued or running when the
service stopped is marked failed on the next start (``Store.fail_interrupted_jobs``).

A worker that dies (``kill -9``, the kernel's OOM killer) breaks the whole pool: the pool is
replaced at once, the jobs that were running fail with ``worker_died``, the jobs still queued
are handed to the new pool, and ``degraded`` is true until a new worker has answered. Workers
end themselves when the server process is gone (:func:`_watch_parent`), so a killed server
leaves no worker computing into its data folder.

CPU jobs report coarse progress (0 queued, 0.1 running, 1 done): the worker processes do not
talk back while they compute. Executions on a real arm report progress as samples are sent.
"""

from __future__ import annotations

import importlib
import logging
import multiprocessing
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Protocol

from drivers.isolation import lower_priority
from service.errors import ApiError, error_body, note_storage_fault
from service.store import FINISHED, JobRow, Store, now

log = logging.getLogger("teachpath.jobs")

#: Called in the main process with the task's return value; returns the job's result (the
#: ids of what it made) after recording the artifact.
OnSuccess = Callable[[Any], dict[str, Any]]

#: The error of a job whose worker process died under it.
WORKER_DIED = {
    "code": "worker_died",
    "message": "the worker process running this job died (killed, or out of memory); nothing "
    "was stored; run the job again, with a smaller input if it was the memory",
    "detail": None,
}


class Task(Protocol):
    """Work for a worker process: a picklable object (a frozen dataclass of its arguments, see
    :mod:`service.tasks`) whose ``run()`` does it there."""

    def run(self) -> Any: ...


def _run(task: Task) -> Any:
    """Runs in the worker process."""
    return task.run()


def _ready() -> int:
    """Runs in a new worker process: it is up."""
    return os.getpid()


@dataclass
class _Pending:
    """A submitted job this process still owns."""

    session_id: str
    task: Task
    on_success: OnSuccess
    future: Future[Any]
    generation: int  # of the pool it was handed to
    outputs: tuple[str, ...]  # the files its worker writes, removed when nothing records them
    discarded: bool = False  # stopped while running: its result is not recorded


#: What the jobs import on their first run: the pipelines, the reconstruction and planning code
#: with the libraries under them (SciPy, toppra), the plots (matplotlib), the dry run's simulated
#: arm. A warmed worker imports them as it starts, so that the operator's first job does not wait
#: for them (a first reconstruction of 1k / 100k points through the service took 5.1-5.7 s,
#: the next ones 2.4 s; warmed, the first 2.6 s: docs/guides/service.md).
WARM_MODULES = (
    "service.tasks",
    "service.plots",
    "recon.reconstruct",
    # The compiled kernels: a build that does not load is then logged at start-up, not at the
    # operator's first reconstruction.
    "recon._kernels",
    "recon.plan",
    # Planning imports toppra on first use (recon.toppra_import), not with recon.plan.
    "toppra",
    "recon.touches",
    "recon.calibrate",
    "drivers.robot.dryrun",
    "drivers.robot.sim",
)


class JobManager:
    """Runs jobs and keeps their rows current.

    Parameters
    ----------
    store : Store
    workers : int
        Worker processes.
    warm : bool
        Start the workers at once and have each import what the jobs need
        (``warm_modules``) before its first job; otherwise a worker starts with the first job
        it is needed for.
    warm_modules : tuple of str
        What a warm worker imports: :data:`WARM_MODULES`.
    """

    def __init__(
        self,
        store: Store,
        workers: int,
        *,
        warm: bool = False,
        warm_modules: tuple[str, ...] = WARM_MODULES,
    ) -> None:
        self.store = store
        self.workers = workers
        self.warm = warm
        self.warm_modules = warm_modules
        self._lock = threading.Lock()
        self._pending: dict[str, _Pending] = {}
        self._order: list[str] = []  # unfinished jobs, oldest first
        self._generation = 0
        self._lost: set[str] = set()  # jobs that were running in a pool that broke
        self._degraded = False
        self._closed = False
        self._pool = self._new_pool()
        #: When warm: one future per worker, done once that worker has started and imported
        #: what the jobs need (the pool starts its processes on demand: these start them now).
        self.warmed: list[Future[int]] = (
            [self._pool.submit(_ready) for _ in range(workers)] if warm else []
        )

    @property
    def degraded(self) -> bool:
        """True from a worker's death until a worker of the new pool has answered."""
        return self._degraded

    def submit(
        self,
        session_id: str,
        kind: str,
        params: dict[str, Any],
        task: Task,
        on_success: OnSuccess,
        *,
        outputs: tuple[str, ...] = (),
    ) -> JobRow:
        """Queue ``task`` in a worker process as a new job.

        ``outputs`` name the files the task writes, removed again if the job's result is not
        recorded (it failed, was cancelled, or its session was deleted).

        Raises
        ------
        ApiError
            503 ``workers_unavailable`` when no worker pool takes the work; no job row stays.
        """
        job = self.store.create_job(session_id, kind, params)
        try:
            with self._lock:
                future = self._dispatch(task)
                self._pending[job.id] = _Pending(
                    session_id, task, on_success, future, self._generation, tuple(outputs)
                )
                self._order.append(job.id)
                self._promote()
        except Exception:
            self.store.delete_job(job.id)  # nothing was submitted: no row for it
            raise
        future.add_done_callback(lambda f: self._finish(job.id, f))
        return self.store.job(job.id) or job  # as it stands now (promoted, perhaps finished)

    def cancel(self, job_id: str) -> JobRow:
        """Cancel a job that has not started.

        Raises
        ------
        ApiError
            409 if it is running or finished.
        """
        with self._lock:
            pending = self._pending.get(job_id)
        job = self.store.job(job_id)
        if pending is None or job is None or job.state in FINISHED:
            raise ApiError(409, "job_finished", f"job {job_id} has already finished")
        if not pending.future.cancel():
            raise ApiError(
                409,
                "job_running",
                f"job {job_id} is running and cannot be "
                "cancelled; stop the execution instead if it moves a robot",
            )
        return self.store.job(job_id) or job

    def discard(self, job_id: str) -> bool:
        """Stop a job's result from being recorded: queued, it is cancelled; running, it ends
        ``cancelled`` when its worker returns, with nothing recorded (a stopped dry run never
        counts as passed). Returns whether the job was unfinished here."""
        with self._lock:
            pending = self._pending.get(job_id)
            if pending is None:
                return False
            pending.discarded = True
        pending.future.cancel()
        return True

    def cancel_session(self, session_id: str) -> int:
        """Cancel the session's queued jobs; its running ones end ``cancelled`` when they
        return, with nothing recorded (:meth:`_finish` checks the session). Returns how many
        jobs the session had unfinished."""
        with self._lock:
            mine = [p for p in self._pending.values() if p.session_id == session_id]
        for pending in mine:
            pending.future.cancel()
        return len(mine)

    def shutdown(self) -> None:
        with self._lock:
            self._closed = True
            self._pool.shutdown(wait=False, cancel_futures=True)

    # -- internals ---------------------------------------------------------------------------

    def _new_pool(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            max_workers=self.workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_worker_init,
            initargs=(os.getpid(), self.warm_modules if self.warm else ()),
        )

    def _dispatch(self, task: Task) -> Future[Any]:
        """Hand ``task`` to the pool (the lock held); a pool found broken is replaced once."""
        if self._closed:
            raise ApiError(503, "shutting_down", "the service is stopping; try again shortly")
        try:
            return self._pool.submit(_run, task)
        except BrokenProcessPool:
            self._replace_locked(self._generation)
        try:
            return self._pool.submit(_run, task)
        except BrokenProcessPool:
            raise ApiError(
                503,
                "workers_unavailable",
                "the worker processes cannot be started; see the server's log",
            ) from None

    def _replace(self, generation: int) -> None:
        with self._lock:
            self._replace_locked(generation)

    def _replace_locked(self, generation: int) -> None:
        """Replace the pool of ``generation`` if it is still the current one (many futures of
        one broken pool report the same death)."""
        if generation != self._generation or self._closed:
            return
        log.error("a worker process died; replacing the worker pool")
        # The jobs the dead pool was running (the oldest, one per worker) are lost; the others
        # had not started and go to the new pool.
        self._lost.update(
            job_id
            for job_id in self._order[: self.workers]
            if self._pending[job_id].generation == generation
        )
        old = self._pool
        self._generation += 1
        self._degraded = True
        self._pool = self._new_pool()
        old.shutdown(wait=False, cancel_futures=True)
        generation_now = self._generation

        def answered(future: Future[int]) -> None:
            if future.exception() is None and generation_now == self._generation:
                self._degraded = False
                log.info("worker pool replaced")

        self._pool.submit(_ready).add_done_callback(answered)

    def _promote(self) -> None:
        """Mark as many of the oldest unfinished jobs running as there are workers."""
        for job_id in self._order[: self.workers]:
            row = self.store.job(job_id)
            if row is not None and row.state == "queued":
                self.store.update_job(job_id, state="running", progress=0.1, started_at=now())

    def _finish(self, job_id: str, future: Future[Any]) -> None:
        with self._lock:
            pending = self._pending.get(job_id)
        if pending is None or pending.future is not future:
            return  # a future of a pool this job has left
        recorded = False
        try:
            if isinstance(_exception(future), BrokenProcessPool) and self._requeue(job_id):
                return
            if self.store.session(pending.session_id) is None:
                # Deleted while the job was pending or running: nothing lands in it.
                self.store.update_job(
                    job_id,
                    state="cancelled",
                    finished_at=now(),
                    error={
                        "code": "session_deleted",
                        "message": "the session was deleted; the job's result was discarded",
                        "detail": None,
                    },
                )
            elif future.cancelled():
                self.store.update_job(job_id, state="cancelled", finished_at=now())
            elif pending.discarded:
                self.store.update_job(
                    job_id,
                    state="cancelled",
                    finished_at=now(),
                    error={
                        "code": "stopped",
                        "message": "stopped on request while it ran; its result was discarded",
                        "detail": None,
                    },
                )
            elif isinstance(future.exception(), BrokenProcessPool):
                self.store.update_job(job_id, state="failed", error=WORKER_DIED, finished_at=now())
            elif (error := future.exception()) is not None:
                note_storage_fault(self.store.faults, error)
                body = error_body(error)
                if body["code"] == "internal_error":
                    log.error("job %s failed", job_id, exc_info=error)
                self.store.update_job(job_id, state="failed", error=body, finished_at=now())
            else:
                result = pending.on_success(future.result())
                recorded = True
                self.store.update_job(
                    job_id, state="succeeded", progress=1.0, result=result, finished_at=now()
                )
        except Exception as error:  # recording the result failed: the job failed
            log.exception("recording the result of job %s failed", job_id)
            note_storage_fault(self.store.faults, error)
            self.store.update_job(
                job_id, state="failed", error=error_body(error), finished_at=now()
            )
        with self._lock:
            self._pending.pop(job_id, None)
            self._lost.discard(job_id)
            if job_id in self._order:
                self._order.remove(job_id)
            self._promote()
        if not recorded:
            for path in pending.outputs:
                _remove(path)

    def _requeue(self, job_id: str) -> bool:
        """After a worker's death: hand a job that had not started to the new pool. Returns
        False for a job that was running (it fails)."""
        with self._lock:
            pending = self._pending[job_id]
            self._replace_locked(pending.generation)
            if job_id in self._lost or self._closed:
                return False
            if self.store.session(pending.session_id) is None:
                return False
            future = self._dispatch(pending.task)
            pending.future, pending.generation = future, self._generation
        future.add_done_callback(lambda f: self._finish(job_id, f))
        return True


def _exception(future: Future[Any]) -> BaseException | None:
    return None if future.cancelled() else future.exception()


def _remove(path: str) -> None:
    try:
        os.remove(path)
    except FileNotFoundError:
        pass
    except OSError as exc:
        log.warning("could not remove %s: %s", path, exc)


def _worker_init(server_pid: int, warm_modules: tuple[str, ...]) -> None:
    """Runs first in each worker process: end with the server, lower its priority below the
    server's (:func:`drivers.isolation.lower_priority`), make every file it writes (arrays,
    preview pictures) private to the service's user, as the data folder is, and import
    ``warm_modules`` (at its lowered priority, beside a server that is answering; one that
    fails to import is logged and left to the job that needs it)."""
    os.umask(0o077)
    _watch_parent(server_pid)
    lower_priority()
    for name in warm_modules:
        try:
            importlib.import_module(name)
        except Exception:  # noqa: BLE001 - a warm-up must never break the pool
            # An initializer that raises breaks the whole pool (every job would fail as a dead
            # worker); unwarmed, the job that needs the module fails with its own error, as
            # before, and the others run.
            logging.getLogger("teachpath.jobs").exception("warming up: importing %s failed", name)


#: How often a worker looks whether the server is still there (s).
PARENT_POLL_S = 0.5


def _watch_parent(server_pid: int) -> None:
    """End this worker as soon as the server process is gone.

    A server killed with ``kill -9`` cannot tell its workers; an orphan went on computing and
    wrote files no artifact names. Linux's PR_SET_PDEATHSIG would fire when the *thread* that
    started the worker ends (any of the web server's pool threads), so a thread polls the parent
    instead. ``os._exit``: nothing of the unfinished work is flushed.
    """
    import time

    def watch() -> None:
        while True:
            time.sleep(PARENT_POLL_S)
            if os.getppid() != server_pid:
                os._exit(0)

    threading.Thread(target=watch, name="teachpath-parent-watch", daemon=True).start()
