"""Inputs of a session: uploaded recordings and scans, and its calibrations.

Uploads are parsed each in a child process of its own (Open3D's readers hold the GIL), waited
on from a thread beside the job pool (:class:`service.parse_lane.ParseLane`), under the memory
and time limits of the settings
(``max_parse_memory_mb``, ``max_scan_decode_s``, ``max_trace_parse_s``; see
:func:`service.tasks.parse_in_child`); a file that cannot be read is a 422, one past a limit a
413, and neither changes anything. The upload workflows are coroutines (they await the parse),
so their database and file work runs in the thread pool, never on the event loop. Each upload
becomes an immutable artifact and the session's current recording or scan, with the original
bytes kept beside it, in one step: the artifact is recorded only once its arrays and the bytes
are on disk, together with the session's update, and nothing is left behind if any of that
fails. Calibrations are fields of the session, and how each was obtained (the residuals of its
fit) goes into its calibration report.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from starlette.concurrency import run_in_threadpool

from recon.params import PIVOT_TOLERANCE_M
from service import pipelines, tasks
from service.artifacts import ID_PREFIX
from service.core import Services
from service.parsing import Arrays
from service.schemas import BaseCalibrationIn, CalibrationIn
from service.settings import Settings
from service.store import ArtifactRow, SessionRow, new_id, now
from service.uploads import storage_name


@dataclass(frozen=True)
class Upload:
    """A file as it arrived: its bytes and its name (cleaned, see
    :func:`service.uploads.clean_filename`)."""

    content: bytes
    filename: str


def trace_parse_limits(settings: Settings) -> tasks.ParseLimits:
    """The bounds of a trace upload's parse, from the settings."""
    return tasks.ParseLimits(
        time_s=settings.max_trace_parse_s,
        memory_mb=settings.max_parse_memory_mb,
        time_setting="TEACHPATH_MAX_TRACE_PARSE_S",
        memory_setting="TEACHPATH_MAX_PARSE_MEMORY_MB",
    )


def scan_parse_limits(settings: Settings) -> tasks.ParseLimits:
    """The bounds of a scan upload's parse, from the settings."""
    return tasks.ParseLimits(
        time_s=settings.max_scan_decode_s,
        memory_mb=settings.max_parse_memory_mb,
        time_setting="TEACHPATH_MAX_SCAN_DECODE_S",
        memory_setting="TEACHPATH_MAX_PARSE_MEMORY_MB",
    )


#: Scan reader options bounded by the settings, and the settings (named in messages).
SCAN_LIMIT_SETTINGS = {
    "max_unpacked_mb": ("max_scan_unpacked_mb", "TEACHPATH_MAX_SCAN_UNPACKED_MB"),
    "timeout_s": ("max_scan_decode_s", "TEACHPATH_MAX_SCAN_DECODE_S"),
    "max_frame_pixels": ("max_scan_frame_pixels", "TEACHPATH_MAX_SCAN_FRAME_PIXELS"),
    "max_pixels": ("max_scan_pixels", "TEACHPATH_MAX_SCAN_PIXELS"),
}


@dataclass(frozen=True)
class TraceOptions:
    """How to read an uploaded trace."""

    format: str | None = None
    units: str | None = None
    rigid_body: str | None = None
    marker: str | None = None
    piece: int | Literal["all"] | None = None


def _tip_for(session: SessionRow, marker: str | None) -> tuple[float, float, float] | None:
    """The session's tip offset, for recordings of a rigid body (a single marker has no
    orientation to carry an offset)."""
    if session.tip_offset_m is None or marker is not None:
        return None
    x, y, z = session.tip_offset_m  # stored as 3 numbers (every way of setting it checks that)
    return (x, y, z)


async def add_recording(
    services: Services,
    session_id: str,
    upload: Upload,
    options: TraceOptions,
    *,
    kind: Literal["recording", "touches"] = "recording",
) -> ArtifactRow:
    """Parse an uploaded trace and make it the session's recording (``kind="recording"``), or
    keep it as the session's newest touches of the workpiece (``kind="touches"``: a recording
    whose tip rests on several points, see :mod:`recon.touches`)."""
    session = await run_in_threadpool(services.session, session_id)
    tip = _tip_for(session, options.marker)
    artifact_id = new_id(ID_PREFIX[kind])
    summary = await _parsed(
        services,
        artifact_id,
        trace_task(
            services.settings,
            kind,
            upload,
            options,
            tip_offset_m=tip,
            out_path=services.array_path(artifact_id),
        ),
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
        _store_upload, services, session_id, kind, artifact_id, upload, params, summary
    )


async def _parsed(
    services: Services, artifact_id: str, task: tasks.ParseRecording | tasks.ParseScan
) -> dict[str, Any]:
    """Run an upload's parse task, whose child writes the arrays at the artifact's path; its
    summary. The arrays never pass through this process (a 24 MB float PLY is 48 MB of points),
    and a parse that fails leaves no file (nor the partial one of a child ended mid-write)."""
    try:
        parsed: tuple[Arrays, dict[str, Any]] = await services.parses.run(task)
        _, summary = parsed
    except BaseException:
        final = Path(services.array_path(artifact_id))
        for path in (final, *final.parent.glob(f".{final.name}.*")):  # see drivers.files
            path.unlink(missing_ok=True)
        raise
    return summary


def _store_upload(
    services: Services,
    session_id: str,
    kind: str,
    artifact_id: str,
    upload: Upload,
    params: dict[str, Any],
    summary: dict[str, Any],
) -> ArtifactRow:
    """Record a parsed upload, whose arrays its parse wrote, as the session's current recording
    or scan, with its bytes (the original bytes too: raw inputs are kept as they came), all or
    nothing."""
    return services.store.add_upload_artifact(
        artifact_id=artifact_id,
        session_id=session_id,
        kind=kind,
        arrays=None,
        upload_path=f"uploads/{artifact_id}/{storage_name(upload.filename)}",
        content=upload.content,
        # Touches are not the session's "current" anything: reconstructions take the newest.
        session_fields={} if kind == "touches" else {f"{kind}_id": artifact_id},
        params=params,
        summary=summary,
        source_name=upload.filename,
    )


async def add_scan(
    services: Services,
    session_id: str,
    upload: Upload,
    *,
    format: str | None,
    units: str,
    options: dict[str, Any] | None,
) -> ArtifactRow:
    """Parse an uploaded scan and make it the session's scan."""
    await run_in_threadpool(services.session, session_id)
    artifact_id = new_id(ID_PREFIX["scan"])
    summary = await _parsed(
        services,
        artifact_id,
        scan_task(
            services.settings,
            upload,
            format=format,
            units=units,
            options=options,
            out_path=services.array_path(artifact_id),
        ),
    )
    params = {"format": summary["format"], "units": units, "options": options}
    return await run_in_threadpool(
        _store_upload, services, session_id, "scan", artifact_id, upload, params, summary
    )


def trace_task(
    settings: Settings,
    kind: Literal["recording", "touches"],
    upload: Upload,
    options: TraceOptions,
    *,
    tip_offset_m: tuple[float, float, float] | None,
    out_path: str | None = None,
) -> tasks.ParseRecording:
    """The parse of a trace upload (``kind`` "recording" or "touches") within the settings'
    limits."""
    return tasks.ParseRecording(
        kind=kind,
        content=upload.content,
        filename=upload.filename,
        format=options.format,
        units=options.units,
        rigid_body=options.rigid_body,
        marker=options.marker,
        tip_offset_m=tip_offset_m,
        piece=options.piece,
        parse_limits=trace_parse_limits(settings),
        out_path=out_path,
    )


def scan_task(
    settings: Settings,
    upload: Upload,
    *,
    format: str | None,
    units: str,
    options: dict[str, Any] | None,
    out_path: str | None = None,
) -> tasks.ParseScan:
    """The parse of a scan upload within the settings' limits."""
    return tasks.ParseScan(
        content=upload.content,
        filename=upload.filename,
        format=format,
        units=units,
        options=options,
        # A client may lower the reader's resource limits, not raise them past the server's.
        limits={
            option: getattr(settings, name) for option, (name, _) in SCAN_LIMIT_SETTINGS.items()
        },
        limit_names={option: env for option, (_, env) in SCAN_LIMIT_SETTINGS.items()},
        parse_limits=scan_parse_limits(settings),
        out_path=out_path,
    )


def reread_upload(
    settings: Settings, kind: str, params: dict[str, Any], content: bytes, filename: str
) -> Arrays:
    """An upload's arrays as reading its bytes again here gives them: the same readers, options
    and limits (child process, memory, time) as an upload of that file. For files that come from
    elsewhere (a bundle's raw uploads are held to what an upload is).

    Parameters
    ----------
    settings : Settings
    kind : {"recording", "touches", "scan"}
    params : dict
        The artifact's recorded reading options (format, units, marker, tip offset, ...).
    content : bytes
    filename : str

    Returns
    -------
    dict of str to numpy.ndarray
        The artifact's arrays as the reader gives them.

    Raises
    ------
    InputFileError, ReconError, ValueError
        What the reader says of the file (an unreadable one, a limit passed, options that are
        not a reader's).
    """
    upload = Upload(content=content, filename=filename)
    task: tasks.ParseScan | tasks.ParseRecording
    if kind == "scan":
        task = scan_task(
            settings,
            upload,
            format=params.get("format"),
            units=params.get("units") or "m",
            options=params.get("options"),
        )
    elif kind in ("recording", "touches"):
        trace_kind: Literal["recording", "touches"] = (
            "recording" if kind == "recording" else "touches"
        )
        options = TraceOptions(
            **{key: params.get(key) for key in ("format", "units", "rigid_body", "marker", "piece")}
        )
        tip = params.get("tip_offset_m")
        task = trace_task(
            settings, trace_kind, upload, options, tip_offset_m=None if tip is None else tuple(tip)
        )
    else:
        raise ValueError(f"a {kind} keeps no uploaded file")
    arrays, _ = task.run()
    return arrays


def set_calibration(services: Services, session_id: str, request: CalibrationIn) -> SessionRow:
    """Set the calibrations named in the request (an explicit null clears one); the report
    says each was set directly, and when (so no earlier fit or file is named as its source)."""
    services.session(session_id)
    fields = {name: getattr(request, name) for name in request.model_fields_set}
    row = None
    for name, value in fields.items():
        entry = {"field": name, "at": now().isoformat(), "cleared": value is None}
        row = services.store.record_calibration(session_id, f"set:{name}", entry, **{name: value})
    return row if row is not None else services.session(session_id)


#: A calibration file is a few hundred bytes; anything far larger is not one.
MAX_CALIBRATION_FILE_BYTES = 64 * 1024
#: The calibration files a session takes, by the name they carry, and the field each sets.
CALIBRATION_FILES = {
    "T_base_tracker": "T_base_tracker",
    "T_scan_tracker": "T_scan_tracker",
    "tip_offset": "tip_offset_m",
}


def load_calibration_file(
    services: Services, session_id: str, content: bytes, filename: str
) -> SessionRow:
    """Set the calibration a stored file holds (``teachpath calibrate`` writes them): a
    tracker-to-base or tracker-to-scan transform, or a pen's tip offset, read by the CLI's
    own readers. The file's name, date and residual go into the session's calibration report.

    Raises
    ------
    ApiError
        422 ``invalid_file``: too large, not JSON, not one of those calibrations, not rigid,
        unknown units (nothing of the session changes).
    """
    import json

    from drivers.calibration import read_calibration, read_tip_calibration
    from drivers.errors import InputFileError
    from service.errors import ApiError

    services.session(session_id)
    label = filename or "the file"
    if len(content) > MAX_CALIBRATION_FILE_BYTES:
        raise ApiError(
            422,
            "invalid_file",
            f"{label} is {len(content) // 1024} KB: a calibration file is a few hundred bytes "
            "(choose the JSON file `teachpath calibrate` wrote)",
        )
    try:
        try:
            name = json.loads(content).get("name")
        except (ValueError, AttributeError, RecursionError):
            name = None  # the readers below say what is wrong with it
        if name == "tip_offset":
            tip = read_tip_calibration(content, label=label)
            fields = {"tip_offset_m": [float(v) for v in tip.offset_m]}
            created, residual = tip.created, tip.residual_rms_m
        else:
            calibration = read_calibration(content, label=label)
            if calibration.name not in CALIBRATION_FILES:
                raise InputFileError(
                    f"{label} holds {calibration.name}; a session takes "
                    f"{', '.join(CALIBRATION_FILES)} (as `teachpath calibrate` writes them)"
                )
            fields = {CALIBRATION_FILES[calibration.name]: calibration.matrix.tolist()}
            created, residual = calibration.created, calibration.residual_rms_m
    except (InputFileError, RecursionError) as error:
        message = str(error) if isinstance(error, InputFileError) else f"{label} nests too deep"
        raise ApiError(422, "invalid_file", message) from None
    (field,) = fields
    entry: dict[str, Any] = {
        "source_name": filename,
        "field": field,
        "created": created,
        "at": now().isoformat(),
    }
    if residual is not None:
        entry["residual_rms_m"] = residual
    return services.store.record_calibration(session_id, f"file:{field}", entry, **fields)


async def pivot_calibration(
    services: Services,
    session_id: str,
    upload: Upload,
    options: TraceOptions,
    *,
    tolerance_m: float = PIVOT_TOLERANCE_M,
    accept_poor_fit: bool = False,
) -> tuple[SessionRow, dict[str, Any]]:
    """The tip offset from a pivoting recording; sets the session's ``tip_offset_m`` (a fit
    worse than ``tolerance_m`` RMS is refused unless ``accept_poor_fit``)."""
    await run_in_threadpool(services.session, session_id)
    result = await services.parses.run(
        tasks.ParsePivot(
            content=upload.content,
            filename=upload.filename,
            format=options.format,
            units=options.units,
            rigid_body=options.rigid_body,
            parse_limits=trace_parse_limits(services.settings),
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
) -> tuple[SessionRow, dict[str, Any]]:
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
