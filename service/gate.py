"""The real-arm gate: whether a trajectory may move the configured arm, and if not, why.

A real arm moves only when every check passes, in two steps.

:func:`check_here` judges **the samples the runner will send**, in this process, against this
arm and this cell, whatever is stored about them: the configured model's joint ranges, speeds
and accelerations, a start and an end at rest, the server's TCP speed cap on every sample of
every phase (forward kinematics of the samples, with the TCP the controller will be given), and
a collision check of the whole motion against this server's mounting plane, cell planes and
keep-out boxes and the scanned workpiece the trajectory was planned along. A stored summary,
clearance or "passed" is never what decides: a trajectory imported from another site, forged or
written by an older version is judged like one planned a moment ago. What it returns
(:class:`CheckedHere`) holds the very arrays it checked; the runner is given those.

:func:`check_real_arm` then decides the rest under the arm's lock: an arm is configured, the
request says ``"confirm": true``, the same trajectory passed a dry run **made by this data
folder's service** in the same mode (and, for movePath, the same tolerance; a dry run imported
with a bundle has no job here and does not count), no other execution owns the arm, and the
arm's state, read just now, is known, free of stops, in remote control and at the trajectory's
first sample. Stored dry-run summaries are read strictly (no coercion: ``"yes"`` is not
``true``) and fail closed.

Each refusal is its own exception class, mapped to 409 and a stable code in
:mod:`service.errors`, so "why was the arm refused?" has one answer in one place.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence, Set
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from pydantic import ValidationError

from drivers.robot.base import START_TOLERANCE_RAD
from recon import kinematics
from recon.arrays import FloatArray
from recon.collision import Cell
from recon.trajectory import JointTrajectory
from service.artifacts import ExecutionSummary, TrajectorySummary
from service.errors import (
    ApprovalMismatch,
    ArmBusy,
    ArmInEmergencyStop,
    ArmInProtectiveStop,
    ArmNotRunning,
    CollidesHere,
    ConfirmationRequired,
    DryRunRequired,
    NoRobotConfigured,
    OutdatedInputs,
    RemoteControlOff,
    RobotUnavailable,
    SamplesOutsideLimits,
    SpeedCapExceeded,
    StartMoved,
    TrajectoryForAnotherRobot,
    UnreadableTrajectory,
)
from service.settings import Settings
from service.store import ArtifactRow

if TYPE_CHECKING:
    from service.robot import Reading


@dataclass(frozen=True)
class CellHere:
    """This server's cell and the tool, as the gate checks a motion against them (base frame).

    Attributes
    ----------
    cell : recon.collision.Cell
        The mounting plane is always part of it; this server's cell planes and keep-out boxes,
        and the scan the trajectory was planned along.
    T_flange_tcp : ndarray of shape (4, 4)
        The TCP the controller will be given.
    tool_radius_m, clearance_m : float
        The tool's capsule radius and the clearance required, as planned.
    tool_spheres_m : tuple of float
        The tool as spheres (X,Y,Z,R each, flange frame), as planned; empty for the capsule.
    cell_revision : int
        The revision of the cell the boxes and planes came from (0: never edited): the arm is
        taken only if that revision is still the one in force.
    """

    cell: Cell
    T_flange_tcp: FloatArray
    tool_radius_m: float
    clearance_m: float
    tool_spheres_m: tuple[float, ...] = ()
    cell_revision: int = 0


def _arm_here(settings: Settings, loaded: JointTrajectory) -> kinematics.URModel:
    """This server's arm, calibrated as its controller is (``ur_calibration``), after checking
    that the trajectory's joints were solved for that very model: joints solved with another
    one put the flange millimetres from where the plan (and its dry run) said.

    Raises
    ------
    TrajectoryForAnotherRobot
        Planned with another calibration, or with one where this server has none (or the
        other way round).
    """
    arm = kinematics.model(settings.ur_robot)
    here = settings.arm_calibration
    if here is None and loaded.calibration is None:
        return arm
    this_arm = arm if here is None else kinematics.with_calibration(arm, here)
    if here is not None and here.same_as(loaded.calibration):
        return this_arm
    try:
        planned_arm = loaded.arm
    except ValueError as exc:  # a calibration of another arm type (an imported file)
        raise TrajectoryForAnotherRobot(
            f"the trajectory's joints were solved with a calibration that is not this "
            f"{settings.ur_robot}'s ({exc}): plan it again here"
        ) from None
    flange_here = kinematics.forward(this_arm, loaded.q_rad)[:, :3, 3]
    flange_planned = kinematics.forward(planned_arm, loaded.q_rad)[:, :3, 3]
    moved_mm = float(np.linalg.norm(flange_here - flange_planned, axis=1).max()) * 1e3
    planned = (
        "UR's nominal kinematics"
        if loaded.calibration is None
        else f"the calibration {loaded.calibration.source or '(unnamed)'}"
    )
    this = (
        "its nominal kinematics (no ur_calibration)"
        if here is None
        else f"the calibration {here.source or '(unnamed)'}"
    )
    raise TrajectoryForAnotherRobot(
        f"the trajectory's joints were solved with {planned}; this server models the arm with "
        f"{this}, which puts the flange up to {moved_mm:.1f} mm from where the plan said: plan "
        "it again here",
        detail={"flange_difference_m": moved_mm / 1e3},
    )


@dataclass(frozen=True)
class CheckedHere:
    """A trajectory whose samples passed every check of :func:`check_here`: the runner is
    given ``trajectory``, the very arrays that were checked.

    Attributes
    ----------
    trajectory_id : str
    trajectory : recon.trajectory.JointTrajectory
    summary : TrajectorySummary
    min_clearance_m : float
        The smallest clearance of the arm and tool to the cell found here.
    fastest_tcp_m_s : float
        The largest TCP speed of any sample.
    """

    trajectory_id: str
    trajectory: JointTrajectory
    summary: TrajectorySummary
    min_clearance_m: float
    fastest_tcp_m_s: float


def _require_arm(settings: Settings) -> None:
    if settings.ur_host is None:
        raise NoRobotConfigured(
            "no real arm is configured (TEACHPATH_UR_HOST); use backend 'sim' for a dry run"
        )


def check_request(settings: Settings, *, confirm: bool) -> None:
    """The cheap checks first: a real arm is configured and the request confirms the motion.

    Raises
    ------
    NoRobotConfigured, ConfirmationRequired
    """
    _require_arm(settings)
    if confirm is not True:
        raise ConfirmationRequired('moving a real arm needs "confirm": true in the request')


def check_here(
    settings: Settings, trajectory: ArtifactRow, loaded: JointTrajectory, here: CellHere
) -> CheckedHere:
    """Check the samples that would be sent against this arm and this cell, in this process.

    Parameters
    ----------
    settings : Settings
        The configured arm (``ur_robot``) and the TCP speed cap (``max_speed_m_s``).
    trajectory : ArtifactRow
        The stored trajectory (its summary is read only to name what it was planned for).
    loaded : JointTrajectory
        Its arrays, as the runner will send them.
    here : CellHere

    Returns
    -------
    CheckedHere

    Raises
    ------
    UnreadableTrajectory, TrajectoryForAnotherRobot, SpeedCapExceeded, SamplesOutsideLimits,
    CollidesHere
    """
    from recon.plan import check_cell
    from recon.plan_params import PlanParams
    from recon.sample_check import sample_problems, tcp_speeds_m_s

    _require_arm(settings)
    summary = trajectory_summary(trajectory)
    if summary.robot != settings.ur_robot or loaded.robot != settings.ur_robot:
        raise TrajectoryForAnotherRobot(
            f"the trajectory was planned for a {summary.robot}; the configured arm is a "
            f"{settings.ur_robot}: plan it again for this arm"
        )
    speed = summary.requested_speed_m_s
    if not (math.isfinite(speed) and speed <= settings.max_speed_m_s):
        raise SpeedCapExceeded(
            f"the trajectory runs at {speed} m/s; this server allows at most "
            f"{settings.max_speed_m_s} m/s on a real arm"
        )
    arm_model = _arm_here(settings, loaded)
    problems = sample_problems(
        arm_model,
        loaded.t_s,
        loaded.q_rad,
        tcp_speed_max_m_s=settings.max_speed_m_s,
        T_flange_tcp=here.T_flange_tcp,
    )
    if problems:
        first = problems[0]
        raise SamplesOutsideLimits(
            f"the samples to be sent break {len(problems)} limit(s) of this arm or server; "
            f"first: {first.message}"
            + ("" if first.sample < 0 else f" (sample {first.sample}, t={first.t_s:.3f} s)")
            + ". Plan it again here (for a TCP speed cap: transit_tcp_speed_m_s and speed_m_s "
            f"at most {settings.max_speed_m_s} m/s)",
            detail={"checks": [p.check for p in problems], "sample": first.sample},
        )
    params = PlanParams(
        robot=settings.ur_robot,
        tool_radius_m=here.tool_radius_m,
        tool_spheres_m=here.tool_spheres_m,
        clearance_m=here.clearance_m,
        tcp_pose=_pose_of(here.T_flange_tcp),
    )
    # The contact zone comes from the samples' own kinematics (ContactZone.of_process).
    report = check_cell(arm_model, loaded, here.cell, params)
    if report.first_collision is not None:
        collision = report.first_collision
        raise CollidesHere(
            f"checked here against this cell, the motion collides: {collision.describe()}. Plan it "
            "again here (a plan made elsewhere does not know this cell's keep-out boxes)",
            detail={
                "sample": collision.sample,
                "link": collision.link,
                "obstacle": collision.obstacle,
                "clearance_m": float(collision.clearance_m),
                "margin_m": float(collision.margin_m),
            },
        )
    return CheckedHere(
        trajectory_id=trajectory.id,
        trajectory=loaded,
        summary=summary,
        min_clearance_m=float(np.min(report.clearance_m)),
        fastest_tcp_m_s=float(
            np.max(tcp_speeds_m_s(arm_model, loaded.q_rad, T_flange_tcp=here.T_flange_tcp))
        ),
    )


def _pose_of(T: FloatArray) -> tuple[float, float, float, float, float, float]:
    """x, y, z (m), rx, ry, rz (rotation vector) of a 4x4 transform."""
    from recon.transforms import pose_from_transform

    x, y, z, rx, ry, rz = (float(v) for v in pose_from_transform(np.asarray(T, dtype=np.float64)))
    return x, y, z, rx, ry, rz


def trajectory_summary(trajectory: ArtifactRow) -> TrajectorySummary:
    """The trajectory's typed summary, or a refusal if it cannot be read."""
    try:
        return TrajectorySummary.model_validate(trajectory.summary, strict=True)
    except ValidationError as exc:
        raise UnreadableTrajectory(
            f"the summary of trajectory {trajectory.id} cannot be read "
            f"({exc.error_count()} problem(s)); plan it again"
        ) from None


def passed_dry_run(
    dry_runs: Iterable[ArtifactRow],
    trajectory_id: str,
    *,
    mode: str,
    tolerance_m: float,
    made_here: Set[str],
) -> bool:
    """Whether one of ``dry_runs`` is a completed, fault-free dry run of this trajectory, run the
    way it is to run now, by this data folder's service.

    ``made_here``: the ids of the executions a job of this service produced (a bundle carries
    no jobs, so a dry run imported from elsewhere, genuine or not, is never among them).
    """
    for row in dry_runs:
        if row.inputs.get("trajectory_id") != trajectory_id or row.id not in made_here:
            continue
        try:
            summary = ExecutionSummary.model_validate(row.summary, strict=True)
        except ValidationError:
            continue  # an unreadable record proves nothing
        if not (summary.dry_run and summary.backend == "sim"):
            continue
        if not summary.completed or summary.faults or summary.mode != mode:
            continue
        if mode == "movepath" and not math.isclose(summary.tolerance_m, tolerance_m):
            continue
        return True
    return False


def check_approved(approved_sha256: str | None, stored_sha256: str, trajectory_id: str) -> None:
    """Refuse when the operator approved another file than the one stored under this id.

    Raises
    ------
    ApprovalMismatch
    """
    if approved_sha256 is not None and approved_sha256 != stored_sha256:
        raise ApprovalMismatch(
            f"trajectory {trajectory_id} is not the file that was approved (sha256 "
            f"{approved_sha256[:12]}… approved, {stored_sha256[:12]}… stored): reload the page, "
            "check the plan again and confirm what it shows",
            detail={"approved_sha256": approved_sha256, "stored_sha256": stored_sha256},
        )


def check_current(outdated: Sequence[str], *, accept_outdated: bool) -> None:
    """Refuse a plan made from inputs that are no longer the session's, unless picked.

    Raises
    ------
    OutdatedInputs
        ``outdated`` is not empty and ``accept_outdated`` is false.
    """
    if outdated and not accept_outdated:
        raise OutdatedInputs(
            "this plan was made from inputs that are no longer the session's: "
            + "; ".join(outdated)
            + ". Reconstruct and plan again from the current ones, or, to run this older plan, "
            "pick it explicitly (accept_outdated: true) after checking its inputs",
            detail={"changed": list(outdated)},
        )


def check_real_arm(
    settings: Settings,
    checked: CheckedHere,
    dry_runs: Iterable[ArtifactRow],
    *,
    dry_runs_made_here: Set[str],
    confirm: bool,
    mode: str,
    tolerance_m: float,
    owner: str | None,
    arm: Reading,
    outdated: Sequence[str] = (),
    accept_outdated: bool = False,
) -> None:
    """Refuse, naming why, unless the configured arm may run the checked trajectory now.

    Parameters
    ----------
    checked : CheckedHere
        The trajectory as :func:`check_here` passed it (the samples were judged in this
        process against this arm and cell).
    dry_runs : iterable of ArtifactRow
        The session's executions.
    dry_runs_made_here : set of str
        Ids of executions that jobs of this service produced (see :func:`passed_dry_run`).
    owner : str or None
        The execution that owns the arm now, if any.
    arm : Reading
        The arm's latest reading (:class:`service.robot.Reading`).
    outdated : list of str
        What changed in the session since the plan (:mod:`service.provenance`).
    accept_outdated : bool
        The request picked this plan explicitly, outdated as it is.

    Raises
    ------
    RealArmRefused
        A subclass per reason.
    """
    check_request(settings, confirm=confirm)
    check_current(outdated, accept_outdated=accept_outdated)
    if not passed_dry_run(
        dry_runs,
        checked.trajectory_id,
        mode=mode,
        tolerance_m=tolerance_m,
        made_here=dry_runs_made_here,
    ):
        raise DryRunRequired(
            f"this trajectory has not passed a dry run here in mode {mode!r}"
            + (" with the same tolerance_m" if mode == "movepath" else "")
            + ": execute it with backend 'sim' first (a dry run imported with a bundle does "
            "not count: run it again here)"
        )
    if owner is not None:
        raise ArmBusy(
            f"execution {owner} is running on the arm: wait for it to end or stop it first",
            detail={"execution_id": owner},
        )
    check_arm_state(arm, checked.trajectory.q_rad[0], robot=settings.ur_robot)


def check_arm_state(arm: Reading, q_start_rad: FloatArray, *, robot: str) -> None:
    """Refuse unless the arm's state is known, fault-free, remote-controlled and at the start.

    Raises
    ------
    RobotUnavailable, ArmInEmergencyStop, ArmInProtectiveStop, ArmNotRunning, RemoteControlOff,
    StartMoved
    """
    state = arm.state
    if not arm.fresh or state.q_rad is None:
        raise RobotUnavailable(
            f"the arm's state is not known ({state.error or f'last read {arm.age_s:.1f} s ago'}): "
            "check its network link; nothing moves on a state that is not known"
        )
    if state.emergency_stop:
        raise ArmInEmergencyStop("the emergency stop is engaged: release it on the arm first")
    if state.protective_stop:
        raise ArmInProtectiveStop(
            "the arm is in a protective stop: inspect its cause, then unlock it (POST "
            "/robot/unlock) before running"
        )
    if state.robot_mode != "RUNNING":
        # Powered off after an emergency stop, brakes still on, booting: no motion can be sent,
        # and a mode not read (UNKNOWN) decides nothing.
        raise ArmNotRunning(
            f"the arm is not running (robot mode {state.robot_mode}): power it on and release "
            "its brakes on the teach pendant first"
        )
    if state.remote_control is False:
        raise RemoteControlOff(
            "the arm is in local control: switch the teach pendant to remote control first"
        )
    gap = np.abs(np.asarray(state.q_rad) - np.asarray(q_start_rad))
    if float(gap.max()) > START_TOLERANCE_RAD:
        arm_model = kinematics.model(robot)
        here, there = kinematics.forward(arm_model, np.array([state.q_rad, q_start_rad]))
        distance_mm = float(np.linalg.norm(here[:3, 3] - there[:3, 3])) * 1e3
        joint = int(np.argmax(gap))
        raise StartMoved(
            f"the arm is not where this plan starts: joint {joint + 1} is "
            f"{np.degrees(gap[joint]):.1f} deg away and the flange {distance_mm:.0f} mm: move "
            "it to the plan's start (a move of its own, planned, dry-run and approved: POST "
            ".../trajectories/{id}/move-to-start), or plan again from where the arm is",
            detail={
                "max_joint_deg": float(np.degrees(gap.max())),
                "flange_distance_m": distance_mm / 1e3,
                "q_arm_rad": list(state.q_rad),
                "q_start_rad": [float(v) for v in q_start_rad],
            },
        )
