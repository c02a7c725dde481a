"""Scans of a session: uploads and their downloads."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, File, Form, Query, Response, UploadFile

from service import inputs
from service.api.common import BINARY, add_artifact_routes, download, received
from service.api.deps import ServicesDep
from service.artifacts import ScanCodec
from service.errors import ApiError
from service.schemas import ScanOut
from service.store import ArtifactRow

router = APIRouter(prefix="/sessions/{session_id}", tags=["scans"])


#: A reader's options are a handful of numbers and names.
MAX_OPTIONS_CHARS = 4096


def _reader_options(options: str | None) -> dict[str, Any] | None:
    if not options:
        return None
    if len(options) > MAX_OPTIONS_CHARS:
        raise ApiError(
            422, "invalid_request", f"options is longer than {MAX_OPTIONS_CHARS} characters"
        )
    try:
        parsed = json.loads(options)
    except RecursionError:
        raise ApiError(422, "invalid_request", "options is nested too deeply") from None
    except ValueError as exc:  # JSONDecodeError, and integers beyond Python's digit limit
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
) -> ArtifactRow:
    """Upload a scan; it becomes the session's scan. A bad file is a 422 and changes nothing."""
    reader_options = _reader_options(options)
    async with received(file, services) as upload:
        return await inputs.add_scan(
            services, session_id, upload, format=format, units=units, options=reader_options
        )


add_artifact_routes(router, "scan", "scans", ScanOut)


@router.get("/scans/{artifact_id}/ply", response_class=Response, responses=BINARY)
def scan_ply(session_id: str, artifact_id: str, services: ServicesDep) -> Response:
    """The scan as a binary PLY (metres)."""
    from drivers.scanning.pointcloud import write_scan

    row = services.artifact(session_id, "scan", artifact_id)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scan.ply"
        write_scan(path, ScanCodec.decode(services.store.read_arrays(row)))
        content = path.read_bytes()
    return download(content, media_type="application/octet-stream", filename=f"{artifact_id}.ply")


#: The most points :func:`scan_points` sends (a pendant draws this many without trouble).
MAX_VIEW_POINTS = 1_000_000


@router.get(
    "/scans/{artifact_id}/points",
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
def scan_points(
    session_id: str,
    artifact_id: str,
    services: ServicesDep,
    max_points: int = Query(
        200_000, ge=1, le=MAX_VIEW_POINTS, description="at most this many points (every k-th)"
    ),
) -> Response:
    """The scan's points for drawing: every k-th point so that at most ``max_points`` remain,
    as little-endian float32 x, y, z triples (scan frame, metres), gzip-compressed
    (``Content-Encoding: gzip``). ``X-Point-Count``: the points sent; ``X-Point-Total``: the
    scan's."""
    import gzip

    import numpy as np

    row = services.artifact(session_id, "scan", artifact_id)
    points = np.asarray(ScanCodec.decode(services.store.read_arrays(row)).points_m)
    step = max(1, -(-len(points) // max_points))
    sent = np.ascontiguousarray(points[::step], dtype="<f4")
    return Response(
        gzip.compress(sent.tobytes(), compresslevel=5, mtime=0),
        media_type="application/octet-stream",
        headers={
            "Content-Encoding": "gzip",
            "X-Point-Count": str(len(sent)),
            "X-Point-Total": str(len(points)),
        },
    )
