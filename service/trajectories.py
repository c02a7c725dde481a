"""Trajectories: a reconstruction planned for a UR arm, as a job.

Planning reuses what the reconstruction stored: its path, the transform between tracker and scan
it used and the scan model it built, so no registration runs twice and the plan records which
``T_scan_tracker`` its tool axis was taken with.
"""

from __future__ import annotations

import numpy as np

from service import tasks
from service.artifacts import ID_PREFIX, as_core_params
from service.cell import cell_now
from service.core import Services
from service.reconstructions import NOT_RECON_PARAMS
from service.robot import start_joints
from service.schemas import TrajectoryCreate
from service.store import JobRow, new_id


def start(services: Services, session_id: str, request: TrajectoryCreate) -> JobRow:
    """Queue the planning; the job's result names the trajectory.

    Raises
    ------
    ApiError
        404 for an unknown reconstruction.
    ValueError
        Parameters the core refuses (an unknown robot, ...).
    """
    session = services.session(session_id)
    recon = services.artifact(session_id, "reconstruction", request.reconstruction_id)
    params = request.plan_params()  # refuses bad combinations now, not in the worker
    if "transit_tcp_speed_m_s" not in request.model_fields_set:
        # The joint moves keep to this server's TCP speed cap, which the real-arm gate checks on
        # every sample: a plan made here with the defaults can run on the arm.
        params["transit_tcp_speed_m_s"] = min(
            params["transit_tcp_speed_m_s"], services.settings.max_speed_m_s
        )
    if "mount_up" not in request.model_fields_set:
        params["mount_up"] = tuple(services.settings.mount_up)  # this cell's mount
    start_from = "given"
    if params["start_q_rad"] is None:
        # The plan starts where the arm is (a real arm's joints now, the sim's home).
        q_start, start_from = start_joints(services.robot, services.settings)
        params["start_q_rad"] = tuple(float(v) for v in q_start)
        request.plan_params_with(params)  # the arm's joints are checked as the request's are
    T = request.T_base_tracker or session.T_base_tracker
    recon_params = {k: v for k, v in recon.params.items() if k not in NOT_RECON_PARAMS}
    out_id = new_id(ID_PREFIX["trajectory"])
    inputs = {"reconstruction_id": recon.id, "scan_id": recon.inputs.get("scan_id")}
    boxes, planes = cell_now(services.store, services.settings).as_lists()
    # The cell too: a replay of the plan must check it against the same obstacles.
    # This cell's arm, calibrated as its controller is (the plan's joints are right for it).
    calibration = services.settings.arm_calibration
    stored_params = {
        **params,
        "T_base_tracker": T,
        "start_from": start_from,
        "keep_out_boxes": boxes,
        "cell_planes": planes,
    }
    done = services.record_when_done(
        session_id,
        "trajectory",
        out_id,
        inputs=inputs,
        params=stored_params,
        result=lambda summary: {"trajectory_id": out_id},
    )
    scan_id = recon.inputs.get("scan_id")
    scan = services.store.artifact(scan_id, kind="scan") if scan_id else None
    task = tasks.Plan(
        reconstruction_path=str(services.store.path_of(recon)),
        params=params,
        recon_params=recon_params,
        T_base_tracker=T,
        out_path=services.array_path(out_id),
        scan_path=None if scan is None else str(services.store.path_of(scan)),
        keep_out_boxes=boxes,
        cell_planes=planes,
        start_from=start_from,
        calibration=None if calibration is None else calibration.as_dict(),
    )
    return services.jobs.submit(
        session_id, "trajectory", {**stored_params, **inputs}, task, done, outputs=(task.out_path,)
    )


def start_move_to_start(services: Services, session_id: str, trajectory_id: str) -> JobRow:
    """Queue the planning of a move of its own from where the arm is to a plan's start: a
    trajectory (``move_to_start_of`` names the plan) that is dry-run, approved and run as any
    plan is, so that the plan itself can run afterwards without being planned again.

    Parameters
    ----------
    services : Services
    session_id : str
    trajectory_id : str
        The plan to move to the start of.

    Returns
    -------
    JobRow
        The planning job; its result names the move (``trajectory_id``).

    Raises
    ------
    ApiError
        404 for an unknown plan; 409 ``move_of_a_move`` for a move, ``arm_busy`` while a run
        owns the arm, ``at_start`` when the arm already stands where the plan starts,
        ``unreadable_plan`` for stored parameters that no longer read, ``arm_outside_limits``
        for joints no move may start from.
    CellUnreadable
        The stored cell cannot be read (nothing is planned against it).
    RobotUnavailable
        A real arm is configured but its joints cannot be read now.
    """
    from drivers.robot.base import START_TOLERANCE_RAD
    from recon.plan_params import PlanParams
    from service.errors import ApiError
    from service.schemas import TRAJECTORY_PARAMS

    services.session(session_id)
    target = services.artifact(session_id, "trajectory", trajectory_id)
    if target.inputs.get("move_to_start_of"):
        raise ApiError(
            409,
            "move_of_a_move",
            f"{trajectory_id} is itself a move to a plan's start: ask for the move to the start "
            f"of {target.inputs['move_to_start_of']} instead",
        )
    with services.live.lock:
        owner = services.live.arm_owner()
    if owner is not None:
        raise ApiError(
            409,
            "arm_busy",
            f"the arm is running execution {owner}: a move is planned from where the arm "
            "stands, once it stands still",
        )
    q_now, start_from = start_joints(services.robot, services.settings)
    q_goal = (target.summary or {}).get("start_q_rad")
    if (
        q_goal is not None
        and float(np.abs(q_now - np.asarray(q_goal)).max()) <= START_TOLERANCE_RAD
    ):
        raise ApiError(
            409,
            "at_start",
            f"the arm already stands where {trajectory_id} starts: dry-run and run the plan",
        )
    params = as_core_params({k: target.params[k] for k in TRAJECTORY_PARAMS if k in target.params})
    # The move keeps to this server's TCP speed cap as the plan's transit does.
    params["transit_tcp_speed_m_s"] = min(
        params.get("transit_tcp_speed_m_s", PlanParams.transit_tcp_speed_m_s),
        services.settings.max_speed_m_s,
    )
    try:
        PlanParams(**{**params, "start_q_rad": None})
    except (TypeError, ValueError) as exc:
        raise ApiError(
            409,
            "unreadable_plan",
            f"the parameters of {trajectory_id} cannot be read ({str(exc)[:200]}): plan it again",
        ) from None
    params["start_q_rad"] = tuple(float(v) for v in q_now)
    try:
        PlanParams(**params)
    except (TypeError, ValueError) as exc:
        raise ApiError(
            409,
            "arm_outside_limits",
            f"the arm's joints cannot start a move ({str(exc)[:200]}): jog it back within its "
            "limits on its teach pendant",
        ) from None
    boxes, planes = cell_now(services.store, services.settings).as_lists()
    T = target.params.get("T_base_tracker")
    inputs = {
        "reconstruction_id": target.inputs.get("reconstruction_id"),
        "scan_id": target.inputs.get("scan_id"),
        "move_to_start_of": trajectory_id,
    }
    stored_params = {
        **params,
        "T_base_tracker": T,
        "start_from": start_from,
        "keep_out_boxes": boxes,
        "cell_planes": planes,
    }
    out_id = new_id(ID_PREFIX["trajectory"])
    done = services.record_when_done(
        session_id,
        "trajectory",
        out_id,
        inputs=inputs,
        params=stored_params,
        result=lambda summary: {"trajectory_id": out_id, "move_to_start_of": trajectory_id},
    )
    store = services.store
    recon = store.artifact(str(inputs["reconstruction_id"]), kind="reconstruction")
    scan = store.artifact(str(inputs["scan_id"]), kind="scan") if inputs["scan_id"] else None
    calibration = services.settings.arm_calibration
    task = tasks.MoveToStart(
        target_path=str(store.path_of(target)),
        target_summary=target.summary,
        target_id=trajectory_id,
        reconstruction_path=None if recon is None else str(store.path_of(recon)),
        params=params,
        q_from_rad=[float(v) for v in q_now],
        out_path=services.array_path(out_id),
        scan_path=None if scan is None else str(store.path_of(scan)),
        T_base_tracker=T,
        keep_out_boxes=boxes,
        cell_planes=planes,
        start_from=start_from,
        calibration=None if calibration is None else calibration.as_dict(),
    )
    return services.jobs.submit(
        session_id, "trajectory", {**stored_params, **inputs}, task, done, outputs=(task.out_path,)
    )
