"""Sessions and their calibrations."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, File, Form, Response, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from starlette.background import BackgroundTask

from recon.params import PIVOT_TOLERANCE_M
from service import inputs
from service.api.common import received
from service.api.deps import ServicesDep
from service.schemas import (
    ArtifactOut,
    BaseCalibrationIn,
    BundleImportOut,
    CalibrationIn,
    CalibrationResult,
    SessionCreate,
    SessionOut,
)
from service.store import ArtifactRow, SessionRow

router = APIRouter(prefix="/sessions", tags=["sessions"])


@router.post("", status_code=201, response_model=SessionOut)
def create_session(body: SessionCreate, services: ServicesDep) -> SessionRow:
    """A new, empty session."""
    return services.store.create_session(body.name)


@router.get("", response_model=list[SessionOut])
def list_sessions(services: ServicesDep) -> list[SessionRow]:
    return services.store.sessions()


@router.post(
    "/import",
    status_code=201,
    response_model=BundleImportOut,
    responses={200: {"model": BundleImportOut, "description": "the session was here already"}},
)
async def import_session(
    services: ServicesDep,
    response: Response,
    file: UploadFile = File(..., description="a session bundle (GET /sessions/{id}/bundle)"),
) -> dict[str, Any]:
    """Import a session bundle: every checksum, the manifest and the schema are checked before
    anything changes (422 ``bundle_invalid`` says what is wrong). A session that is here already
    with the same content is left as it is (200, ``created`` false); one with the same id and
    other content is refused (409 ``bundle_conflict``). Each file in it is held to the upload
    limit, the whole to eight times that, and no member may unpack to over 100 times its
    compressed size. Each raw upload in it is read again as an upload of it would be (the same
    readers and limits) and must give the bundle's arrays."""
    from service.bundles import import_under

    async with received(file, services) as upload:
        result = await run_in_threadpool(
            import_under, services.store, upload.content, services.settings
        )
    if not result.created:
        response.status_code = 200
    return {
        "session": services.session(result.session_id),
        "created": result.created,
        "n_artifacts": result.n_artifacts,
        "n_files": result.n_files,
        "n_bytes": result.n_bytes,
    }


@router.get(
    "/{session_id}/bundle",
    response_class=FileResponse,
    responses={200: {"content": {"application/zip": {}}}},
)
async def export_session(session_id: str, services: ServicesDep) -> FileResponse:
    """The session as one zip: a manifest (teachpath and schema versions, the session and its
    calibrations, every artifact with its inputs, parameters, summary and SHA-256) and every
    file of every artifact. Exporting the same session again gives the same bytes."""
    import tempfile

    from service.bundles import export_bundle

    services.session(session_id)
    # Closed by the `with` below; opened first, so that a failure can delete it by its name.
    handle = tempfile.NamedTemporaryFile(  # noqa: SIM115
        prefix="teachpath-bundle-", suffix=".zip", delete=False
    )
    path = Path(handle.name)
    try:
        with handle:
            await run_in_threadpool(export_bundle, services.store, session_id, handle)
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    return FileResponse(
        path,
        media_type="application/zip",
        filename=f"{session_id}.zip",
        background=BackgroundTask(path.unlink, missing_ok=True),
    )


@router.get("/{session_id}", response_model=SessionOut)
def get_session(session_id: str, services: ServicesDep) -> SessionRow:
    return services.session(session_id)


@router.delete("/{session_id}", status_code=204)
def delete_session(session_id: str, services: ServicesDep) -> Response:
    """Soft delete: the session disappears from the API, its data stays on disk. Its jobs are
    cancelled (a running one's result is discarded) and its captures stop. Refused (409
    session_owns_arm) while an execution of the session runs on the arm: stop it first."""
    services.delete_session(session_id)
    return Response(status_code=204)


@router.get("/{session_id}/artifacts", response_model=list[ArtifactOut])
def list_artifacts(session_id: str, services: ServicesDep) -> list[ArtifactRow]:
    """Every artifact of the session, of every kind, oldest first: what it is made of and what
    each was made from (inputs, parameters, checksum)."""
    services.session(session_id)
    return services.store.artifacts(session_id)


@router.put("/{session_id}/calibration", response_model=SessionOut)
def set_calibration(session_id: str, body: CalibrationIn, services: ServicesDep) -> SessionRow:
    """Set calibrations: T_base_tracker (tracker -> robot base), T_scan_tracker (tracker ->
    scan, the initial guess for registration), tip_offset_m (the pen's tip in its rigid body's
    frame, applied to recordings uploaded or captured afterwards). Fields left out keep their
    value; an explicit null clears one."""
    return inputs.set_calibration(services, session_id, body)


@router.post("/{session_id}/calibration/file", response_model=SessionOut)
async def load_calibration_file(
    session_id: str,
    services: ServicesDep,
    file: UploadFile = File(
        ..., description="a calibration `teachpath calibrate` wrote (JSON, at most 64 KB)"
    ),
) -> SessionRow:
    """Set the calibration a stored file holds: T_base_tracker, T_scan_tracker (4x4, as
    ``teachpath calibrate base|scan`` writes them) or the pen's tip offset (``calibrate
    pivot``); checked as the CLI checks them (rigid, units). 422 ``invalid_file`` otherwise,
    and nothing changes."""
    async with received(file, services) as upload:
        row: SessionRow = await run_in_threadpool(
            inputs.load_calibration_file, services, session_id, upload.content, upload.filename
        )
        return row


@router.post("/{session_id}/calibration/pivot", response_model=CalibrationResult)
async def pivot_calibration(
    session_id: str,
    services: ServicesDep,
    file: UploadFile = File(..., description="a recording of the pen pivoting about its tip"),
    format: str | None = Form(None, description="csv, motive or c3d; default from the name"),
    units: Literal["m", "mm"] | None = Form(None, description="if the file states none"),
    rigid_body: str | None = Form(None, description="Motive: the pen's rigid body"),
    tolerance_m: float = Form(
        PIVOT_TOLERANCE_M, gt=0, le=0.01, description="largest acceptable RMS of the tip (m)"
    ),
    accept_poor_fit: Literal["true", "false"] = Form(
        "false", description="store a fit worse than the tolerance (default: refused, 422)"
    ),
) -> dict[str, Any]:
    """Pivot calibration: the tip offset from a recording where the tip stays on one point
    while the pen tilts in every direction. Sets the session's tip_offset_m; a fit worse than
    the tolerance is refused (422 poor_fit with its figures) unless accepted."""
    async with received(file, services) as upload:
        row, result = await inputs.pivot_calibration(
            services,
            session_id,
            upload,
            inputs.TraceOptions(format=format, units=units, rigid_body=rigid_body),
            tolerance_m=tolerance_m,
            accept_poor_fit=accept_poor_fit == "true",
        )
    return {"session": row, "result": result}


@router.post("/{session_id}/calibration/base", response_model=CalibrationResult)
def base_calibration(
    session_id: str, body: BaseCalibrationIn, services: ServicesDep
) -> dict[str, Any]:
    """T_base_tracker from point pairs (the same points in the base and tracker frames, at
    least 3 not on a line); pairs off by more than the tolerance are reported and left out.
    Sets the session's T_base_tracker."""
    row, result = inputs.base_calibration(services, session_id, body)
    return {"session": row, "result": result}
