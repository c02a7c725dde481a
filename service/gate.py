"""The real-arm gate: whether a trajectory may move the configured arm, and if not, why.

A real arm moves only when every check passes: an arm is configured, the trajectory was planned
for that model, the request says ``"confirm": true``, its speed is within the server's cap, the
same trajectory passed a dry run in the same mode (and, for movePath, the same tolerance), no
other execution owns the arm, and the arm's state, read just now, is known, free of stops, in
remote control and at the trajectory's first sample.
The gate reads typed summaries, strictly (no coercion: ``"yes"`` is not ``true``), and fails
closed: a stored dry run whose summary is not a complete
:class:`~service.artifacts.ExecutionSummary` (an older or damaged record, a missing field) does
not count as passed, and a trajectory whose summary cannot be read is refused.

Each refusal is its own exception class, mapped to 409 and a stable code in
:mod:`service.errors`, so "why was the arm refused?" has one answer in one place.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np
from pydantic import ValidationError

from drivers.robot.base import START_TOLERANCE_RAD
from recon import kinematics
from recon.types import FloatArray
from service.artifacts import ExecutionSummary, TrajectorySummary
from service.settings import Settings
from service.store import ArtifactRow

if TYPE_CHECKING:
    from service.robot import Reading


class RealArmRefused(Exception):
    """The configured arm may not run this trajectory now (the message says what to do).

    ``detail`` carries what the operator's page shows beside the message (distances, ids).
    """

    def __init__(self, message: str, *, detail: dict | None = None) -> None:
        super().__init__(message)
        self.detail = detail


class NoRobotConfigured(RealArmRefused):
    """No real arm is configured on this server."""


class TrajectoryForAnotherRobot(RealArmRefused):
    """The trajectory was planned for another UR model than the configured arm."""


class ConfirmationRequired(RealArmRefused):
    """The request did not say ``"confirm": true``."""


class SpeedCapExceeded(RealArmRefused):
    """The trajectory's speed is above the server's cap for a real arm."""


class DryRunRequired(RealArmRefused):
    """No passed dry run of this trajectory in this mode (and tolerance) is on record."""


class UnreadableTrajectory(RealArmRefused):
    """The trajectory's summary cannot be read: what it was planned for is unknown."""


class ArmBusy(RealArmRefused):
    """Another execution owns the arm (one real-arm execution at a time)."""


class RobotUnavailable(RealArmRefused):
    """The arm's state cannot be read now: nothing is decided on a state that is not known."""


class ArmInProtectiveStop(RealArmRefused):
    """The arm is in a protective stop: inspect its cause and unlock it first."""


class ArmInEmergencyStop(RealArmRefused):
    """An emergency stop is engaged."""


class RemoteControlOff(RealArmRefused):
    """The arm is in local control: the pendant must hand it over (remote control) first."""


class StartMoved(RealArmRefused):
    """The arm is not where the trajectory starts (it was moved since the plan)."""


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
    dry_runs: Iterable[ArtifactRow], trajectory_id: str, *, mode: str, tolerance_m: float
) -> bool:
    """Whether one of ``dry_runs`` is a completed, fault-free dry run of this trajectory, run the
    way it is to run now."""
    for row in dry_runs:
        if row.inputs.get("trajectory_id") != trajectory_id:
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


def check_real_arm(
    settings: Settings,
    trajectory: ArtifactRow,
    dry_runs: Iterable[ArtifactRow],
    *,
    confirm: bool,
    mode: str,
    tolerance_m: float,
    owner: str | None,
    arm: Reading,
    q_start_rad: FloatArray,
) -> TrajectorySummary:
    """Refuse, naming why, unless the configured arm may run ``trajectory`` now.

    Parameters
    ----------
    owner : str or None
        The execution that owns the arm now, if any.
    arm : Reading
        The arm's latest reading (:class:`service.robot.Reading`).
    q_start_rad : ndarray of shape (6,)
        Where the trajectory starts.

    Returns
    -------
    TrajectorySummary
        The trajectory's summary, read once for the runner.

    Raises
    ------
    RealArmRefused
        A subclass per reason.
    """
    if settings.ur_host is None:
        raise NoRobotConfigured(
            "no real arm is configured (TEACHPATH_UR_HOST); use backend 'sim' for a dry run"
        )
    summary = trajectory_summary(trajectory)
    if summary.robot != settings.ur_robot:
        raise TrajectoryForAnotherRobot(
            f"the trajectory was planned for a {summary.robot}; the configured arm is a "
            f"{settings.ur_robot}"
        )
    if confirm is not True:
        raise ConfirmationRequired('moving a real arm needs "confirm": true in the request')
    speed = summary.requested_speed_m_s
    if not (math.isfinite(speed) and speed <= settings.max_speed_m_s):
        raise SpeedCapExceeded(
            f"the trajectory runs at {speed} m/s; this server allows at most "
            f"{settings.max_speed_m_s} m/s on a real arm"
        )
    if not passed_dry_run(dry_runs, trajectory.id, mode=mode, tolerance_m=tolerance_m):
        raise DryRunRequired(
            f"this trajectory has not passed a dry run in mode {mode!r}"
            + (" with the same tolerance_m" if mode == "movepath" else "")
            + ": execute it with backend 'sim' first"
        )
    if owner is not None:
        raise ArmBusy(
            f"execution {owner} is running on the arm: wait for it to end or stop it first",
            detail={"execution_id": owner},
        )
    check_arm_state(arm, q_start_rad, robot=settings.ur_robot)
    return summary


def check_arm_state(arm: Reading, q_start_rad: FloatArray, *, robot: str) -> None:
    """Refuse unless the arm's state is known, fault-free, remote-controlled and at the start.

    Raises
    ------
    RobotUnavailable, ArmInEmergencyStop, ArmInProtectiveStop, RemoteControlOff, StartMoved
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
            f"{np.degrees(gap[joint]):.1f} deg away and the flange {distance_mm:.0f} mm: plan "
            "again from where the arm is",
            detail={
                "max_joint_deg": float(np.degrees(gap.max())),
                "flange_distance_m": distance_mm / 1e3,
                "q_arm_rad": list(state.q_rad),
                "q_start_rad": [float(v) for v in q_start_rad],
            },
        )
