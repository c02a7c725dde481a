"""Jobs: state, progress, a server-sent event stream, cancellation."""

from __future__ import annotations

import asyncio
import json

from fastapi import APIRouter, Depends
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse

from service.api.deps import context
from service.errors import not_found
from service.jobs import job_json
from service.schemas import JobOut
from service.store import FINISHED

router = APIRouter(tags=["jobs"])

#: How often the event stream looks at a job.
POLL_S = 0.2


def _job(ctx, job_id: str):
    job = ctx.store.job(job_id)
    if job is None:
        raise not_found("job", job_id)
    return job


@router.get("/jobs/{job_id}", response_model=JobOut)
async def get_job(job_id: str, ctx=Depends(context)) -> dict:
    """State (queued, running, succeeded, failed, cancelled), progress 0..1, result or error."""
    return job_json(_job(ctx, job_id))


@router.get("/sessions/{session_id}/jobs", response_model=list[JobOut])
def list_jobs(session_id: str, ctx=Depends(context)) -> list[dict]:
    ctx.session(session_id)
    return [job_json(j) for j in ctx.store.jobs(session_id)]


@router.post("/jobs/{job_id}/cancel", response_model=JobOut)
def cancel_job(job_id: str, ctx=Depends(context)) -> dict:
    """Cancel a job that has not started (409 once it runs or has finished)."""
    _job(ctx, job_id)
    return job_json(ctx.jobs.cancel(job_id))


@router.get(
    "/jobs/{job_id}/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}},
)
async def job_events(job_id: str, ctx=Depends(context)) -> StreamingResponse:
    """Server-sent events: the job as JSON each time it changes, until it has finished."""
    first = await run_in_threadpool(_job, ctx, job_id)

    async def stream():
        last = None
        job = first
        while True:
            body = job_json(job)
            if body != last:
                yield f"event: job\ndata: {json.dumps(body)}\n\n"
                last = body
            if job.state in FINISHED:
                return
            await asyncio.sleep(POLL_S)
            job = ctx.store.job(job_id)  # the store keeps jobs in memory: no I/O here

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
    )
