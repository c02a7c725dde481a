"""Reconstructions: a session's recording reconstructed with its scan, as a job.

The parameters are checked here, before anything is queued; the worker task
(:class:`service.tasks.Reconstruct`) runs the pipeline the command line runs and writes the
arrays (with the scan model and the transform it used, for planning) and a preview picture.
"""

from __future__ import annotations

from pathlib import Path

from service import tasks
from service.artifacts import ID_PREFIX
from service.core import Services
from service.errors import ApiError
from service.schemas import ReconstructionCreate
from service.store import JobRow, new_id


def preview_path(services: Services, reconstruction_id: str) -> Path:
    """Where the preview picture of a reconstruction is kept."""
    return Path(services.array_path(reconstruction_id, "png"))


def start(services: Services, session_id: str, request: ReconstructionCreate) -> JobRow:
    """Queue the reconstruction; the job's result names it.

    Raises
    ------
    ApiError
        409 ``no_recording`` when the session has none; 404 for unknown ids.
    ValueError
        A combination of parameters the core refuses.
    """
    session = services.session(session_id)
    recording_id = request.recording_id or session.recording_id
    if recording_id is None:
        raise ApiError(
            409,
            "no_recording",
            "the session has no recording: upload one "
            "(PUT /sessions/{id}/recording) or capture one first",
        )
    recording = services.artifact(session_id, "recording", recording_id)
    scan = None
    if request.use_scan:
        scan_id = request.scan_id or session.scan_id
        if scan_id is not None:
            scan = services.artifact(session_id, "scan", scan_id)
    params = request.recon_params()  # refuses bad combinations now, not in the worker
    T_init = request.T_scan_tracker or session.T_scan_tracker
    out_id = new_id(ID_PREFIX["reconstruction"])
    inputs = {"recording_id": recording.id, "scan_id": scan.id if scan else None}
    stored_params = {**params, "T_scan_tracker_init": T_init if scan else None}
    done = services.record_when_done(
        session_id,
        "reconstruction",
        out_id,
        inputs=inputs,
        params=stored_params,
        result=lambda summary: {"reconstruction_id": out_id},
    )
    task = tasks.Reconstruct(
        recording_path=str(services.store.path_of(recording)),
        scan_path=str(services.store.path_of(scan)) if scan else None,
        params=params,
        out_path=services.array_path(out_id),
        preview_path=str(preview_path(services, out_id)),
        preview_title=recording.source_name or "reconstruction",
        T_scan_tracker_init=T_init if scan else None,
    )
    return services.jobs.submit(
        session_id,
        "reconstruction",
        {**stored_params, **inputs},
        task,
        done,
        outputs=(task.out_path, task.preview_path),
    )
