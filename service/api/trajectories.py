"""Trajectories: planned as jobs, listed, downloaded."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from fastapi import APIRouter, Query, Request, Response

from service import tasks, trajectories
from service.api.common import CSV, add_artifact_routes, download, gzip_json
from service.api.deps import ServicesDep
from service.artifacts import TrajectorySummary
from service.cell import CellUnreadable, cell_now
from service.core import Services
from service.provenance import trajectory_outdated
from service.schemas import JobOut, TrajectoryCreate, TrajectoryOut
from service.store import ArtifactRow, JobRow, SessionRow

router = APIRouter(prefix="/sessions/{session_id}", tags=["trajectories"])


@router.post("/trajectories", status_code=202, response_model=JobOut)
def start_trajectory(session_id: str, body: TrajectoryCreate, services: ServicesDep) -> JobRow:
    """Plan a timed joint trajectory along a reconstruction; the result holds the feasibility
    report."""
    return trajectories.start(services, session_id, body)


@router.post("/trajectories/{trajectory_id}/move-to-start", status_code=202, response_model=JobOut)
def start_move_to_start(session_id: str, trajectory_id: str, services: ServicesDep) -> JobRow:
    """Plan a move of its own from where the arm is now to this plan's start (a joint move at
    the plan's transit speeds, checked against the cell). The result is a trajectory like any
    other (its summary's ``move_to_start_of`` names the plan): dry-run it, approve it and run
    it; the plan then starts where the arm stands. 409 ``at_start`` when it already does."""
    return trajectories.start_move_to_start(services, session_id, trajectory_id)


def _outdated(services: Services, session: SessionRow, row: ArtifactRow) -> list[str]:
    try:
        cell = cell_now(services.store, services.settings)
    except CellUnreadable as exc:  # the list stays readable; the plans cannot run
        return [*trajectory_outdated(services.store, session, row), exc.message]
    return trajectory_outdated(services.store, session, row, cell=cell)


add_artifact_routes(router, "trajectory", "trajectories", TrajectoryOut, outdated=_outdated)


@router.get("/trajectories/{artifact_id}/csv", response_class=Response, responses=CSV)
def trajectory_csv(session_id: str, artifact_id: str, services: ServicesDep) -> Response:
    """t,q0..q5 (s, rad) and the planned TCP x,y,z,rx,ry,rz (base frame), as `teachpath plan`
    writes it."""
    from drivers.export import trajectory_csv_text

    row = services.artifact(session_id, "trajectory", artifact_id)
    trajectory = tasks.load_trajectory(services.store.path_of(row), row.summary)
    meta = TrajectorySummary.model_validate(row.summary).file_meta()
    return download(
        trajectory_csv_text(trajectory, meta={**meta, "session_id": session_id, "id": row.id}),
        media_type="text/csv",
        filename=f"{artifact_id}.csv",
    )


@router.get("/trajectories/{artifact_id}/preview", response_class=Response)
def trajectory_preview(
    session_id: str,
    artifact_id: str,
    services: ServicesDep,
    request: Request,
    max_samples: int = Query(1500, ge=10, le=20_000, description="about this many samples"),
) -> Response:
    """The plan as the pendant animates it (gzip JSON): per kept sample the time, phase, the
    arm's joint positions from its DH chain and the TCP (base frame, m), TCP speed, joint
    angles, and each margin as the smallest since the previous sample sent (joint limits,
    wrist and elbow singularity, clearance to the cell); the slow-downs with their causes."""
    from service.parsing import load_arrays
    from service.preview import trajectory_preview as preview

    row = services.artifact(session_id, "trajectory", artifact_id)
    path = services.store.path_of(row)
    trajectory = tasks.load_trajectory(path, row.summary)
    clearance = load_arrays(path).get("clearance_m")
    return gzip_json(preview(trajectory, clearance, max_samples=max_samples), request)


@router.get(
    "/trajectories/{artifact_id}/plot.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}}},
)
def trajectory_plot(session_id: str, artifact_id: str, services: ServicesDep) -> Response:
    """The plan preview as a picture: TCP speed against the requested speed with the causes of
    slow-downs, joint angles and speeds against their limits, the phases shaded (what
    `teachpath plan --plot` writes)."""
    import tempfile

    from service.plots import plot_plan

    row = services.artifact(session_id, "trajectory", artifact_id)
    trajectory = tasks.load_trajectory(services.store.path_of(row), row.summary)
    with tempfile.TemporaryDirectory(prefix="teachpath-plot-") as tmp:
        path = Path(tmp) / "plan.png"
        plot_plan(path, trajectory, title=f"{row.id} ({trajectory.robot})")
        content = path.read_bytes()
    return Response(content, media_type="image/png", headers={"Cache-Control": "no-store"})


@router.get(
    "/trajectories/{artifact_id}/urscript",
    response_class=Response,
    responses={200: {"content": {"text/plain": {}}}},
)
def trajectory_urscript(
    session_id: str,
    artifact_id: str,
    services: ServicesDep,
    mode: Literal["servoj", "movep"] = Query("servoj", description="the path as servoj or movep"),
    tolerance_m: float = Query(5e-4, gt=0, le=0.01, description="movep: largest deviation"),
) -> Response:
    """The trajectory as a standalone URScript program for the teach pendant (see
    `teachpath export-urscript`)."""
    from drivers.robot.urscript import program_header, urscript_program

    row = services.artifact(session_id, "trajectory", artifact_id)
    trajectory = tasks.load_trajectory(services.store.path_of(row), row.summary)
    summary = TrajectorySummary.model_validate(row.summary)
    meta = {**summary.file_meta(), "session_id": session_id, "id": row.id}
    program = urscript_program(
        trajectory,
        tcp_pose=summary.tcp_pose or (0.0,) * 6,
        payload_kg=summary.payload_kg,
        payload_cog_m=summary.payload_cog_m or (0.0, 0.0, 0.0),
        mode=mode,
        tolerance_m=tolerance_m,
        header=program_header(meta, f"trajectory {row.id}"),
    )
    return download(program, media_type="text/plain", filename=f"{artifact_id}.script")
