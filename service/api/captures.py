"""Captures: record a tracker source into the session as the samples arrive."""

from __future__ import annotations

from fastapi import APIRouter

from service import captures
from service.api.deps import ServicesDep
from service.schemas import CaptureCreate, CaptureOut

router = APIRouter(prefix="/sessions/{session_id}/captures", tags=["captures"])


@router.post("", status_code=201, response_model=CaptureOut)
def start_capture(session_id: str, body: CaptureCreate, services: ServicesDep):
    """Start capturing; the samples are stored as they arrive and become a recording when the
    capture stops or the source ends."""
    return captures.start(services, session_id, body)


@router.get("/{capture_id}", response_model=CaptureOut)
def get_capture(session_id: str, capture_id: str, services: ServicesDep):
    return captures.get(services, session_id, capture_id)


@router.post("/{capture_id}/stop", response_model=CaptureOut)
def stop_capture(session_id: str, capture_id: str, services: ServicesDep):
    return captures.stop(services, session_id, capture_id)
