"""The demo session: the paper's Fig. 4 scene (a noisy trace along a cylinder's rim and a
misplaced scan of it), calibrated in front of a UR5e, created on start with ``--demo``."""

from __future__ import annotations

from service import tasks
from service.artifacts import ID_PREFIX, RecordingCodec, ScanCodec
from service.store import SessionRow, Store, new_id

#: Where the demo workpiece sits in front of a UR5e, metres (the demo session's calibration).
DEMO_T_BASE_TRACKER = [[1.0, 0, 0, 0.45], [0, 1.0, 0, 0.1], [0, 0, 1.0, 0.05], [0, 0, 0, 1.0]]
DEMO_NAME = "demo"


def create_demo_session(store: Store) -> SessionRow | None:
    """The demo session, unless one exists."""
    if any(s.name == DEMO_NAME for s in store.sessions()):
        return None
    from recon import scenes

    scene = scenes.cylinder_edge(0)
    assert scene.scan is not None  # the cylinder scene is scanned
    session = store.create_session(DEMO_NAME)
    rec_id, scan_id = new_id(ID_PREFIX["recording"]), new_id(ID_PREFIX["scan"])
    store.add_arrays_artifact(
        artifact_id=rec_id,
        session_id=session.id,
        kind="recording",
        arrays=RecordingCodec.encode(scene.recording, truth_m=scene.truth_m),
        params={"format": "synthetic", "scene": scene.description},
        summary=tasks.recording_summary(scene.recording, "synthetic"),
        source_name="demo: cylinder edge trace",
    )
    store.add_arrays_artifact(
        artifact_id=scan_id,
        session_id=session.id,
        kind="scan",
        arrays=ScanCodec.encode(scene.scan),
        params={"format": "synthetic"},
        summary=tasks.scan_summary(scene.scan, "synthetic"),
        source_name="demo: cylinder scan",
    )
    return store.update_session(
        session.id, recording_id=rec_id, scan_id=scan_id, T_base_tracker=DEMO_T_BASE_TRACKER
    )
