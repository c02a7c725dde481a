"""The real-arm gate: whether a trajectory may move the configured arm, and if not, why.

A real arm moves only when every check passes: an arm is configured, the trajectory was planned
for that model, the request says ``"confirm": true``, its speed is within the server's cap, and
the same trajectory passed a dry run in the same mode (and, for movePath, the same tolerance).
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

from pydantic import ValidationError

from service.artifacts import ExecutionSummary, TrajectorySummary
from service.settings import Settings
from service.store import ArtifactRow


class RealArmRefused(Exception):
    """The configured arm may not run this trajectory now (the message says what to do)."""


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
) -> TrajectorySummary:
    """Refuse, naming why, unless the configured arm may run ``trajectory``.

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
    return summary
