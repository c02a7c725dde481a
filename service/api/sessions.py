"""Sessions, their calibration, and the uploaded inputs (recordings and scans)."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Literal

from fastapi import APIRouter, Depends, File, Form, Response, UploadFile

from service.api.deps import context
from service.context import artifact_json, session_json
from service.errors import ApiError
from service.schemas import (
    ArtifactOut,
    BaseCalibrationIn,
    CalibrationIn,
    CalibrationResult,
    SessionCreate,
    SessionOut,
)
from service.store import now

router = APIRouter(tags=["sessions"])


@router.post("/sessions", status_code=201, response_model=SessionOut)
def create_session(body: SessionCreate, ctx=Depends(context)) -> dict:
    """A new, empty session."""
    return session_json(ctx.store.create_session(body.name))


@router.get("/sessions", response_model=list[SessionOut])
def list_sessions(ctx=Depends(context)) -> list[dict]:
    return [session_json(s) for s in ctx.store.sessions()]


@router.get("/sessions/{session_id}", response_model=SessionOut)
def get_session(session_id: str, ctx=Depends(context)) -> dict:
    return session_json(ctx.session(session_id))


@router.delete("/sessions/{session_id}", status_code=204)
def delete_session(session_id: str, ctx=Depends(context)) -> Response:
    """Soft delete: the session disappears from the API, its data stays on disk."""
    ctx.session(session_id)
    ctx.store.update_session(session_id, deleted_at=now())
    return Response(status_code=204)


@router.put("/sessions/{session_id}/calibration", response_model=SessionOut)
def set_calibration(session_id: str, body: CalibrationIn, ctx=Depends(context)) -> dict:
    """Set calibrations: T_base_tracker (tracker -> robot base), T_scan_tracker (tracker ->
    scan, the initial guess for registration), tip_offset_m (the pen's tip in its rigid body's
    frame, applied to recordings uploaded or captured afterwards). Fields left out keep their
    value; an explicit null clears one."""
    return session_json(ctx.set_calibration(session_id, body))


@router.post("/sessions/{session_id}/calibration/pivot", response_model=CalibrationResult)
async def pivot_calibration(
    session_id: str,
    file: UploadFile = File(..., description="a recording of the pen pivoting about its tip"),
    format: str | None = Form(None, description="csv, motive or c3d; default from the name"),
    units: Literal["m", "mm"] | None = Form(None, description="if the file states none"),
    rigid_body: str | None = Form(None, description="Motive: the pen's rigid body"),
    ctx=Depends(context),
) -> dict:
    """Pivot calibration: the tip offset from a recording where the tip stays on one point
    while the pen tilts in every direction. Sets the session's tip_offset_m."""
    content = await _read_upload(file, ctx)
    row, result = await ctx.pivot_calibration(
        session_id, content, file.filename or "upload", format, units, rigid_body
    )
    return {"session": session_json(row), "result": result}


@router.post("/sessions/{session_id}/calibration/base", response_model=CalibrationResult)
def base_calibration(session_id: str, body: BaseCalibrationIn, ctx=Depends(context)) -> dict:
    """T_base_tracker from point pairs (the same points in the base and tracker frames, at
    least 3 not on a line); pairs off by more than the tolerance are reported and left out.
    Sets the session's T_base_tracker."""
    row, result = ctx.base_calibration(session_id, body)
    return {"session": session_json(row), "result": result}


async def _read_upload(file: UploadFile, ctx) -> bytes:
    limit = int(ctx.settings.max_upload_mb * 1024 * 1024)
    content = await file.read(limit + 1)
    if len(content) > limit:
        raise ApiError(
            413, "upload_too_large", f"the upload exceeds {ctx.settings.max_upload_mb:g} MB"
        )
    if not content:
        raise ApiError(422, "invalid_file", "the uploaded file is empty")
    return content


@router.put("/sessions/{session_id}/recording", status_code=201, response_model=ArtifactOut)
async def upload_recording(
    session_id: str,
    file: UploadFile = File(..., description="the trace; format from the name or `format`"),
    format: str | None = Form(None, description="csv, motive or c3d"),
    units: Literal["m", "mm"] | None = Form(None, description="if the file states none (m)"),
    rigid_body: str | None = Form(None, description="Motive: the pen's rigid body"),
    marker: str | None = Form(None, description="Motive or C3D: a single marker as the pen"),
    piece: int | None = Form(
        None, ge=0, description="after long dropouts: which piece (default the longest)"
    ),
    ctx=Depends(context),
) -> dict:
    """Upload a trace; it becomes the session's recording. The session's tip offset is applied,
    short dropouts are bridged and long ones split it (the summary says what was done). A bad
    file is a 422 and changes nothing."""
    content = await _read_upload(file, ctx)
    return artifact_json(
        await ctx.add_recording(
            session_id,
            content,
            file.filename or "upload",
            format,
            units,
            rigid_body=rigid_body,
            marker=marker,
            piece=piece,
        )
    )


@router.put("/sessions/{session_id}/scan", status_code=201, response_model=ArtifactOut)
async def upload_scan(
    session_id: str,
    file: UploadFile = File(
        ...,
        description="PLY/PCD/XYZ(N/RGB)/PTS point cloud, E57, a .zip of RGB-D frames (with "
        "intrinsics and poses), or a RealSense .bag",
    ),
    format: str | None = Form(None, description="ply, pcd, xyz, xyzn, xyzrgb, pts, e57, rgbd, bag"),
    units: Literal["m", "mm"] = Form("m", description="point clouds only; others fix their own"),
    options: str | None = Form(
        None,
        description='the reader\'s options as a JSON object, e.g. {"depth_scale": 1000} for '
        "RGB-D frames",
    ),
    ctx=Depends(context),
) -> dict:
    """Upload a scan; it becomes the session's scan. A bad file is a 422 and changes nothing."""
    reader_options = None
    if options:
        try:
            reader_options = json.loads(options)
        except json.JSONDecodeError as exc:
            raise ApiError(422, "invalid_request", f"options is not valid JSON: {exc}") from None
        if not isinstance(reader_options, dict):
            raise ApiError(422, "invalid_request", "options must be a JSON object")
    content = await _read_upload(file, ctx)
    return artifact_json(
        await ctx.add_scan(
            session_id, content, file.filename or "upload", format, units, reader_options
        )
    )


@router.get("/sessions/{session_id}/recordings", response_model=list[ArtifactOut])
def list_recordings(session_id: str, ctx=Depends(context)) -> list[dict]:
    """Every recording of the session (uploads and captures), oldest first."""
    ctx.session(session_id)
    return [artifact_json(a) for a in ctx.store.artifacts(session_id, "recording")]


@router.get("/sessions/{session_id}/scans", response_model=list[ArtifactOut])
def list_scans(session_id: str, ctx=Depends(context)) -> list[dict]:
    ctx.session(session_id)
    return [artifact_json(a) for a in ctx.store.artifacts(session_id, "scan")]


@router.get("/sessions/{session_id}/recordings/{artifact_id}", response_model=ArtifactOut)
def get_recording(session_id: str, artifact_id: str, ctx=Depends(context)) -> dict:
    return artifact_json(ctx.artifact(session_id, "recording", artifact_id))


@router.get("/sessions/{session_id}/scans/{artifact_id}", response_model=ArtifactOut)
def get_scan(session_id: str, artifact_id: str, ctx=Depends(context)) -> dict:
    return artifact_json(ctx.artifact(session_id, "scan", artifact_id))


@router.get(
    "/sessions/{session_id}/recordings/{artifact_id}/csv",
    response_class=Response,
    responses={200: {"content": {"text/csv": {}}}},
)
def recording_csv(session_id: str, artifact_id: str, ctx=Depends(context)) -> Response:
    """The recording as the canonical trace CSV (metres, seconds)."""
    from drivers.tracking.canonical_csv import write_trace_csv
    from service.tasks import recording_from

    row = ctx.artifact(session_id, "recording", artifact_id)
    recording = recording_from(ctx.store.read_arrays(row))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "trace.csv"
        write_trace_csv(path, recording)
        content = path.read_bytes()
    return Response(
        content,
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="{artifact_id}.csv"'},
    )


@router.get(
    "/sessions/{session_id}/scans/{artifact_id}/ply",
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
def scan_ply(session_id: str, artifact_id: str, ctx=Depends(context)) -> Response:
    """The scan as a binary PLY (metres)."""
    from drivers.scanning.pointcloud import write_scan
    from service.tasks import scan_from

    row = ctx.artifact(session_id, "scan", artifact_id)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scan.ply"
        write_scan(path, scan_from(ctx.store.read_arrays(row)))
        content = path.read_bytes()
    return Response(
        content,
        media_type="application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="{artifact_id}.ply"'},
    )
