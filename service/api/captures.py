"""Captures: record a tracker source into the session as the samples arrive."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from service.api.deps import context
from service.context import capture_json
from service.errors import not_found
from service.schemas import CaptureCreate, CaptureOut

router = APIRouter(tags=["captures"])


@router.post("/sessions/{session_id}/captures", status_code=201, response_model=CaptureOut)
def start_capture(session_id: str, body: CaptureCreate, ctx=Depends(context)) -> dict:
    """Start capturing; the samples are stored as they arrive and become a recording when the
    capture stops or the source ends."""
    return capture_json(ctx.start_capture(session_id, body))


@router.get("/sessions/{session_id}/captures/{capture_id}", response_model=CaptureOut)
def get_capture(session_id: str, capture_id: str, ctx=Depends(context)) -> dict:
    ctx.session(session_id)
    row = ctx.store.capture(capture_id)
    if row is None or row.session_id != session_id:
        raise not_found("capture", capture_id)
    return capture_json(row)


@router.post("/sessions/{session_id}/captures/{capture_id}/stop", response_model=CaptureOut)
def stop_capture(session_id: str, capture_id: str, ctx=Depends(context)) -> dict:
    ctx.session(session_id)
    return capture_json(ctx.stop_capture(session_id, capture_id))
