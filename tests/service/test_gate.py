"""The real-arm gate on its own: every refusal by name, and dry runs that must not count."""

from __future__ import annotations

import pytest

from service import gate
from service.settings import Settings
from service.store import ArtifactRow

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


def check(settings, trajectory, dry_runs, *, confirm=True, mode="servoj", tolerance_m=5e-4):
    return gate.check_real_arm(
        settings, trajectory, dry_runs, confirm=confirm, mode=mode, tolerance_m=tolerance_m
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


def test_every_refusal_has_its_own_code():
    from service.errors import classify

    refusals = [
        gate.NoRobotConfigured,
        gate.TrajectoryForAnotherRobot,
        gate.ConfirmationRequired,
        gate.SpeedCapExceeded,
        gate.DryRunRequired,
        gate.UnreadableTrajectory,
    ]
    codes = [classify(cls("x")) for cls in refusals]
    assert all(status == 409 for status, _ in codes)
    assert len({code for _, code in codes}) == len(refusals)
