"""Reconstructions: started as jobs, listed for comparison, downloaded."""

from __future__ import annotations

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import FileResponse

from service import reconstructions
from service.api.common import CSV, PNG, add_artifact_routes, download, gzip_json
from service.api.deps import ServicesDep
from service.artifacts import ReconstructionCodec
from service.core import Services
from service.errors import ApiError
from service.provenance import reconstruction_outdated
from service.schemas import JobOut, ReconstructionCreate, ReconstructionOut
from service.store import ArtifactRow, JobRow, SessionRow

router = APIRouter(prefix="/sessions/{session_id}", tags=["reconstructions"])


@router.post("/reconstructions", status_code=202, response_model=JobOut)
def start_reconstruction(
    session_id: str, body: ReconstructionCreate, services: ServicesDep
) -> JobRow:
    """Reconstruct the session's recording (with its scan); the job's result names the
    reconstruction."""
    return reconstructions.start(services, session_id, body)


def _outdated(services: Services, session: SessionRow, row: ArtifactRow) -> list[str]:
    return reconstruction_outdated(services.store, session, row)


add_artifact_routes(
    router, "reconstruction", "reconstructions", ReconstructionOut, outdated=_outdated
)


@router.get("/reconstructions/{artifact_id}/csv", response_class=Response, responses=CSV)
def reconstruction_csv(session_id: str, artifact_id: str, services: ServicesDep) -> Response:
    """x,y,z (m) with the per-point diagnostics, as `teachpath reconstruct` writes it."""
    from drivers.export import reconstruction_csv_text

    row = services.artifact(session_id, "reconstruction", artifact_id)
    arrays = services.store.read_arrays(row)
    text = reconstruction_csv_text(ReconstructionCodec.per_point(arrays))
    return download(text, media_type="text/csv", filename=f"{artifact_id}.csv")


@router.get("/reconstructions/{artifact_id}/difference", response_class=Response)
def reconstruction_difference(
    session_id: str,
    artifact_id: str,
    services: ServicesDep,
    request: Request,
    against: str = Query(..., min_length=1, max_length=64, description="the other reconstruction"),
) -> Response:
    """For overlaying two reconstructions (gzip JSON): this one's points (tracker frame, m),
    each one's distance from the other's path, the mean and the largest with its index."""
    from service.preview import reconstruction_difference as difference

    rows = [services.artifact(session_id, "reconstruction", i) for i in (artifact_id, against)]
    points = [
        ReconstructionCodec.per_point(services.store.read_arrays(r))["points_m"] for r in rows
    ]
    return gzip_json(difference(points[0], points[1]), request)


@router.get(
    "/reconstructions/{artifact_id}/preview.png", response_class=FileResponse, responses=PNG
)
def reconstruction_preview(
    session_id: str, artifact_id: str, services: ServicesDep
) -> FileResponse:
    """A picture of the scan, the trace and the reconstruction, with the displacements."""
    services.artifact(session_id, "reconstruction", artifact_id)
    path = reconstructions.preview_path(services, artifact_id)
    if not path.is_file():
        raise ApiError(404, "not_found", f"no preview for {artifact_id}")
    return FileResponse(path, media_type="image/png")
