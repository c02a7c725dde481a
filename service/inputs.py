"""Inputs of a session: uploaded recordings and scans, and its calibrations.

Uploads are parsed in a worker process (Open3D's readers hold the GIL); a file that cannot be
read is a 422 that changes nothing. The upload workflows are coroutines (they await the parse),
so their database and file work runs in the thread pool, never on the event loop. Each upload
becomes an immutable artifact and the session's current recording or scan; the original bytes
are kept beside it. Calibrations are fields of the session, and how each was obtained (the
residuals of its fit) goes into its calibration report.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from starlette.concurrency import run_in_threadpool

from recon.params import PIVOT_TOLERANCE_M
from service import pipelines, tasks
from service.artifacts import ID_PREFIX
from service.core import Services
from service.schemas import BaseCalibrationIn, CalibrationIn
from service.store import ArtifactRow, SessionRow, new_id, now


@dataclass(frozen=True)
class Upload:
    """A file as it arrived: its bytes and the name the client gave it."""

    content: bytes
    filename: str


@dataclass(frozen=True)
class TraceOptions:
    """How to read an uploaded trace."""

    format: str | None = None
    units: str | None = None
    rigid_body: str | None = None
    marker: str | None = None
    piece: int | Literal["all"] | None = None


def _tip_for(session: SessionRow, marker: str | None):
    """The session's tip offset, for recordings of a rigid body (a single marker has no
    orientation to carry an offset)."""
    if session.tip_offset_m is None or marker is not None:
        return None
    return tuple(session.tip_offset_m)


def _keep_upload(services: Services, artifact_id: str, upload: Upload) -> None:
    """The original bytes too: raw inputs are kept as they came."""
    safe = "".join(c if c.isalnum() or c in "._-" else "_" for c in Path(upload.filename).name)
    services.store.write_bytes(f"uploads/{artifact_id}/{safe or 'upload'}", upload.content)


async def add_recording(
    services: Services, session_id: str, upload: Upload, options: TraceOptions
) -> ArtifactRow:
    """Parse an uploaded trace and make it the session's recording."""
    session = await run_in_threadpool(services.session, session_id)
    tip = _tip_for(session, options.marker)
    arrays, summary = await services.jobs.run(
        tasks.ParseRecording(
            content=upload.content,
            filename=upload.filename,
            format=options.format,
            units=options.units,
            rigid_body=options.rigid_body,
            marker=options.marker,
            tip_offset_m=tip,
            piece=options.piece,
        )
    )
    params = {
        "format": summary["format"],
        "units": summary.get("units") or options.units,
        "rigid_body": options.rigid_body,
        "marker": options.marker,
        "piece": summary.get("piece"),
        "tip_offset_m": list(tip) if tip and summary["tip_offset_applied"] else None,
    }
    return await run_in_threadpool(
        _store_upload, services, session_id, "recording", upload, arrays, params, summary
    )


def _store_upload(
    services: Services,
    session_id: str,
    kind: str,
    upload: Upload,
    arrays: dict,
    params: dict,
    summary: dict,
) -> ArtifactRow:
    """Record a parsed upload as the session's current recording or scan, with its bytes."""
    artifact_id = new_id(ID_PREFIX[kind])
    row = services.store.add_arrays_artifact(
        artifact_id=artifact_id,
        session_id=session_id,
        kind=kind,
        arrays=arrays,
        params=params,
        summary=summary,
        source_name=upload.filename,
    )
    _keep_upload(services, artifact_id, upload)
    services.store.update_session(session_id, **{f"{kind}_id": artifact_id})
    return row


async def add_scan(
    services: Services,
    session_id: str,
    upload: Upload,
    *,
    format: str | None,
    units: str,
    options: dict | None,
) -> ArtifactRow:
    """Parse an uploaded scan and make it the session's scan."""
    await run_in_threadpool(services.session, session_id)
    settings = services.settings
    # A client may lower the reader's resource limits, not raise them past the server's.
    limits = {
        "max_unpacked_mb": settings.max_scan_unpacked_mb,
        "timeout_s": settings.max_scan_decode_s,
    }
    arrays, summary = await services.jobs.run(
        tasks.ParseScan(
            content=upload.content,
            filename=upload.filename,
            format=format,
            units=units,
            options=options,
            limits=limits,
        )
    )
    params = {"format": summary["format"], "units": units, "options": options}
    return await run_in_threadpool(
        _store_upload, services, session_id, "scan", upload, arrays, params, summary
    )


def set_calibration(services: Services, session_id: str, request: CalibrationIn) -> SessionRow:
    """Set the calibrations named in the request (an explicit null clears one)."""
    services.session(session_id)
    fields = {name: getattr(request, name) for name in request.model_fields_set}
    return services.store.update_session(session_id, **fields)


async def pivot_calibration(
    services: Services,
    session_id: str,
    upload: Upload,
    options: TraceOptions,
    *,
    tolerance_m: float = PIVOT_TOLERANCE_M,
    accept_poor_fit: bool = False,
) -> tuple[SessionRow, dict]:
    """The tip offset from a pivoting recording; sets the session's ``tip_offset_m`` (a fit
    worse than ``tolerance_m`` RMS is refused unless ``accept_poor_fit``)."""
    await run_in_threadpool(services.session, session_id)
    result = await services.jobs.run(
        tasks.ParsePivot(
            content=upload.content,
            filename=upload.filename,
            format=options.format,
            units=options.units,
            rigid_body=options.rigid_body,
            tolerance_m=tolerance_m,
            accept_poor_fit=accept_poor_fit,
        )
    )
    row = await run_in_threadpool(
        services.store.record_calibration,
        session_id,
        "pivot",
        {**result, "source_name": upload.filename, "at": now().isoformat()},
        tip_offset_m=result["tip_offset_m"],
    )
    return row, result


def base_calibration(
    services: Services, session_id: str, request: BaseCalibrationIn
) -> tuple[SessionRow, dict]:
    """``T_base_tracker`` from point pairs; sets the session's ``T_base_tracker``."""
    services.session(session_id)
    scale = 1e-3 if request.units == "mm" else 1.0
    outcome = pipelines.point_pairs(
        [[v * scale for v in pair.base] for pair in request.pairs],
        [[v * scale for v in pair.tracker] for pair in request.pairs],
        tolerance_m=request.tolerance_m,
        accept_poor_fit=request.accept_poor_fit,
    )
    result = outcome.as_json()
    row = services.store.record_calibration(
        session_id,
        "base",
        {**result, "at": now().isoformat()},
        T_base_tracker=result["T_base_tracker"],
    )
    return row, result
