"""The arm: its state now, a stream of it, and unlocking a protective stop."""

from __future__ import annotations

import json

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse

from service.api.deps import ServicesDep
from service.executions import arm_owner
from service.schemas import RobotOut

router = APIRouter(prefix="/robot", tags=["robot"])

#: How long the event stream waits for a change before it repeats the state (a keep-alive).
KEEPALIVE_S = 5.0


def _view(services) -> dict:
    with services.live.lock:
        owner = arm_owner(services)
    return services.robot.view(owner)


@router.get("", response_model=RobotOut)
def robot_state(services: ServicesDep) -> dict:
    """Backend, robot mode, safety status, protective stop (and when it may be unlocked),
    remote control, joints and TCP, who owns the arm, and the server's speed cap."""
    return _view(services)


@router.get(
    "/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}},
)
async def robot_events(services: ServicesDep) -> StreamingResponse:
    """Server-sent events: the arm's state each time it changes (and every few seconds)."""

    async def stream():
        version = -1
        while True:
            # Returns on a change, or after KEEPALIVE_S: either way the page gets the state.
            version, _ = await run_in_threadpool(services.robot.wait_change, version, KEEPALIVE_S)
            view = await run_in_threadpool(_view, services)
            body = RobotOut.model_validate(view).model_dump(mode="json")
            yield f"event: robot\ndata: {json.dumps(body)}\n\n"

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
    )


@router.post("/unlock", response_model=RobotOut)
def unlock_protective_stop(services: ServicesDep) -> dict:
    """Unlock a protective stop (after its cause is gone; UR refuses within 5 s of it)."""
    services.robot.unlock_protective_stop()
    return _view(services)
