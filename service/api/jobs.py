"""Jobs: state, progress, a server-sent event stream, cancellation.

Every database read runs in the thread pool (sync routes, ``run_in_threadpool`` in the event
stream), never on the event loop.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse

from service import executions
from service.api.deps import ServicesDep
from service.core import Services
from service.errors import not_found
from service.schemas import JobOut
from service.store import FINISHED, JobRow

router = APIRouter(prefix="/jobs", tags=["jobs"])
session_router = APIRouter(prefix="/sessions/{session_id}/jobs", tags=["jobs"])

#: How often the event stream looks at a job.
POLL_S = 0.2


def _job(services: Services, job_id: str) -> JobRow:
    job = services.store.job(job_id)
    if job is None:
        raise not_found("job", job_id)
    return job


@router.get("/{job_id}", response_model=JobOut)
def get_job(job_id: str, services: ServicesDep) -> JobRow:
    """State (queued, running, succeeded, failed, cancelled), progress 0..1, result or error."""
    return _job(services, job_id)


@session_router.get("", response_model=list[JobOut])
def list_jobs(session_id: str, services: ServicesDep) -> list[JobRow]:
    services.session(session_id)
    return services.store.jobs(session_id)


@router.post("/{job_id}/cancel", response_model=JobOut)
def cancel_job(job_id: str, services: ServicesDep) -> JobRow:
    """Cancel a job that has not started (409 once it runs or has finished). An execution is
    stopped instead, running or not (as ``POST /executions/{id}/stop``)."""
    job = _job(services, job_id)
    execution_id = job.params.get("execution_id") if job.kind == "execution" else None
    if execution_id is not None and job.state not in FINISHED:
        return executions.stop(services, str(execution_id)).job
    return services.jobs.cancel(job_id)


@router.get(
    "/{job_id}/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}},
)
async def job_events(job_id: str, services: ServicesDep) -> StreamingResponse:
    """Server-sent events: the job as JSON each time it changes, until it has finished."""
    first = await run_in_threadpool(_job, services, job_id)

    async def stream() -> AsyncIterator[str]:
        last: dict[str, Any] | None = None
        job = first
        while True:
            body = JobOut.model_validate(job).model_dump(mode="json")
            if body != last:
                yield f"event: job\ndata: {json.dumps(body)}\n\n"
                last = body
            if job.state in FINISHED:
                return
            await asyncio.sleep(POLL_S)
            job = await run_in_threadpool(_job, services, job_id)

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
    )
