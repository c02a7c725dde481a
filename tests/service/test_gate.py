"""The real-arm gate on its own: every refusal by name, and dry runs that must not count."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.robot.monitor import ArmState
from recon.kinematics import HOME_Q_RAD
from service import gate
from service.robot import Reading
from service.settings import Settings
from service.store import ArtifactRow

START = HOME_Q_RAD
TRAJECTORY_SUMMARY = {
    "robot": "ur5e",
    "requested_speed_m_s": 0.05,
    "duration_s": 4.0,
    "n_samples": 2000,
    "rate_hz": 500.0,
    "path_length_m": 0.2,
    "tool_axis_from": "scan",
    "ik_branch": 0,
    "min_limit_margin_rad": 1.0,
    "min_wrist_singularity": 0.5,
    "min_elbow_singularity": 0.5,
    "min_shoulder_margin_m": 0.1,
}


def passed_dry_run(**changes) -> dict:
    summary = {
        "backend": "sim",
        "dry_run": True,
        "robot": "ur5e",
        "mode": "servoj",
        "tolerance_m": 5e-4,
        "completed": True,
        "faults": [],
        "n_samples": 2050,
    }
    summary.update(changes)
    return summary


def row(artifact_id: str, summary: dict, trajectory_id: str = "trj_1") -> ArtifactRow:
    return ArtifactRow(
        id=artifact_id, kind="execution", inputs={"trajectory_id": trajectory_id}, summary=summary
    )


@pytest.fixture
def settings(tmp_path):
    return Settings(data_dir=tmp_path, ur_host="127.0.0.9", ur_robot="ur5e", max_speed_m_s=0.1)


@pytest.fixture
def trajectory():
    return ArtifactRow(id="trj_1", kind="trajectory", inputs={}, summary=TRAJECTORY_SUMMARY)


def arm_at(q, **state) -> Reading:
    """A fresh reading of a healthy arm at joints ``q`` (fields of ArmState to change)."""
    fields = {
        "robot_mode": "RUNNING",
        "safety_status": "NORMAL",
        "remote_control": True,
        "q_rad": tuple(q),
        **state,
    }
    return Reading(ArmState(backend="ur_rtde", reachable=True, **fields), time.monotonic(), None)


def check(
    settings,
    trajectory,
    dry_runs,
    *,
    confirm=True,
    mode="servoj",
    tolerance_m=5e-4,
    owner=None,
    arm=None,
):
    return gate.check_real_arm(
        settings,
        trajectory,
        dry_runs,
        confirm=confirm,
        mode=mode,
        tolerance_m=tolerance_m,
        owner=owner,
        arm=arm_at(START) if arm is None else arm,
        q_start_rad=np.array(START),
    )


def test_a_passed_dry_run_in_the_same_mode_lets_the_arm_run(settings, trajectory):
    summary = check(settings, trajectory, [row("exe_1", passed_dry_run())])
    assert summary.robot == "ur5e" and summary.requested_speed_m_s == 0.05


@pytest.mark.parametrize(
    ("dry_run", "why"),
    [
        (passed_dry_run(faults=["protective stop"]), "faulted"),
        (passed_dry_run(completed=False), "incomplete"),
        (passed_dry_run(mode="movepath"), "another mode"),
        (passed_dry_run(backend="ur_rtde", dry_run=False), "a real run, not a dry run"),
        (passed_dry_run(dry_run=False), "not marked as a dry run"),
        ({"completed": True, "faults": []}, "an older record without mode, backend, ..."),
        ({**passed_dry_run(), "completed": "yes"}, "a field of the wrong type"),
        ({}, "an empty summary"),
    ],
)
def test_dry_runs_that_do_not_count(settings, trajectory, dry_run, why):
    with pytest.raises(gate.DryRunRequired):
        check(settings, trajectory, [row("exe_1", dry_run)])


def test_a_dry_run_of_another_trajectory_does_not_count(settings, trajectory):
    with pytest.raises(gate.DryRunRequired):
        check(settings, trajectory, [row("exe_1", passed_dry_run(), trajectory_id="trj_2")])


def test_movepath_needs_a_dry_run_with_the_same_tolerance(settings, trajectory):
    dry = [row("exe_1", passed_dry_run(mode="movepath", tolerance_m=1e-3))]
    with pytest.raises(gate.DryRunRequired, match="tolerance_m"):
        check(settings, trajectory, dry, mode="movepath", tolerance_m=5e-4)
    assert check(settings, trajectory, dry, mode="movepath", tolerance_m=1e-3)


@pytest.mark.parametrize("confirm", [False, None, "yes", 1, "true"])
def test_only_the_boolean_true_confirms(settings, trajectory, confirm):
    with pytest.raises(gate.ConfirmationRequired):
        check(settings, trajectory, [row("exe_1", passed_dry_run())], confirm=confirm)


def test_the_speed_cap(settings, trajectory):
    fast = ArtifactRow(
        id="trj_1",
        kind="trajectory",
        inputs={},
        summary={**TRAJECTORY_SUMMARY, "requested_speed_m_s": 0.2},
    )
    with pytest.raises(gate.SpeedCapExceeded, match="0.1 m/s"):
        check(settings, fast, [row("exe_1", passed_dry_run())])


def test_no_arm_configured(tmp_path, trajectory):
    with pytest.raises(gate.NoRobotConfigured):
        check(Settings(data_dir=tmp_path), trajectory, [row("exe_1", passed_dry_run())])


def test_a_trajectory_for_another_robot(settings):
    other = ArtifactRow(
        id="trj_1", kind="trajectory", inputs={}, summary={**TRAJECTORY_SUMMARY, "robot": "ur10e"}
    )
    with pytest.raises(gate.TrajectoryForAnotherRobot, match="ur10e"):
        check(settings, other, [row("exe_1", passed_dry_run())])


def test_a_trajectory_whose_summary_cannot_be_read_is_refused(settings):
    broken = ArtifactRow(id="trj_1", kind="trajectory", inputs={}, summary={"robot": "ur5e"})
    with pytest.raises(gate.UnreadableTrajectory):
        check(settings, broken, [row("exe_1", passed_dry_run())])


def test_one_arm_owner(settings, trajectory):
    with pytest.raises(gate.ArmBusy, match="exe_7") as refused:
        check(settings, trajectory, [row("exe_1", passed_dry_run())], owner="exe_7")
    assert refused.value.detail == {"execution_id": "exe_7"}


def test_an_arm_away_from_the_start_is_refused_with_the_distance(settings, trajectory):
    moved = np.array(START) + [0.0, 0.0, 0.05, 0.0, 0.0, 0.0]
    with pytest.raises(gate.StartMoved, match="joint 3") as refused:
        check(settings, trajectory, [row("exe_1", passed_dry_run())], arm=arm_at(moved))
    assert refused.value.detail["max_joint_deg"] == pytest.approx(np.degrees(0.05))
    assert refused.value.detail["flange_distance_m"] > 0.01
    # Within the tolerance it runs.
    close = np.array(START) + 0.5 * gate.START_TOLERANCE_RAD
    assert check(settings, trajectory, [row("exe_1", passed_dry_run())], arm=arm_at(close))


@pytest.mark.parametrize(
    ("state", "refusal"),
    [
        ({"protective_stop": True, "safety_status": "PROTECTIVE_STOP"}, gate.ArmInProtectiveStop),
        ({"emergency_stop": True}, gate.ArmInEmergencyStop),
        ({"remote_control": False}, gate.RemoteControlOff),
    ],
)
def test_an_arm_that_cannot_run_now_is_refused(settings, trajectory, state, refusal):
    with pytest.raises(refusal):
        check(settings, trajectory, [row("exe_1", passed_dry_run())], arm=arm_at(START, **state))


def test_an_arm_whose_state_is_not_known_is_refused(settings, trajectory):
    unreachable = Reading(ArmState.unreachable("ur_rtde", "127.0.0.9: no answer"), 0.0, None)
    with pytest.raises(gate.RobotUnavailable, match="127.0.0.9"):
        check(settings, trajectory, [row("exe_1", passed_dry_run())], arm=unreachable)
    stale = Reading(arm_at(START).state, time.monotonic() - 60.0, None)
    with pytest.raises(gate.RobotUnavailable, match="60"):
        check(settings, trajectory, [row("exe_1", passed_dry_run())], arm=stale)


def test_every_refusal_has_its_own_code():
    from service.errors import classify

    refusals = [
        gate.NoRobotConfigured,
        gate.TrajectoryForAnotherRobot,
        gate.ConfirmationRequired,
        gate.SpeedCapExceeded,
        gate.DryRunRequired,
        gate.UnreadableTrajectory,
        gate.ArmBusy,
        gate.RobotUnavailable,
        gate.ArmInProtectiveStop,
        gate.ArmInEmergencyStop,
        gate.RemoteControlOff,
        gate.StartMoved,
    ]
    codes = [classify(cls("x")) for cls in refusals]
    assert all(status == 409 for status, _ in codes)
    assert len({code for _, code in codes}) == len(refusals)
