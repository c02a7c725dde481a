"""Captures: a tracker source recorded into the session as the samples arrive.

The samples go to a file as they arrive (:mod:`service.capture_runner`); when the capture stops,
the source ends or the service restarts after a crash, the file is cleaned into an immutable
recording that becomes the session's current one.

A live capture (NatNet) runs a receiver process of its own, so at most ``max_live_captures``
run at once (ten had the service at twelve processes): one more is a 409 ``too_many_captures``
until one stops. Its ``local`` address must be one of this machine's interfaces, checked by
binding to it before the capture starts (the wildcard 0.0.0.0 is refused by the schema).
"""

from __future__ import annotations

import socket
from typing import TYPE_CHECKING

import numpy as np

from drivers.errors import InputFileError
from drivers.tracking.readers import RawTrace, trace_from_raw
from service import tasks
from service.artifacts import ID_PREFIX, RecordingCodec
from service.capture_runner import CaptureRunner, read_capture_file
from service.core import Services
from service.errors import ApiError, not_found
from service.schemas import CaptureCreate, NatNetSourceIn, ReplaySource
from service.store import CaptureRow, SessionDeletedError, new_id

if TYPE_CHECKING:
    from drivers.tracking.base import TrackerSource

#: Source kinds that run a receiver process of their own (counted against max_live_captures).
LIVE_KINDS = frozenset({"natnet"})


def _source_for(
    services: Services, session_id: str, source_request: ReplaySource | NatNetSourceIn
) -> TrackerSource:
    """The tracker source a capture request names, built through the sources' registry."""
    from drivers.tracking.base import create_source

    if source_request.kind == "replay":
        recording = services.artifact(session_id, "recording", source_request.recording_id)
        return create_source(
            source_request.source_config(),
            recording=RecordingCodec.decode(services.store.read_arrays(recording)),
        )
    # The NatNet receiver runs in a child process of its own (no frame lost to the GIL held
    # elsewhere here); it connects when the runner asks for the first batch, and a server that
    # does not answer fails the capture with a clear error.
    return create_source(source_request.source_config())


def check_local_interface(address: str) -> None:
    """Refuse a ``local`` address that is not one of this machine's (a socket cannot bind it).

    Raises
    ------
    ApiError
        422 ``invalid_request``, naming the address and what to give instead.
    """
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind((address, 0))
        except OSError as exc:
            raise ApiError(
                422,
                "invalid_request",
                f"source.local: {address!r} is not an address of this machine ({exc.strerror}); "
                "give the address of its interface on the tracker's network (or 127.0.0.1 for a "
                "server on this machine)",
            ) from None


def start(services: Services, session_id: str, request: CaptureCreate) -> CaptureRow:
    """Start capturing from the request's source.

    Raises
    ------
    ApiError
        404 for an unknown session or recording, 422 for a ``local`` address that is not this
        machine's, 409 ``too_many_captures`` when ``max_live_captures`` live ones run already.
    """
    services.session(session_id)
    kind = request.source.kind
    if isinstance(request.source, NatNetSourceIn):  # a live feed (LIVE_KINDS)
        check_local_interface(request.source.local)
    source = _source_for(services, session_id, request.source)
    cap = services.settings.max_live_captures
    with services.live.lock:
        # Counted and registered under one lock: two requests at once cannot both take the
        # last place.
        running = sum(1 for r in services.live.captures.values() if r.kind in LIVE_KINDS)
        if kind in LIVE_KINDS and running >= cap:
            source.close()
            raise ApiError(
                409,
                "too_many_captures",
                f"{running} live capture(s) are running, the most allowed at once "
                f"(TEACHPATH_MAX_LIVE_CAPTURES = {cap}); stop one (POST "
                f"/sessions/{session_id}/captures/{{capture_id}}/stop) before starting another",
                detail={"running": running, "limit": cap},
            )
        row = services.store.create_capture(session_id, request.source.model_dump())
        runner = CaptureRunner(
            services.store,
            row.id,
            source,
            lambda capture_id, state, error: finish(services, capture_id, state, error),
            kind=kind,
        )
        services.live.captures[row.id] = runner
    runner.start()
    return row


def get(services: Services, session_id: str, capture_id: str) -> CaptureRow:
    services.session(session_id)
    row = services.store.capture(capture_id)
    if row is None or row.session_id != session_id:
        raise not_found("capture", capture_id)
    return row


def stop(services: Services, session_id: str, capture_id: str) -> CaptureRow:
    """Stop a capture; its samples so far become a recording."""
    get(services, session_id, capture_id)
    runner = services.live.captures.get(capture_id)
    if runner is not None:
        runner.stop()
        runner.thread.join(timeout=10)
    return get(services, session_id, capture_id)  # as the stop left it


def finish(services: Services, capture_id: str, state: str, error: str | None) -> None:
    """Turn a capture's file into a recording (also for one interrupted by a restart)."""
    store = services.store
    row = store.capture(capture_id)
    if row is None:  # deleted with its session meanwhile: nothing to turn into a recording
        return
    session = store.session(row.session_id)
    recording_id, n_samples = None, row.n_samples
    try:
        raw = RawTrace(read_capture_file(store.data_dir / row.path), "capture")
        # What the file holds, not the last count the runner wrote (a crash leaves it behind).
        n_samples = len(raw.batch)
        # A live feed tracks the rigid body: move it to the tip (when it has orientations).
        # A replayed recording is stored at the tip already.
        live = row.source.get("kind") == "natnet"
        tip = session.tip_offset_m if live and session is not None else None
        trace = trace_from_raw(
            raw,
            tip_offset_m=None if tip is None else np.array(tip),
            tip_needs_orientations=False,
        )
        recording_id = new_id(ID_PREFIX["recording"])
        summary = tasks.recording_summary(trace.recording, "capture")
        summary.update(trace.summary())
        store.add_arrays_artifact(
            artifact_id=recording_id,
            session_id=row.session_id,
            kind="recording",
            arrays=RecordingCodec.encode(trace.recording),
            inputs={"capture_id": capture_id},
            params={
                "format": "capture",
                "tip_offset_m": tip if trace.tip_offset_applied else None,
                "piece": trace.piece,
            },
            summary=summary,
        )
        store.update_session(row.session_id, recording_id=recording_id)
    except InputFileError as exc:
        # Nothing to keep is a failure whatever ended the capture; say both.
        recording_id = None
        reason = f"nothing usable was received: {exc}"
        state, error = "failed", (reason if error is None else f"{error}; {reason}")[:500]
    except SessionDeletedError:
        recording_id = None
        state, error = "cancelled", "the session was deleted; the samples were not kept"
    except (OSError, ValueError) as exc:
        recording_id = None
        state, error = "failed", f"the capture file could not be read: {exc}"
    store.update_capture(
        capture_id, state=state, recording_id=recording_id, error=error, n_samples=n_samples
    )
    with services.live.lock:
        services.live.captures.pop(capture_id, None)


def recover(services: Services) -> None:
    """After a restart: captures left running keep what they received, as recordings."""
    for row in services.store.stop_interrupted_captures():
        finish(
            services,
            row.id,
            "interrupted",
            "the service stopped during the capture; the samples received so far were kept",
        )
