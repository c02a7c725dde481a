"""Captures: record a tracker source into the session as the samples arrive."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
from fastapi import APIRouter, Query
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse

from drivers.errors import InputFileError
from service import captures
from service.api.deps import ServicesDep
from service.schemas import CaptureCreate, CaptureOut
from service.store import CaptureRow

router = APIRouter(prefix="/sessions/{session_id}/captures", tags=["captures"])


@router.post("", status_code=201, response_model=CaptureOut)
def start_capture(session_id: str, body: CaptureCreate, services: ServicesDep) -> CaptureRow:
    """Start capturing; the samples are stored as they arrive and become a recording when the
    capture stops or the source ends."""
    return captures.start(services, session_id, body)


@router.get("/{capture_id}", response_model=CaptureOut)
def get_capture(session_id: str, capture_id: str, services: ServicesDep) -> CaptureRow:
    return captures.get(services, session_id, capture_id)


@router.post("/{capture_id}/stop", response_model=CaptureOut)
def stop_capture(session_id: str, capture_id: str, services: ServicesDep) -> CaptureRow:
    return captures.stop(services, session_id, capture_id)


#: How often the sample stream looks for new samples (the runner writes every 50 ms batch).
POLL_S = 0.1


@router.get(
    "/{capture_id}/samples",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}},
)
async def capture_samples(
    session_id: str,
    capture_id: str,
    services: ServicesDep,
    from_sample: int = Query(0, ge=0, le=10**9, description="the first sample to send"),
) -> StreamingResponse:
    """Server-sent events while the capture runs: ``samples`` with each stretch of new samples
    (``first`` index, ``t_s``, ``points_m`` in the tracker frame at the pen's tip, null where
    tracking was lost, ``valid``), ``capture`` (the capture, as GET returns it) whenever its
    state changes; the stream ends after the last sample of a capture that has ended
    (``error`` if its file cannot be read)."""
    from service.capture_stream import CaptureTail, samples_event

    row = await run_in_threadpool(captures.get, services, session_id, capture_id)
    session = await run_in_threadpool(services.store.session, session_id)
    live = row.source.get("kind") == "natnet"
    tip = session.tip_offset_m if live and session is not None else None
    tail = CaptureTail(
        services.store.data_dir / row.path,
        from_sample,
        None if tip is None else np.asarray(tip, dtype=np.float64),
    )

    async def stream() -> AsyncIterator[str]:
        last: dict[str, Any] | None = None
        while True:
            # The state first, then the file: a capture seen ended has all its samples written.
            now = await run_in_threadpool(services.store.capture, capture_id)
            ended = now is None or now.state != "running"
            try:
                while (read := await run_in_threadpool(tail.read)) is not None:
                    yield f"event: samples\ndata: {json.dumps(samples_event(*read))}\n\n"
            except (InputFileError, OSError, ValueError) as exc:
                # Said in the stream (its headers are sent): the page shows it and looks again.
                yield f"event: error\ndata: {json.dumps({'message': str(exc)})}\n\n"
                return
            body = None if now is None else CaptureOut.model_validate(now).model_dump(mode="json")
            if body != last and body is not None:
                yield f"event: capture\ndata: {json.dumps(body)}\n\n"
                last = body
            if ended:
                return
            await asyncio.sleep(POLL_S)

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
    )
