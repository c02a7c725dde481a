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


#: What a reconstruction's stored parameters hold beyond the core's ReconParams.
NOT_RECON_PARAMS = ("T_scan_tracker_init", "touches_considered")


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
    recording_ids: list[str]
    if request.recording_ids:
        recording_ids = list(dict.fromkeys(request.recording_ids))  # each once, in order
    elif (only := request.recording_id or session.recording_id) is not None:
        recording_ids = [only]
    else:
        raise ApiError(
            409,
            "no_recording",
            "the session has no recording: upload one "
            "(PUT /sessions/{id}/recording) or capture one first",
        )
    recordings = [services.artifact(session_id, "recording", rid) for rid in recording_ids]
    scan = None
    if request.use_scan:
        scan_id = request.scan_id or session.scan_id
        if scan_id is not None:
            scan = services.artifact(session_id, "scan", scan_id)
    params = request.recon_params()  # refuses bad combinations now, not in the worker
    touches = None
    if request.touches_id is not None:
        touches = services.artifact(session_id, "touches", request.touches_id)
    elif request.use_touches and request.registration:
        # The newest touches place the scan, unless the frames are to be trusted as given.
        newest = services.store.artifacts(session_id, "touches")
        touches = newest[-1] if newest else None
    uses_scan = params["alpha"] == "auto" or params["alpha"] < 1.0
    # Whether touches place the scan of this reconstruction (when there are any): touches
    # added later make it outdated only then (service/provenance.py).
    touches_considered = bool(
        scan is not None and uses_scan and request.use_touches and request.registration
    )
    if scan is None or not uses_scan or not request.use_touches:
        touches = None  # nothing to place, or asked not to: not an input
    T_init = request.T_scan_tracker or session.T_scan_tracker
    out_id = new_id(ID_PREFIX["reconstruction"])
    inputs: dict[str, str | list[str] | None] = (
        {"recording_id": recordings[0].id}
        if len(recordings) == 1
        else {"recording_ids": [r.id for r in recordings]}
    )
    inputs["scan_id"] = scan.id if scan else None
    if touches is not None:
        inputs["touches_id"] = touches.id
    stored_params = {
        **params,
        "T_scan_tracker_init": T_init if scan else None,
        "touches_considered": touches_considered,
    }
    done = services.record_when_done(
        session_id,
        "reconstruction",
        out_id,
        inputs=inputs,
        params=stored_params,
        result=lambda summary: {"reconstruction_id": out_id},
    )
    task = tasks.Reconstruct(
        recording_paths=tuple(str(services.store.path_of(r)) for r in recordings),
        scan_path=str(services.store.path_of(scan)) if scan else None,
        params=params,
        out_path=services.array_path(out_id),
        preview_path=str(preview_path(services, out_id)),
        preview_title=recordings[0].source_name or "reconstruction",
        T_scan_tracker_init=T_init if scan else None,
        touches_path=str(services.store.path_of(touches)) if touches else None,
    )
    return services.jobs.submit(
        session_id,
        "reconstruction",
        {**stored_params, **inputs},
        task,
        done,
        outputs=(task.out_path, task.preview_path),
    )
