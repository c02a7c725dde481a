"""Reconstructions, trajectories and executions: started as jobs, listed for comparison."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
from fastapi import APIRouter, Depends, Response
from fastapi.responses import FileResponse

from service.api.deps import context
from service.context import artifact_json
from service.errors import ApiError
from service.jobs import job_json
from service.schemas import (
    ArtifactOut,
    ExecutionCreate,
    JobOut,
    ReconstructionCreate,
    TrajectoryCreate,
)

router = APIRouter(tags=["reconstructions, trajectories, executions"])


@router.post("/sessions/{session_id}/reconstructions", status_code=202, response_model=JobOut)
def start_reconstruction(session_id: str, body: ReconstructionCreate, ctx=Depends(context)) -> dict:
    """Reconstruct the session's recording (with its scan); the job's result names the
    reconstruction."""
    return job_json(ctx.reconstruct(session_id, body))


@router.post("/sessions/{session_id}/trajectories", status_code=202, response_model=JobOut)
def start_trajectory(session_id: str, body: TrajectoryCreate, ctx=Depends(context)) -> dict:
    """Plan a timed joint trajectory along a reconstruction; the result holds the feasibility
    report."""
    return job_json(ctx.plan(session_id, body))


@router.post("/sessions/{session_id}/executions", status_code=202, response_model=JobOut)
def start_execution(session_id: str, body: ExecutionCreate, ctx=Depends(context)) -> dict:
    """Run a trajectory: on the simulated arm (a dry run, the default) or, confirmed and after
    a passed dry run, on the configured real arm."""
    return job_json(ctx.execute(session_id, body))


@router.post("/executions/{execution_id}/stop", response_model=JobOut)
def stop_execution(execution_id: str, ctx=Depends(context)) -> dict:
    """Stop the arm (decelerating) or cancel an execution that has not started."""
    return job_json(ctx.stop_execution(execution_id))


@router.get("/sessions/{session_id}/reconstructions", response_model=list[ArtifactOut])
def list_reconstructions(session_id: str, ctx=Depends(context)) -> list[dict]:
    """All reconstructions of the session, with their parameters and summaries to compare."""
    ctx.session(session_id)
    return [artifact_json(a) for a in ctx.store.artifacts(session_id, "reconstruction")]


@router.get("/sessions/{session_id}/trajectories", response_model=list[ArtifactOut])
def list_trajectories(session_id: str, ctx=Depends(context)) -> list[dict]:
    ctx.session(session_id)
    return [artifact_json(a) for a in ctx.store.artifacts(session_id, "trajectory")]


@router.get("/sessions/{session_id}/executions", response_model=list[ArtifactOut])
def list_executions(session_id: str, ctx=Depends(context)) -> list[dict]:
    ctx.session(session_id)
    return [artifact_json(a) for a in ctx.store.artifacts(session_id, "execution")]


@router.get("/sessions/{session_id}/reconstructions/{artifact_id}", response_model=ArtifactOut)
def get_reconstruction(session_id: str, artifact_id: str, ctx=Depends(context)) -> dict:
    return artifact_json(ctx.artifact(session_id, "reconstruction", artifact_id))


@router.get("/sessions/{session_id}/trajectories/{artifact_id}", response_model=ArtifactOut)
def get_trajectory(session_id: str, artifact_id: str, ctx=Depends(context)) -> dict:
    return artifact_json(ctx.artifact(session_id, "trajectory", artifact_id))


@router.get("/sessions/{session_id}/executions/{artifact_id}", response_model=ArtifactOut)
def get_execution(session_id: str, artifact_id: str, ctx=Depends(context)) -> dict:
    return artifact_json(ctx.artifact(session_id, "execution", artifact_id))


def _csv(header: list[str], columns: list[np.ndarray], filename: str) -> Response:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(header)
    data = np.column_stack(columns)
    for row in data:
        writer.writerow(["" if not np.isfinite(v) else f"{v:.10g}" for v in row])
    return Response(
        buffer.getvalue(),
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )


@router.get(
    "/sessions/{session_id}/reconstructions/{artifact_id}/csv",
    response_class=Response,
    responses={200: {"content": {"text/csv": {}}}},
)
def reconstruction_csv(session_id: str, artifact_id: str, ctx=Depends(context)) -> Response:
    """x,y,z (m) with the per-point diagnostics, as `teachpath reconstruct` writes it."""
    from drivers.export import reconstruction_csv_text

    row = ctx.artifact(session_id, "reconstruction", artifact_id)
    return Response(
        reconstruction_csv_text(ctx.store.read_arrays(row)),
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="{artifact_id}.csv"'},
    )


@router.get(
    "/sessions/{session_id}/reconstructions/{artifact_id}/preview.png",
    response_class=FileResponse,
    responses={200: {"content": {"image/png": {}}}},
)
def reconstruction_preview(session_id: str, artifact_id: str, ctx=Depends(context)):
    """A picture of the scan, the trace and the reconstruction, with the displacements."""
    ctx.artifact(session_id, "reconstruction", artifact_id)
    path: Path = ctx.preview_path(artifact_id)
    if not path.is_file():
        raise ApiError(404, "not_found", f"no preview for {artifact_id}")
    return FileResponse(path, media_type="image/png")


@router.get(
    "/sessions/{session_id}/trajectories/{artifact_id}/csv",
    response_class=Response,
    responses={200: {"content": {"text/csv": {}}}},
)
def trajectory_csv(session_id: str, artifact_id: str, ctx=Depends(context)) -> Response:
    """t,q0..q5 (s, rad) and the planned TCP x,y,z,rx,ry,rz (base frame)."""
    from drivers.export import TRAJECTORY_COLUMNS

    row = ctx.artifact(session_id, "trajectory", artifact_id)
    data = ctx.store.read_arrays(row)
    return _csv(
        list(TRAJECTORY_COLUMNS),
        [data["t_s"], data["q_rad"], data["tcp_m"], data["tcp_rotvec"]],
        f"{artifact_id}.csv",
    )


@router.get(
    "/sessions/{session_id}/executions/{artifact_id}/csv",
    response_class=Response,
    responses={200: {"content": {"text/csv": {}}}},
)
def execution_csv(session_id: str, artifact_id: str, ctx=Depends(context)) -> Response:
    """What ran: t, planned and actual joints."""
    row = ctx.artifact(session_id, "execution", artifact_id)
    data = ctx.store.read_arrays(row)
    if "t_s" not in data:
        raise ApiError(404, "not_found", f"execution {artifact_id} recorded no samples")
    header = ["t"] + [f"q{i}_planned" for i in range(6)] + [f"q{i}_actual" for i in range(6)]
    return _csv(
        header, [data["t_s"], data["q_planned_rad"], data["q_actual_rad"]], f"{artifact_id}.csv"
    )
