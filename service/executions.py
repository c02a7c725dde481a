"""Executions: a trajectory run on the simulated arm (a dry run) or, through the real-arm gate,
on the configured arm; and stopping one.

A dry run is an ordinary CPU job (:class:`service.tasks.DryRun`). A real-arm execution runs in a
thread of this process (:class:`service.arm_runner.ExecutionRunner`) that talks to the arm
through the ur_rtde backend's own worker process. Both record the same
:class:`~service.artifacts.ExecutionSummary`, which is what the gate reads back.
"""

from __future__ import annotations

from drivers.robot.base import backend_config, create_backend
from service import tasks
from service.arm_runner import ExecutionRunner
from service.artifacts import ID_PREFIX, ExecutionCodec
from service.core import Services
from service.errors import not_found
from service.gate import check_real_arm
from service.pipelines import ExecutionOutcome
from service.schemas import ExecutionCreate
from service.store import ArtifactRow, JobRow, new_id


def start(services: Services, session_id: str, request: ExecutionCreate) -> JobRow:
    """Start an execution; the job's result names it.

    Raises
    ------
    RealArmRefused
        A real-arm execution the gate refuses (see :mod:`service.gate`).
    """
    services.session(session_id)
    trajectory = services.artifact(session_id, "trajectory", request.trajectory_id)
    out_id = new_id(ID_PREFIX["execution"])
    if request.backend == "sim":
        job = _dry_run(services, session_id, trajectory, request, out_id)
    else:
        job = _on_arm(services, session_id, trajectory, request, out_id)
    with services.live.lock:
        services.live.execution_jobs[out_id] = job.id
    return job


def _job_params(request: ExecutionCreate, trajectory: ArtifactRow, out_id: str) -> dict:
    return {
        "backend": request.backend,
        "mode": request.mode,
        "tolerance_m": request.tolerance_m,
        "execution_id": out_id,
        "trajectory_id": trajectory.id,
    }


def _job_result(execution_id: str, summary: dict) -> dict:
    return {"execution_id": execution_id, "completed": summary["completed"]}


def _artifact_params(services: Services, request: ExecutionCreate) -> dict:
    params = {
        "backend": request.backend,
        "dry_run": request.backend == "sim",
        "mode": request.mode,
        "tolerance_m": request.tolerance_m,
    }
    if request.backend == "ur_rtde":
        params["host"] = services.settings.ur_host
    return params


def _dry_run(services, session_id, trajectory, request, out_id) -> JobRow:
    done = services.record_when_done(
        session_id,
        "execution",
        out_id,
        inputs={"trajectory_id": trajectory.id},
        params=_artifact_params(services, request),
        result=lambda summary: _job_result(out_id, summary),
    )
    task = tasks.DryRun(
        trajectory_path=str(services.store.path_of(trajectory)),
        trajectory_summary=trajectory.summary,
        out_path=services.array_path(out_id),
        mode=request.mode,
        tolerance_m=request.tolerance_m,
    )
    return services.jobs.submit(
        session_id, "execution", _job_params(request, trajectory, out_id), task, done
    )


def _on_arm(services, session_id, trajectory, request, out_id) -> JobRow:
    from drivers.robot.dryrun import execution_report

    settings = services.settings
    check_real_arm(
        settings,
        trajectory,
        services.store.artifacts(session_id, "execution"),
        confirm=request.confirm,
        mode=request.mode,
        tolerance_m=request.tolerance_m,
    )
    loaded = tasks.load_trajectory(services.store.path_of(trajectory), trajectory.summary)
    config = backend_config("ur_rtde", host=settings.ur_host, robot=settings.ur_robot)
    backend = create_backend(config)
    job = services.store.create_job(
        session_id, "execution", _job_params(request, trajectory, out_id)
    )

    def record(execution_record, faults: list[str], duration_s: float) -> dict:
        outcome = ExecutionOutcome(
            report=execution_report(
                loaded,
                execution_record,
                mode=request.mode,
                duration_s=duration_s,
                lookahead_s=config.lookahead_s,
                faults=faults,
                dry_run=False,
            ),
            record=execution_record,
            backend="ur_rtde",
            tolerance_m=request.tolerance_m,
        )
        summary = outcome.summary()
        services.store.add_arrays_artifact(
            artifact_id=out_id,
            session_id=session_id,
            kind="execution",
            arrays=ExecutionCodec.encode(execution_record),
            inputs={"trajectory_id": trajectory.id},
            params=_artifact_params(services, request),
            summary=summary,
        )
        return _job_result(out_id, summary)

    runner = ExecutionRunner(
        services.store,
        job.id,
        backend,
        loaded,
        record,
        mode=request.mode,
        tolerance_m=request.tolerance_m,
    )
    with services.live.lock:
        services.live.executions[out_id] = runner
    runner.start()
    return services.store.job(job.id)


def stop(services: Services, execution_id: str) -> JobRow:
    """Stop the arm of a running execution (it decelerates) or cancel one not yet started."""
    job_id = services.live.execution_jobs.get(execution_id)
    if job_id is None:
        job = next(
            (
                j
                for j in services.store.jobs()
                if j.kind == "execution" and j.params.get("execution_id") == execution_id
            ),
            None,
        )
        if job is None:
            raise not_found("execution", execution_id)
        job_id = job.id
    runner = services.live.executions.get(execution_id)
    if runner is not None:
        runner.stop()
    elif services.store.job(job_id).state == "queued":
        services.jobs.cancel(job_id)
    return services.store.job(job_id)
