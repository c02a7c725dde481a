"""Recordings of a session: trace uploads (captures add them too) and their downloads."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Literal

from fastapi import APIRouter, File, Form, Response, UploadFile

from service import inputs
from service.api.common import CSV, add_artifact_routes, download, received
from service.api.deps import ServicesDep
from service.artifacts import RecordingCodec
from service.schemas import RecordingOut, TouchesOut
from service.store import ArtifactRow

router = APIRouter(prefix="/sessions/{session_id}", tags=["recordings"])


@router.put("/recording", status_code=201, response_model=RecordingOut)
async def upload_recording(
    session_id: str,
    services: ServicesDep,
    file: UploadFile = File(..., description="the trace; format from the name or `format`"),
    format: str | None = Form(None, description="csv, motive or c3d"),
    units: Literal["m", "mm"] | None = Form(None, description="if the file states none (m)"),
    rigid_body: str | None = Form(None, description="Motive: the pen's rigid body"),
    marker: str | None = Form(None, description="Motive or C3D: a single marker as the pen"),
    piece: str | None = Form(
        None,
        max_length=12,
        pattern=r"^(all|[0-9]{1,6})$",
        description="after long dropouts: which piece (0-based), or `all` of them (the arm "
        "lifts between pieces); default the longest",
    ),
) -> ArtifactRow:
    """Upload a trace; it becomes the session's recording. The session's tip offset is applied,
    short dropouts are bridged and long ones split it (the summary says what was done). A bad
    file is a 422 and changes nothing."""
    options = inputs.TraceOptions(
        format=format,
        units=units,
        rigid_body=rigid_body,
        marker=marker,
        piece=None if piece is None else "all" if piece == "all" else int(piece),
    )
    async with received(file, services) as upload:
        return await inputs.add_recording(services, session_id, upload, options)


add_artifact_routes(router, "recording", "recordings", RecordingOut)


@router.put("/touches", status_code=201, response_model=TouchesOut)
async def upload_touches(
    session_id: str,
    services: ServicesDep,
    file: UploadFile = File(
        ..., description="a recording in which the pen's tip rests on several workpiece points"
    ),
    format: str | None = Form(None, description="csv, motive or c3d"),
    units: Literal["m", "mm"] | None = Form(None, description="if the file states none (m)"),
    rigid_body: str | None = Form(None, description="Motive: the pen's rigid body"),
    marker: str | None = Form(None, description="Motive or C3D: a single marker as the pen"),
) -> ArtifactRow:
    """Upload touches of the workpiece: the tip rests 0.3 s or more on each of at least three
    points, on two or three faces, and moves between them. Reconstructions with a scan then
    register the scanner by them (the newest touches; ``use_touches: false`` opts out), so the
    trace's drift stays out of where the robot goes. A file with fewer rests is a 422 and
    changes nothing."""
    options = inputs.TraceOptions(
        format=format, units=units, rigid_body=rigid_body, marker=marker, piece="all"
    )
    async with received(file, services) as upload:
        return await inputs.add_recording(services, session_id, upload, options, kind="touches")


add_artifact_routes(router, "touches", "touches", TouchesOut)


@router.get("/recordings/{artifact_id}/csv", response_class=Response, responses=CSV)
def recording_csv(session_id: str, artifact_id: str, services: ServicesDep) -> Response:
    """The recording as the canonical trace CSV (metres, seconds)."""
    from drivers.tracking.canonical_csv import write_trace_csv

    row = services.artifact(session_id, "recording", artifact_id)
    recording = RecordingCodec.decode(services.store.read_arrays(row))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "trace.csv"
        write_trace_csv(path, recording)
        content = path.read_bytes()
    return download(content, media_type="text/csv", filename=f"{artifact_id}.csv")
