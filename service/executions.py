"""Executions: a trajectory run on the simulated arm (a dry run) or, through the real-arm gate,
on the configured arm; and stopping one.

A dry run is an ordinary CPU job (:class:`service.tasks.DryRun`). A real-arm execution runs in a
thread of this process (:class:`service.arm_runner.ExecutionRunner`) that talks to the arm
through the ur_rtde backend's own worker process. Both record the same
:class:`~service.artifacts.ExecutionSummary`, which is what the gate reads back.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import ValidationError

from drivers.robot.base import BackendConfig, ExecutionRecord, create_backend
from drivers.robot.dryrun import reached_phase, stream_lag_s
from recon.arrays import FloatArray
from recon.trajectory import JointTrajectory
from service import tasks
from service.arm_runner import ExecutionRunner, Recorder, Tool, journal_record
from service.artifacts import ID_PREFIX, ExecutionCodec, ReconstructionCodec, ScanCodec
from service.cell import cell_now
from service.core import Services
from service.errors import ApiError, CellUnknown, UnreadableTrajectory, not_found
from service.gate import (
    CellHere,
    check_approved,
    check_current,
    check_here,
    check_real_arm,
    check_request,
)
from service.pipelines import ExecutionOutcome, cell_for
from service.provenance import trajectory_outdated
from service.robot import ur_rtde_config
from service.schemas import ExecutionCreate
from service.store import FINISHED, ArtifactRow, JobRow, StorageError, Store, new_id

if TYPE_CHECKING:
    from recon.inputs import Scan

log = logging.getLogger("teachpath.executions")


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


def _job_params(request: ExecutionCreate, trajectory: ArtifactRow, out_id: str) -> dict[str, Any]:
    return {
        "backend": request.backend,
        "mode": request.mode,
        "tolerance_m": request.tolerance_m,
        "execution_id": out_id,
        "trajectory_id": trajectory.id,
    }


def _job_result(execution_id: str, summary: dict[str, Any]) -> dict[str, Any]:
    return {"execution_id": execution_id, "completed": summary["completed"]}


def _artifact_params(services: Services, request: ExecutionCreate) -> dict[str, Any]:
    params: dict[str, str | float | bool | None] = {
        "backend": request.backend,
        "dry_run": request.backend == "sim",
        "mode": request.mode,
        "tolerance_m": request.tolerance_m,
    }
    if request.backend == "ur_rtde":
        params["host"] = services.settings.ur_host
    return params


def _dry_run(
    services: Services,
    session_id: str,
    trajectory: ArtifactRow,
    request: ExecutionCreate,
    out_id: str,
) -> JobRow:
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
        session_id,
        "execution",
        _job_params(request, trajectory, out_id),
        task,
        done,
        outputs=(task.out_path,),
    )


def journal_path(services: Services, execution_id: str) -> Path:
    """Where a real-arm execution's samples are written as they arrive."""
    return services.store.data_dir / "journals" / f"{execution_id}.journal"


def _on_arm(
    services: Services,
    session_id: str,
    trajectory: ArtifactRow,
    request: ExecutionCreate,
    out_id: str,
) -> JobRow:
    settings = services.settings
    check_request(settings, confirm=request.confirm)
    check_approved(request.approved_sha256, trajectory.sha256, trajectory.id)
    # Outdated first: the clearest answer (a moved calibration also moves the cell checked
    # below); checked again under the lock, just before the arm is taken (uploads do not take
    # that lock: an input changed in the moments between is caught at the second look).
    check_current(
        trajectory_outdated(
            services.store,
            services.session(session_id),
            trajectory,
            cell=cell_now(services.store, settings),
        ),
        accept_outdated=request.accept_outdated,
    )
    tool = _tool_of(trajectory)
    # The samples are judged here, against this arm and this cell, before the lock (the check
    # takes a fraction of a second); the runner is given the very arrays judged.
    here = _cell_here(services, trajectory, tool)
    checked = check_here(settings, trajectory, _load_for_gate(services, trajectory), here)
    loaded = checked.trajectory
    # One owner: deciding and taking the arm happen under one lock, so two requests that
    # arrive together cannot both pass the gate.
    with services.live.lock:
        session = services.session(session_id)  # not deleted meanwhile (checked under this lock)
        cell = cell_now(services.store, settings)
        if cell.revision != here.cell_revision:
            # Cell edits take this lock too: after this look, none lands before the arm is taken.
            raise CellUnknown(
                "the cell was edited while this run was being checked: start the run again, "
                "and it is checked against the cell as it is now"
            )
        outdated = trajectory_outdated(services.store, session, trajectory, cell=cell)
        check_real_arm(
            settings,
            checked,
            services.store.artifacts(session_id, "execution"),
            dry_runs_made_here=_dry_runs_made_here(services, session_id),
            confirm=request.confirm,
            mode=request.mode,
            tolerance_m=request.tolerance_m,
            owner=services.live.arm_owner(),
            arm=services.robot.poll(),  # read now: the arm may have been jogged a moment ago
            outdated=outdated,
            accept_outdated=request.accept_outdated,
        )
        config = ur_rtde_config(settings)
        job = services.store.create_job(
            session_id, "execution", _job_params(request, trajectory, out_id)
        )
        runner = ExecutionRunner(
            services.store,
            job.id,
            create_backend(config),
            loaded,
            _recorder(
                services,
                session_id,
                trajectory,
                request,
                out_id,
                loaded,
                config,
                accepted_outdated=outdated,
            ),
            tool=tool,
            journal=str(journal_path(services, out_id)),
            mode=request.mode,
            tolerance_m=request.tolerance_m,
            approved_sha256=trajectory.sha256,  # checked equal to the request's, if it named one
            trajectory_id=trajectory.id,
        )
        services.live.executions[out_id] = runner
    runner.start()
    return services.store.job(job.id) or job  # as it stands now (perhaps already running)


def _load_for_gate(services: Services, trajectory: ArtifactRow) -> JointTrajectory:
    """The trajectory's arrays, or the gate's refusal if they cannot be read."""
    try:
        return tasks.load_trajectory(services.store.path_of(trajectory), trajectory.summary)
    except (OSError, ValueError, KeyError, ValidationError) as exc:
        raise UnreadableTrajectory(
            f"the samples of trajectory {trajectory.id} cannot be read ({type(exc).__name__}: "
            f"{str(exc)[:200]}); plan it again"
        ) from None


def _dry_runs_made_here(services: Services, session_id: str) -> set[str]:
    """Executions produced by jobs of this data folder's service (a bundle carries no jobs)."""
    return {
        str(job.params.get("execution_id"))
        for job in services.store.jobs(session_id)
        if job.kind == "execution"
        and job.state == "succeeded"
        and job.params.get("backend") == "sim"
    }


def _cell_here(services: Services, trajectory: ArtifactRow, tool: Tool) -> CellHere:
    """This server's cell (its planes and keep-out boxes, never the plan's stored copy) with the
    scan the trajectory was planned along, placed as it was planned.

    Raises
    ------
    CellUnknown
        The plan names a scan that cannot be read or placed: the check cannot decide.
    UnreadableTrajectory
        The plan's tool (radius, clearance, TCP) is not a valid one.
    """
    from recon.plan_params import PlanParams
    from recon.transforms import transform_from_pose

    store, settings = services.store, services.settings
    cell_in_force = cell_now(store, settings)  # not the plan's copy of it
    summary = trajectory.summary if isinstance(trajectory.summary, dict) else {}
    scan: Scan | None = None
    T_scan_tracker: FloatArray | None = None
    scan_id = trajectory.inputs.get("scan_id")
    if scan_id is not None:
        try:
            scan_row = store.artifact(str(scan_id), kind="scan", session_id=trajectory.session_id)
            recon_row = store.artifact(
                str(trajectory.inputs.get("reconstruction_id")), kind="reconstruction"
            )
            if scan_row is None or recon_row is None:
                raise LookupError("the scan or the reconstruction is no longer stored")
            scan = ScanCodec.decode(tasks.load_arrays(store.path_of(scan_row)))
            T_scan_tracker = ReconstructionCodec.decode(
                tasks.load_arrays(store.path_of(recon_row))
            ).T_scan_tracker
            if T_scan_tracker is None:
                raise LookupError("the reconstruction does not say where the scan was")
        except (OSError, ValueError, KeyError, LookupError) as exc:
            raise CellUnknown(
                f"the scan this trajectory was planned along cannot be placed here ({exc}), so "
                "its motion cannot be checked against the workpiece: reconstruct and plan again"
            ) from None
    try:
        params = PlanParams(
            robot=settings.ur_robot,
            tool_radius_m=trajectory.params.get("tool_radius_m", PlanParams.tool_radius_m),
            tool_spheres_m=tuple(trajectory.params.get("tool_spheres_m") or ()),
            clearance_m=trajectory.params.get("clearance_m", PlanParams.clearance_m),
        )
        T_flange_tcp = transform_from_pose(np.asarray(tool[0], dtype=np.float64))
        T_base_tracker = _placement_here(store, trajectory, summary.get("T_base_tracker"))
        _require_this_mount(trajectory, settings.mount_up)
        cell = cell_for(
            scan,
            T_scan_tracker,
            None if T_base_tracker is None else np.asarray(T_base_tracker, dtype=np.float64),
            cell_in_force.keep_out_boxes_m,
            cell_in_force.cell_planes,
        )
    except (TypeError, ValueError) as exc:
        raise UnreadableTrajectory(
            f"the tool or placement of trajectory {trajectory.id} is not a valid one ({exc}); "
            "plan it again"
        ) from None
    return CellHere(
        cell=cell,
        T_flange_tcp=T_flange_tcp,
        tool_radius_m=params.tool_radius_m,
        tool_spheres_m=params.tool_spheres_m,
        clearance_m=params.clearance_m,
        cell_revision=cell_in_force.revision,
    )


#: A trajectory's tracker-to-base transform may differ from its session's by this much and
#: still be the same calibration (rounding of a stored copy), metres and radians.
SAME_PLACEMENT_M, SAME_PLACEMENT_RAD = 1e-4, 1e-4


def _placement_here(
    store: Store, trajectory: ArtifactRow, planned_with: list[list[float]] | None
) -> FloatArray | list[list[float]] | None:
    """The tracker-to-base transform the motion is checked with: the session's calibration in
    this cell. A plan made with another one (a recalibrated cell, or a forged copy that moves the
    workpiece away from the motion) is refused: the scan would be checked in the wrong place.

    Raises
    ------
    CellUnknown
    """
    session = store.session(trajectory.session_id)
    stored = None if session is None else session.T_base_tracker
    if stored is None:
        return planned_with  # no calibration here: the plan's own, as the plan was checked
    here = np.asarray(stored, dtype=np.float64)
    if planned_with is not None:
        planned = np.asarray(planned_with, dtype=np.float64)
        moved_m = float(np.linalg.norm(here[:3, 3] - planned[:3, 3]))
        turn = np.clip((np.trace(here[:3, :3].T @ planned[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
        if moved_m > SAME_PLACEMENT_M or float(np.arccos(turn)) > SAME_PLACEMENT_RAD:
            raise CellUnknown(
                f"trajectory {trajectory.id} was planned with another tracker-to-base "
                f"calibration than this session's ({moved_m * 1e3:.1f} mm, "
                f"{np.degrees(np.arccos(turn)):.2f} deg apart): plan it again here"
            )
    return here


def _require_this_mount(trajectory: ArtifactRow, mount_up: Sequence[float]) -> None:
    """A plan made for another mount (its tool comes at the work from what is not above here)
    is refused; a plan from before mounts were recorded was made for a floor mount.

    Raises
    ------
    CellUnknown
    """
    planned = np.asarray(trajectory.params.get("mount_up") or (0.0, 0.0, 1.0), dtype=np.float64)
    here = np.asarray(mount_up, dtype=np.float64)
    if planned.shape != (3,) or not np.all(np.isfinite(planned)):
        raise ValueError(f"its mount_up {trajectory.params.get('mount_up')!r} is not a direction")
    cos = float(planned @ here / (np.linalg.norm(planned) * np.linalg.norm(here)))
    if cos < np.cos(SAME_PLACEMENT_RAD):
        raise CellUnknown(
            f"trajectory {trajectory.id} was planned for another mount (up "
            f"{', '.join(f'{v:g}' for v in planned)} in the base frame) than this arm's "
            f"({', '.join(f'{v:g}' for v in here)}, TEACHPATH_MOUNT_UP): plan it again here"
        )


def _tool_of(trajectory: ArtifactRow) -> tuple[list[float], float | None, list[float]]:
    """The TCP pose and payload a trajectory was planned with (for the controller; a payload
    of None is not set: the installation's stays)."""
    params = trajectory.params
    tcp = params.get("tcp_pose") or [*(params.get("tcp_offset_m") or (0.0, 0.0, 0.0)), 0, 0, 0]
    if not any(tcp):
        tcp = [*(params.get("tcp_offset_m") or (0.0, 0.0, 0.0)), 0.0, 0.0, 0.0]
    return (
        [float(v) for v in tcp],
        None if params.get("payload_kg") is None else float(params["payload_kg"]),
        [float(v) for v in params.get("payload_cog_m") or (0.0, 0.0, 0.0)],
    )


def _recorder(
    services: Services,
    session_id: str,
    trajectory: ArtifactRow,
    request: ExecutionCreate,
    out_id: str,
    loaded: JointTrajectory,
    config: BackendConfig,
    *,
    accepted_outdated: Sequence[str] = (),
) -> Recorder:
    """What the runner calls at the end: the execution's artifact, measured as a dry run is.
    ``accepted_outdated``: what had changed since the plan when the operator picked it anyway
    (kept in the record's params)."""
    params = _artifact_params(services, request)
    if request.approved_sha256 is not None:
        params["approved_sha256"] = request.approved_sha256  # what the operator confirmed
    if accepted_outdated:
        params["accepted_outdated"] = list(accepted_outdated)

    def record(
        execution_record: ExecutionRecord | None, faults: list[str], stopped_in: str | None
    ) -> dict[str, Any]:
        summary = _real_summary(loaded, execution_record, faults, stopped_in, request, config)
        services.store.add_arrays_artifact(
            artifact_id=out_id,
            session_id=session_id,
            kind="execution",
            arrays=ExecutionCodec.encode(execution_record),
            inputs={"trajectory_id": trajectory.id},
            params=params,
            summary=summary,
        )
        journal_path(services, out_id).unlink(missing_ok=True)  # the artifact holds it now
        return {**_job_result(out_id, summary), "stopped_in": stopped_in}

    return record


def _real_summary(
    trajectory: JointTrajectory,
    record: ExecutionRecord | None,
    faults: list[str],
    stopped_in: str | None,
    request: ExecutionCreate,
    config: BackendConfig,
) -> dict[str, Any]:
    from drivers.robot.dryrun import execution_report

    outcome = ExecutionOutcome(
        report=execution_report(
            trajectory,
            record,
            mode=request.mode,
            lookahead_s=config.lookahead_s,
            faults=faults,
            dry_run=False,
        ),
        record=record,
        backend="ur_rtde",
        tolerance_m=request.tolerance_m,
    )
    realtime = None if record is None else record.realtime
    return {**outcome.summary(), "stopped_in": stopped_in, "realtime": realtime}


@dataclass(frozen=True)
class StopOutcome:
    """What a stop request found: the job, and whether its execution had already ended."""

    job: JobRow
    already_ended: bool


def latch_stop(services: Services, execution_id: str) -> bool:
    """Latch the stop of an execution running on this instance's arm, at once.

    Touches neither the database nor a thread pool (a dictionary read and two events set), so
    the stop route calls it on the event loop before anything else. Returns whether a runner of
    that execution was found here.
    """
    runner = services.live.executions.get(execution_id)
    if runner is None:
        return False
    runner.stop()
    return True


def stop(services: Services, execution_id: str) -> StopOutcome:
    """Stop the arm of a running execution (it decelerates, and nothing moves after), or
    cancel one not yet started; says whether the execution had already ended."""
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
    job = services.store.job(job_id)
    if job is None:  # its row deleted with its session: the arm's stop still wins
        if runner is not None:
            runner.stop()
        raise not_found("execution", execution_id)
    already_ended = job.state in FINISHED
    elsewhere = runner is None and job.owner not in (None, services.store.instance_id)
    if elsewhere and (not already_ended or services.store.is_live(job.owner)):
        # Several instances share the database: only the one that runs it can stop this arm.
        # Answering "stopped" or "already ended" here could be a lie with the arm still moving
        # (whatever the database says, the instance that drives the arm knows).
        raise ApiError(
            409,
            "other_instance",
            f"execution {execution_id} runs on another teachpath instance ({job.owner}): this "
            "one cannot stop it. Send the stop to that instance, or stop the arm at its teach "
            "pendant or emergency stop",
        )
    if runner is not None:
        runner.stop()  # latched, whether it moves yet or not
    elif not already_ended:
        # A dry run (a pool job): stopped, it ends cancelled and never counts as passed.
        services.jobs.discard(job_id)
    return StopOutcome(job=services.store.job(job_id) or job, already_ended=already_ended)


def _running_here(services: Services, execution_id: str) -> ExecutionRunner:
    """The runner of an execution this instance is running, or the error that says why not."""
    runner: ExecutionRunner | None = services.live.executions.get(execution_id)
    if runner is None:
        if execution_id in services.live.execution_jobs:
            raise ApiError(
                409, "not_running", f"execution {execution_id} has ended: nothing to change"
            )
        raise ApiError(
            404,
            "not_found",
            f"execution {execution_id} is not running on this instance: change its speed "
            "where it was started, or at the arm's teach pendant",
        )
    if not runner.running:
        raise ApiError(409, "not_running", f"execution {execution_id} has ended: nothing to change")
    if not runner.overridable:
        raise ApiError(
            409,
            "not_streamed",
            f"execution {execution_id} runs as a movePath, which the controller times itself: "
            "its speed cannot be changed nor the run paused here. Stop it, or use the speed "
            "slider of the arm's teach pendant",
        )
    return runner


def speed_view(execution_id: str, runner: ExecutionRunner) -> dict[str, Any]:
    """What :class:`service.schemas.RunSpeedOut` shows."""
    return {"execution_id": execution_id, **runner.speed_view()}


def set_speed(services: Services, execution_id: str, fraction: float) -> dict[str, Any]:
    """Change a running execution's speed (5 .. 100 % of the planned speed)."""
    runner = _running_here(services, execution_id)
    try:
        runner.set_speed(fraction)
    except ValueError as error:
        raise ApiError(422, "bad_speed", str(error)) from None
    log.info("execution %s: speed set to %.0f %%", execution_id, 100 * fraction)
    return speed_view(execution_id, runner)


def pause(services: Services, execution_id: str) -> dict[str, Any]:
    """Bring a running execution's arm to rest on its path (idempotent)."""
    runner = _running_here(services, execution_id)
    if runner.step != "moving":
        raise ApiError(
            409,
            "not_moving",
            f"execution {execution_id} is {runner.step}, not moving yet: there is nothing to "
            "pause. Stop it to cancel it",
        )
    runner.pause()
    log.info("execution %s: paused", execution_id)
    return speed_view(execution_id, runner)


def resume(services: Services, execution_id: str, approved_sha256: str) -> dict[str, Any]:
    """Go on from a pause, once the operator has approved the run again (idempotent)."""
    runner = _running_here(services, execution_id)
    if runner.approved_sha256 is not None and approved_sha256 != runner.approved_sha256:
        raise ApiError(
            409,
            "approval_mismatch",
            f"the approved trajectory ({approved_sha256[:12]}…) is not the one running "
            f"({runner.approved_sha256[:12]}…): reload the page and approve the resume again",
            detail={"approved_sha256": approved_sha256, "running_sha256": runner.approved_sha256},
        )
    runner.resume()
    log.info("execution %s: resumed", execution_id)
    return speed_view(execution_id, runner)


def recover(services: Services) -> None:
    """After a restart: real-arm executions that were running when the service stopped become
    execution records from their journals (what was executed is kept)."""
    folder = services.store.data_dir / "journals"
    if not folder.is_dir():
        return
    # ``.csv``: the text journals of earlier versions, still recovered.
    journals = sorted([*folder.glob("exe_*.journal"), *folder.glob("exe_*.csv")])
    for journal in journals:
        execution_id = journal.stem
        try:
            _recover_one(services, execution_id, journal)
        except Exception:  # one damaged journal must not stop the service from starting
            log.exception("could not recover the execution journal %s", journal)


def _recover_one(services: Services, execution_id: str, journal: Path) -> None:
    store = services.store
    job = next(
        (
            j
            for j in store.jobs()
            if j.kind == "execution" and j.params.get("execution_id") == execution_id
        ),
        None,
    )
    if job is not None and job.state == "running" and store.is_live(job.owner):
        return  # another live instance drives this arm now: its journal is its own
    if job is None or store.artifact(execution_id) is not None:
        journal.unlink(missing_ok=True)
        return
    trajectory_row = store.artifact(job.params["trajectory_id"], kind="trajectory")
    if trajectory_row is None:  # deleted with its session: the journal is kept, unread
        raise StorageError(
            f"the plan {job.params['trajectory_id']} of execution {execution_id} is gone: its "
            f"journal {journal.name} is kept but cannot become an execution record"
        )
    trajectory = tasks.load_trajectory(store.path_of(trajectory_row), trajectory_row.summary)
    fault = "the service stopped during the execution"
    record = journal_record(trajectory, journal, fault)
    if record is None:  # nothing was journalled: the arm never moved
        record = ExecutionRecord(np.zeros(0), np.zeros((0, 6)), np.zeros((0, 6)), False, fault)
    request = ExecutionCreate(
        trajectory_id=trajectory_row.id,
        backend="ur_rtde",
        mode=job.params.get("mode", "servoj"),
        tolerance_m=job.params.get("tolerance_m", 5e-4),
    )
    config = ur_rtde_config(services.settings, robot=trajectory.robot)
    where = reached_phase(trajectory, record, stream_lag_s(request.mode, config.lookahead_s))
    summary = _real_summary(trajectory, record, [fault], where, request, config)  # its fault
    store.add_arrays_artifact(
        artifact_id=execution_id,
        session_id=job.session_id,
        kind="execution",
        arrays=ExecutionCodec.encode(record),
        inputs={"trajectory_id": trajectory_row.id},
        params={**_artifact_params(services, request), "recovered_from_journal": True},
        summary=summary,
    )
    journal.unlink(missing_ok=True)
