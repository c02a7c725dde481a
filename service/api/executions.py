"""Executions: dry runs on the simulated arm and runs on the real one; stopping them."""

from __future__ import annotations

import csv
import io
from typing import Any

import anyio
import anyio.to_thread
import numpy as np
from fastapi import APIRouter, Query, Request, Response

from service import executions, tasks
from service.api.common import CSV, add_artifact_routes, download, gzip_json
from service.api.deps import ServicesDep, has_token
from service.artifacts import ExecutionCodec
from service.errors import ApiError
from service.schemas import (
    ExecutionCreate,
    ExecutionOut,
    JobOut,
    ResumeIn,
    RunSpeedOut,
    SpeedIn,
    StopOut,
)
from service.store import JobRow

router = APIRouter(prefix="/sessions/{session_id}", tags=["executions"])
stop_router = APIRouter(prefix="/executions", tags=["executions"])
#: The speed override and pause of a running execution: with the token.
control_router = APIRouter(prefix="/executions", tags=["executions"])


@router.post("/executions", status_code=202, response_model=JobOut)
def start_execution(session_id: str, body: ExecutionCreate, services: ServicesDep) -> JobRow:
    """Run a trajectory: on the simulated arm (a dry run, the default) or, confirmed and after
    a passed dry run, on the configured real arm."""
    return executions.start(services, session_id, body)


add_artifact_routes(router, "execution", "executions", ExecutionOut)


@router.get("/executions/{artifact_id}/csv", response_class=Response, responses=CSV)
def execution_csv(session_id: str, artifact_id: str, services: ServicesDep) -> Response:
    """What ran: t, planned and actual joints."""
    row = services.artifact(session_id, "execution", artifact_id)
    samples = ExecutionCodec.decode(services.store.read_arrays(row))
    if samples is None:
        raise ApiError(404, "not_found", f"execution {artifact_id} recorded no samples")
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(
        ["t"] + [f"q{i}_planned" for i in range(6)] + [f"q{i}_actual" for i in range(6)]
    )
    for row_values in np.column_stack([samples.t_s, samples.q_planned_rad, samples.q_actual_rad]):
        writer.writerow(["" if not np.isfinite(v) else f"{v:.10g}" for v in row_values])
    return download(buffer.getvalue(), media_type="text/csv", filename=f"{artifact_id}.csv")


@router.get("/executions/{artifact_id}/review", response_class=Response)
def execution_review(
    session_id: str,
    artifact_id: str,
    services: ServicesDep,
    request: Request,
    max_samples: int = Query(1500, ge=10, le=20_000, description="about this many samples"),
) -> Response:
    """Planned against actual (gzip JSON): where the TCP was (base frame, m) and how far the
    arm was from the planned path along the execution, with the largest deviation and when."""
    from service.preview import execution_review as review

    row = services.artifact(session_id, "execution", artifact_id)
    samples = ExecutionCodec.decode(services.store.read_arrays(row))
    if samples is None:
        raise ApiError(404, "not_found", f"execution {artifact_id} recorded no samples")
    plan = services.artifact(session_id, "trajectory", row.inputs["trajectory_id"])
    trajectory = tasks.load_trajectory(services.store.path_of(plan), plan.summary)
    return gzip_json(review(trajectory, samples, max_samples=max_samples), request)


#: Threads for a stop's bookkeeping, apart from the pool ordinary requests share: a stop is
#: answered even while every one of those is busy.
STOP_THREADS = anyio.CapacityLimiter(4)


@stop_router.post("/{execution_id}/stop", response_model=StopOut)
async def stop_execution(
    execution_id: str, services: ServicesDep, request: Request
) -> dict[str, Any]:
    """Stop the arm (decelerating; nothing of this execution moves afterwards) or cancel an
    execution that has not started; says whether it had already ended. Needs no token for an
    execution this instance started (any screen by the cell stops the arm); with the token,
    any execution the database knows."""
    # Latched first, on the event loop: no database, no worker thread, nothing an ordinary
    # request can hold stands between the request and the arm's stop.
    executions.latch_stop(services, execution_id)
    if execution_id not in services.live.execution_jobs and not has_token(request):
        # Without the token no search of the database: a flood of made-up ids must not load
        # it, nor keep the stop's threads from a real Stop.
        raise ApiError(
            404,
            "not_found",
            f"execution {execution_id} was not started by this instance: sign in to stop an "
            "execution of another, or stop the arm at its teach pendant",
        )
    outcome = await anyio.to_thread.run_sync(
        executions.stop, services, execution_id, limiter=STOP_THREADS
    )
    job = JobOut.model_validate(outcome.job).model_dump()
    return {**job, "already_ended": outcome.already_ended}


# The speed override and pause touch no database and no worker thread (a shared number is
# set): answered on the event loop, like the stop, so a busy pool never delays a pause.


@control_router.post("/{execution_id}/speed", response_model=RunSpeedOut)
async def set_speed(execution_id: str, body: SpeedIn, services: ServicesDep) -> dict[str, Any]:
    """Run a real-arm execution (servoJ) at a fraction of its planned speed from now on, as a
    UR program's speed slider does: the arm ramps to it within the joints' acceleration limits,
    on the same path, never faster than planned."""
    return executions.set_speed(services, execution_id, body.fraction)


@control_router.post("/{execution_id}/pause", response_model=RunSpeedOut)
async def pause(execution_id: str, services: ServicesDep) -> dict[str, Any]:
    """Bring a moving real-arm execution (servoJ) to rest on its path, within the acceleration
    limits; it holds there until resumed (an approval) or stopped. A pause longer than 10
    minutes ends the run as stopped."""
    return executions.pause(services, execution_id)


@control_router.post("/{execution_id}/resume", response_model=RunSpeedOut)
async def resume(execution_id: str, body: ResumeIn, services: ServicesDep) -> dict[str, Any]:
    """Go on along the path from where a pause left the arm, at the speed set: the operator
    approves it again (``confirm`` true, and the running trajectory's sha256)."""
    if body.confirm is not True:
        raise ApiError(
            409,
            "not_confirmed",
            "resuming moves the arm: confirm it (confirm: true) with the trajectory's sha256",
        )
    return executions.resume(services, execution_id, body.approved_sha256)
