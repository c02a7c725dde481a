"""Whether a stored result was made from the session's current inputs.

A session's inputs change: a new trace is uploaded, captured or replayed, a new scan, new
touches, a new tracker-to-base calibration. A reconstruction or a plan made before stays
stored, but it is *outdated*: it shows a path the operator did not trace last, or joints that
put the tool where the old calibration said. The pendant shows such results as outdated and
the real-arm gate refuses an outdated plan (``outdated_inputs``) unless the request picks it
explicitly (``accept_outdated``), and the run's record keeps what was accepted.

One function per kind, each returning the reasons in the operator's words (empty: current).
"""

from __future__ import annotations

from collections.abc import Sized

import numpy as np
from numpy.typing import ArrayLike

from service.cell import CellNow
from service.store import ArtifactRow, SessionRow, Store

#: Calibrations closer than this (translation, metres; rotation, radians) are the same one
#: (a JSON round trip changes nothing; a new calibration moves millimetres).
SAME_CALIBRATION_M = 1e-6
SAME_CALIBRATION_RAD = 1e-6


def reconstruction_outdated(
    store: Store, session: SessionRow, reconstruction: ArtifactRow
) -> list[str]:
    """What changed in the session since ``reconstruction`` was made from it.

    Parameters
    ----------
    store : Store
        For the session's newest touches and the scan's upload time.
    session : SessionRow
    reconstruction : ArtifactRow

    Returns
    -------
    list of str
        One sentence per input that is no longer the session's current one.
    """
    reasons = []
    inputs = reconstruction.inputs
    used = inputs.get("recording_ids") or [inputs.get("recording_id")]
    if session.recording_id not in used and _newer(store, session.recording_id, reconstruction):
        reasons.append(
            f"the trace: made from {', '.join(map(str, used))}; the session's trace is now "
            f"{session.recording_id}"
        )
    scan_id = inputs.get("scan_id")
    if session.scan_id != scan_id and _newer(store, session.scan_id, reconstruction):
        reasons.append(
            f"the scan: made with {scan_id or 'none'}; scan {session.scan_id} was added after it"
        )
    touches_id = inputs.get("touches_id")
    newest = store.artifacts(session.id, "touches")
    if touches_id is not None:
        if newest and newest[-1].id != touches_id:
            reasons.append(
                f"the touches: the scan was placed by {touches_id}; newer touches "
                f"{newest[-1].id} were added"
            )
    elif (
        newest
        and _touches_considered(reconstruction)
        and newest[-1].created_at > reconstruction.created_at
    ):
        # Made before any touches: the next reconstruction places the scan by them.
        reasons.append(
            f"the touches: touches {newest[-1].id} were added after it (a reconstruction now "
            "places the scan by them)"
        )
    return reasons


def trajectory_outdated(
    store: Store,
    session: SessionRow,
    trajectory: ArtifactRow,
    reconstruction: ArtifactRow | None = None,
    *,
    cell: CellNow | None = None,
) -> list[str]:
    """What changed since ``trajectory`` was planned: its reconstruction's inputs
    (:func:`reconstruction_outdated`), the tracker-to-base calibration and the cell.

    Parameters
    ----------
    store : Store
    session : SessionRow
    trajectory : ArtifactRow
    reconstruction : ArtifactRow, optional
        The trajectory's reconstruction (looked up when not given).
    cell : CellNow, optional
        The cell in force (:func:`service.cell.cell_now`); not compared when not given.

    Returns
    -------
    list of str
    """
    if reconstruction is None:
        reconstruction = store.artifact(
            trajectory.inputs.get("reconstruction_id", ""), kind="reconstruction"
        )
    reasons = (
        [] if reconstruction is None else reconstruction_outdated(store, session, reconstruction)
    )
    planned = trajectory.params.get("T_base_tracker")
    if planned is None and session.T_base_tracker is not None:
        reasons.append(
            "the tracker-to-base calibration: the plan was made without one; the session has "
            "one now"
        )
    elif planned is not None and session.T_base_tracker is not None:
        moved_m, turned_rad = _difference(planned, session.T_base_tracker)
        if moved_m > SAME_CALIBRATION_M or turned_rad > SAME_CALIBRATION_RAD:
            reasons.append(
                "the tracker-to-base calibration: the session's differs from the plan's by "
                f"{moved_m * 1e3:.1f} mm and {np.degrees(turned_rad):.2f} deg"
            )
    params = trajectory.params
    boxes, planes = params.get("keep_out_boxes") or [], params.get("cell_planes") or []
    if cell is not None and "keep_out_boxes" not in params:
        reasons.append(
            "the cell: the plan does not record the cell it was checked against (made by an "
            f"earlier version); the cell now has "
            f"{_count(cell.keep_out_boxes_m, 'keep-out box', 'keep-out boxes')} and "
            f"{_count(cell.cell_planes, 'plane', 'planes')} ({cell.source})"
        )
    elif cell is not None and cell.differs_from(boxes, planes):
        reasons.append(
            f"the cell: planned with {_count(boxes, 'keep-out box', 'keep-out boxes')} and "
            f"{_count(planes, 'plane', 'planes')}; the cell now has "
            f"{_count(cell.keep_out_boxes_m, 'keep-out box', 'keep-out boxes')} and "
            f"{_count(cell.cell_planes, 'plane', 'planes')} ({cell.source})"
        )
    return reasons


def _count(items: Sized, one: str, many: str) -> str:
    return f"{len(items)} {one if len(items) == 1 else many}"


def _touches_considered(reconstruction: ArtifactRow) -> bool:
    """Whether touches, had there been any, would have placed this reconstruction's scan (a
    scan used, registration on, touches not declined). Recorded at its start; for one made by
    an earlier version, judged from what it recorded (touches were then on by default)."""
    params, inputs = reconstruction.params, reconstruction.inputs
    if "touches_considered" in params:
        return bool(params["touches_considered"])
    alpha = params.get("alpha", "auto")
    uses_scan = alpha == "auto" or (isinstance(alpha, int | float) and alpha < 1.0)
    return inputs.get("scan_id") is not None and uses_scan and params.get("register", True)


def _newer(store: Store, artifact_id: str | None, than: ArtifactRow) -> bool:
    """Whether the session's current input ``artifact_id`` came after ``than`` was made (an
    input a request named on purpose, older than the result, is not a change since)."""
    if artifact_id is None:
        return False
    current = store.artifact(artifact_id)
    return current is not None and current.created_at > than.created_at


def _difference(T_a: ArrayLike, T_b: ArrayLike) -> tuple[float, float]:
    """Translation (m) and rotation angle (rad) between two 4x4 transforms."""
    a, b = np.asarray(T_a, dtype=np.float64), np.asarray(T_b, dtype=np.float64)
    moved_m = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return moved_m, float(np.arccos(np.clip(cos, -1.0, 1.0)))
