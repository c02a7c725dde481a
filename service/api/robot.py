"""The arm: its state now, a stream of it, and unlocking a protective stop."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import StreamingResponse

from service import executions
from service.api.deps import ServicesDep, has_token
from service.errors import ApiError
from service.schemas import CellIn, CellOut, RobotOut

if TYPE_CHECKING:
    from service.arm_runner import ExecutionRunner
    from service.core import Services

#: The arm's state: no token needed (the safety bar of any screen by the cell).
router = APIRouter(prefix="/robot", tags=["robot"])
#: Acting on the arm, and the cell's setup: with the token.
unlock_router = APIRouter(prefix="/robot", tags=["robot"])
cell_router = APIRouter(prefix="/cell", tags=["robot"])

#: How long the event stream waits for a change before it repeats the state (a keep-alive).
KEEPALIVE_S = 5.0
#: How often a stream looks whether the state changed (on the event loop: no thread is held).
EVENT_POLL_S = 0.05
#: Open event streams at most (one token serves every pendant of a cell; a page holds one).
MAX_EVENT_STREAMS = 64
#: Of those, streams without the token at most: screens that are not signed in cannot take
#: the slots the signed-in pendants need.
MAX_ANONYMOUS_STREAMS = 16

#: Which run owns the arm and what of its speed the safety bar shows: (its execution's id, the
#: speed fraction, paused, at rest).
RunSignature = tuple[str | None, float, bool, bool]


def _view(services: Services) -> dict[str, Any]:
    with services.live.lock:
        owner = services.live.arm_owner()
        runner = services.live.executions.get(owner) if owner else None
    return _with_speed(services.robot.view(owner), owner, runner)


def _owner_now(services: Services) -> tuple[str | None, ExecutionRunner | None]:
    """The execution that owns the arm and its runner, for the event loop: from a copy of the
    runners (a C-level copy under the GIL) instead of the lock a starting execution holds while
    it reads the arm."""
    runners = dict(services.live.executions)
    owner = next((eid for eid, runner in runners.items() if runner.running), None)
    return owner, None if owner is None else runners.get(owner)


def _view_now(services: Services) -> dict[str, Any]:
    """The view, for the event loop (see :func:`_owner_now`)."""
    owner, runner = _owner_now(services)
    return _with_speed(services.robot.view(owner), owner, runner)


def _run_signature(services: Services) -> RunSignature | None:
    """Which run owns the arm and what of its speed the safety bar shows. A change is sent at
    once: a run that has ended (the arm free again: with the arm at rest, its readings no longer
    change, and the bar said "busy" until the next keep-alive), a pause asked, the arm come to
    rest."""
    owner, runner = _owner_now(services)
    if runner is None:
        return None
    view = runner.speed_view()
    return (owner, view["speed_fraction"], view["paused"], view["speed_now"] == 0)


def _with_speed(
    view: dict[str, Any], owner: str | None, runner: ExecutionRunner | None
) -> dict[str, Any]:
    """The view with the owning run's speed override (what the safety bar shows beside Stop)."""
    speed = None if runner is None or owner is None else executions.speed_view(owner, runner)
    return {**view, "run_speed": speed}


@router.get("", response_model=RobotOut)
def robot_state(services: ServicesDep) -> dict[str, Any]:
    """Backend, robot mode, safety status, protective stop (and when it may be unlocked),
    remote control, joints and TCP, who owns the arm, and the server's speed cap."""
    return _view(services)


@router.get(
    "/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}},
)
async def robot_events(services: ServicesDep, request: Request) -> StreamingResponse:
    """Server-sent events: the arm's state each time it changes (and every few seconds). At
    most 64 streams are open at once, 16 of them without the token (429 beyond): each is a
    coroutine on the event loop that reads the one watch of the arm, so no stream holds a
    thread an ordinary request needs."""
    live = services.live
    anonymous = not has_token(request)
    if live.event_streams >= MAX_EVENT_STREAMS or (
        anonymous and live.anonymous_streams >= MAX_ANONYMOUS_STREAMS
    ):
        limit = MAX_ANONYMOUS_STREAMS if anonymous else MAX_EVENT_STREAMS
        raise ApiError(
            429,
            "too_many_streams",
            f"{limit} event streams{' without the token' if anonymous else ''} are open "
            "already: close a pendant, sign in, or poll GET /robot",
        )

    async def stream() -> AsyncIterator[str]:
        # Counted while it runs (on the event loop: no lock needed).
        live.event_streams += 1
        live.anonymous_streams += anonymous
        loop = asyncio.get_running_loop()
        version: int = -1
        run: RunSignature | None = None
        try:
            while True:
                # On a change, or after KEEPALIVE_S: either way the page gets the state.
                deadline = loop.time() + KEEPALIVE_S
                while (
                    services.robot.version == version
                    and _run_signature(services) == run
                    and loop.time() < deadline
                ):
                    await asyncio.sleep(EVENT_POLL_S)
                version, run = services.robot.version, _run_signature(services)
                body = RobotOut.model_validate(_view_now(services)).model_dump(mode="json")
                yield f"event: robot\ndata: {json.dumps(body)}\n\n"
        finally:
            live.event_streams -= 1
            live.anonymous_streams -= anonymous

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
    )


@unlock_router.post("/unlock", response_model=RobotOut)
def unlock_protective_stop(services: ServicesDep) -> dict[str, Any]:
    """Unlock a protective stop (after its cause is gone; UR refuses within 5 s of it)."""
    services.robot.unlock_protective_stop()
    return _view(services)


def _cell_view(services: Services) -> dict[str, Any]:
    from service.cell import cell_now

    settings = services.settings
    cell = cell_now(services.store, settings)
    with services.live.lock:
        editable = services.live.arm_owner() is None
    boxes, planes = cell.as_lists()
    # The arm's calibration is read from that file at start (settings.arm_calibration).
    calibration_file = settings.ur_calibration
    return {
        "robot": settings.ur_robot,
        "keep_out_boxes_m": boxes,
        "cell_planes": planes,
        "revision": cell.revision,
        "source": cell.source,
        "editable": editable,
        "mount_up": list(settings.mount_up),
        "arm_kinematics": (
            f"calibrated ({calibration_file.name})"
            if settings.arm_calibration is not None and calibration_file is not None
            else "UR's nominal kinematics (no calibration.conf given)"
        ),
    }


@cell_router.get("", response_model=CellOut)
def cell(services: ServicesDep) -> dict[str, Any]:
    """This server's cell, as every plan and the real-arm gate check against it: the keep-out
    boxes and planes (base frame, m), how the arm is mounted, and whether its kinematics are
    the controller's calibration or UR's nominal ones. The boxes and planes are the start-up
    settings (TEACHPATH_KEEP_OUT_BOXES, TEACHPATH_CELL_PLANES) until edited (PUT /cell)."""
    return _cell_view(services)


@cell_router.put("", response_model=CellOut)
def edit_cell(body: CellIn, services: ServicesDep) -> dict[str, Any]:
    """Set this arm's keep-out boxes and planes. Plans made before are then outdated, and the
    real-arm gate checks every run against the new cell. Refused (409) while a real-arm
    execution runs, and when the cell changed since the revision named (``cell_changed``)."""
    from service import cell as cells

    cells.edit_cell(services, body.keep_out_boxes_m, body.cell_planes, revision=body.revision)
    return _cell_view(services)


@cell_router.delete("", response_model=CellOut)
def reset_cell(
    services: ServicesDep,
    revision: int = Query(..., ge=0, le=2**31 - 1, description="the revision this was seen at"),
) -> dict[str, Any]:
    """Go back to the start-up settings' boxes and planes (refused as an edit is)."""
    from service import cell as cells

    cells.edit_cell(services, None, None, revision=revision)
    return _cell_view(services)
