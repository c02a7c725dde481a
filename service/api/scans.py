"""Scans of a session: uploads and their downloads."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Literal

from fastapi import APIRouter, File, Form, Response, UploadFile

from service import inputs
from service.api.common import BINARY, add_artifact_routes, download, received
from service.api.deps import ServicesDep
from service.artifacts import ScanCodec
from service.errors import ApiError
from service.schemas import ScanOut

router = APIRouter(prefix="/sessions/{session_id}", tags=["scans"])


def _reader_options(options: str | None) -> dict | None:
    if not options:
        return None
    try:
        parsed = json.loads(options)
    except json.JSONDecodeError as exc:
        raise ApiError(422, "invalid_request", f"options is not valid JSON: {exc}") from None
    if not isinstance(parsed, dict):
        raise ApiError(422, "invalid_request", "options must be a JSON object")
    return parsed


@router.put("/scan", status_code=201, response_model=ScanOut)
async def upload_scan(
    session_id: str,
    services: ServicesDep,
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
):
    """Upload a scan; it becomes the session's scan. A bad file is a 422 and changes nothing."""
    reader_options = _reader_options(options)
    async with received(file, services) as upload:
        return await inputs.add_scan(
            services, session_id, upload, format=format, units=units, options=reader_options
        )


add_artifact_routes(router, "scan", "scans", ScanOut)


@router.get("/scans/{artifact_id}/ply", response_class=Response, responses=BINARY)
def scan_ply(session_id: str, artifact_id: str, services: ServicesDep):
    """The scan as a binary PLY (metres)."""
    from drivers.scanning.pointcloud import write_scan

    row = services.artifact(session_id, "scan", artifact_id)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scan.ply"
        write_scan(path, ScanCodec.decode(services.store.read_arrays(row)))
        content = path.read_bytes()
    return download(content, media_type="application/octet-stream", filename=f"{artifact_id}.ply")
