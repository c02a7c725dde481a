"""Jobs: CPU work in a pool of worker processes, never on the event loop.

A job is a row in the database (queued, running, succeeded, failed, cancelled; progress 0..1;
result or error) and, while it runs, a future of a process pool (spawn context: Open3D and numpy
hold the GIL for long stretches, and a separate process keeps the event loop answering). The
main process records each finished job's result. A job that was queued or running when the
service stopped is marked failed on the next start (``Store.fail_interrupted_jobs``).

CPU jobs report coarse progress (0 queued, 0.1 running, 1 done): the worker processes do not
talk back while they compute. Executions on a real arm report progress as samples are sent.
"""

from __future__ import annotations

import logging
import multiprocessing
import threading
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, Protocol

from service.errors import ApiError, error_body
from service.store import FINISHED, JobRow, Store, now

log = logging.getLogger("teachpath.jobs")

#: Called in the main process with the task's return value; returns the job's result (the
#: ids of what it made) after recording the artifact.
OnSuccess = Callable[[Any], dict]


class Task(Protocol):
    """Work for a worker process: a picklable object (a frozen dataclass of its arguments, see
    :mod:`service.tasks`) whose ``run()`` does it there."""

    def run(self) -> Any: ...


def _run(task: Task) -> Any:
    """Runs in the worker process."""
    return task.run()


class JobManager:
    """Runs jobs and keeps their rows current.

    Parameters
    ----------
    store : Store
    workers : int
        Worker processes.
    """

    def __init__(self, store: Store, workers: int) -> None:
        self.store = store
        self.workers = workers
        self._pool = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_worker_init,
        )
        self._lock = threading.Lock()
        self._futures: dict[str, Future] = {}
        self._order: list[str] = []  # unfinished jobs, oldest first

    def submit(
        self,
        session_id: str,
        kind: str,
        params: dict,
        task: Task,
        on_success: OnSuccess,
    ) -> JobRow:
        """Queue ``task`` in a worker process as a new job."""
        job = self.store.create_job(session_id, kind, params)
        with self._lock:
            future = self._pool.submit(_run, task)
            self._futures[job.id] = future
            self._order.append(job.id)
            self._promote()
        future.add_done_callback(lambda f: self._finish(job.id, f, on_success))
        return self.store.job(job.id)

    def cancel(self, job_id: str) -> JobRow:
        """Cancel a job that has not started.

        Raises
        ------
        ApiError
            409 if it is running or finished.
        """
        with self._lock:
            future = self._futures.get(job_id)
        job = self.store.job(job_id)
        if future is None or job is None or job.state in FINISHED:
            raise ApiError(409, "job_finished", f"job {job_id} has already finished")
        if not future.cancel():
            raise ApiError(
                409,
                "job_running",
                f"job {job_id} is running and cannot be "
                "cancelled; stop the execution instead if it moves a robot",
            )
        return self.store.job(job_id)

    async def run(self, task: Task):
        """Await ``task`` in a worker process (for work a request waits on, such as parsing an
        upload: Open3D's readers hold the GIL)."""
        import asyncio

        return await asyncio.get_running_loop().run_in_executor(self._pool, _run, task)

    def shutdown(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)

    # -- internals ---------------------------------------------------------------------------

    def _promote(self) -> None:
        """Mark as many of the oldest unfinished jobs running as there are workers."""
        for job_id in self._order[: self.workers]:
            row = self.store.job(job_id)
            if row is not None and row.state == "queued":
                self.store.update_job(job_id, state="running", progress=0.1, started_at=now())

    def _finish(self, job_id: str, future: Future, on_success: OnSuccess) -> None:
        try:
            if future.cancelled():
                self.store.update_job(job_id, state="cancelled", finished_at=now())
            elif future.exception() is not None:
                error = future.exception()
                body = error_body(error)
                if body["code"] == "internal_error":
                    log.error("job %s failed", job_id, exc_info=error)
                self.store.update_job(job_id, state="failed", error=body, finished_at=now())
            else:
                result = on_success(future.result())
                self.store.update_job(
                    job_id, state="succeeded", progress=1.0, result=result, finished_at=now()
                )
        except Exception as error:  # recording the result failed: the job failed
            log.exception("recording the result of job %s failed", job_id)
            self.store.update_job(
                job_id, state="failed", error=error_body(error), finished_at=now()
            )
        finally:
            with self._lock:
                self._futures.pop(job_id, None)
                if job_id in self._order:
                    self._order.remove(job_id)
                self._promote()


#: Niceness of the worker processes where the idle scheduling class is not available: CPU work
#: yields to the API (50 pollers during a 1M-point reconstruction on 2 cores: without it, p99
#: status latency was over a second).
WORKER_NICENESS = 10


def _worker_init() -> None:
    """Runs first in each worker process: lower its priority below the server's.

    Linux's SCHED_IDLE runs the worker (and the threads it starts later, which inherit it) only
    on CPU time nothing else wants: with 50 clients polling every 0.5 s during a 1M-point
    reconstruction, p99 status latency was 19-34 ms with niceness 10 alone and 10-16 ms with
    the idle class (tests/bench/test_bench_api.py, two and four runs).
    """
    import os

    try:
        os.nice(WORKER_NICENESS)
    except OSError:  # not permitted here: run at normal priority
        pass
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):  # not Linux, or not permitted: the niceness stays
        pass
