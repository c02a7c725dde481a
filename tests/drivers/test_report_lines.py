"""An execution report's lines say only what was measured: a run stopped before the path gives
no path speed or path tracking, and says its deviation elsewhere."""

from __future__ import annotations

from drivers.robot.dryrun import ExecutionReport

PLANNED = {"transit": 19.87, "approach": 1.05, "process": 15.29, "retract": 1.04}


def _report(**fields) -> ExecutionReport:
    base = {
        "robot": "ur5e",
        "completed": False,
        "mode": "servoj",
        "duration_s": 9.74,
        "planned_duration_s": 37.25,
        "max_path_deviation_m": None,
        "max_lag_m": None,
        "max_joint_error_rad": 0.001,
        "min_limit_margin_rad": 0.8,
        "min_wrist_singularity": 0.7,
        "min_elbow_singularity": 0.7,
        "requested_speed_m_s": 0.02,
        "mean_speed_m_s": 0.0193,
        "dry_run": False,
        "phase_durations_s": PLANNED,
    }
    return ExecutionReport(**{**base, **fields})


def test_a_run_stopped_in_the_transit_reports_no_path_figures():
    lines = _report(
        executed_phase_durations_s={"transit": 9.37},
        max_deviation_by_phase_m={"transit": 0.000527},
    ).lines()
    assert lines[1] == "duration 9.74 s (planned 37.25 s); the path was not reached"
    assert lines[2] == (
        "tracking along the path: not measured (the arm was not on it); elsewhere 0.527 mm off "
        "at most (transit)"
    )
    assert not any("mean TCP speed" in line for line in lines)


def test_a_run_that_reached_the_path_reports_its_speed_and_tracking():
    lines = _report(
        completed=True,
        max_path_deviation_m=0.00006,
        max_lag_m=0.005,
        executed_phase_durations_s=PLANNED,
        max_deviation_by_phase_m={"transit": 0.00001, "process": 0.00006},
    ).lines()
    assert "mean TCP speed along the path 19.3 mm/s of 20.0 requested" in lines[1]
    assert lines[2].startswith("tracking: 0.060 mm off the path at most, 5.00 mm")


def test_a_move_to_start_has_no_path():
    lines = _report(
        completed=True,
        phase_durations_s={"transit": 12.9},
        executed_phase_durations_s={"transit": 12.9},
        max_deviation_by_phase_m={"transit": 0.0004},
    ).lines()
    assert lines[1].endswith("no path: a joint move")
    assert lines[2] == "tracking: 0.400 mm off the planned way at most (transit)"


def test_nothing_recorded_says_so():
    lines = _report(executed_phase_durations_s={}, max_deviation_by_phase_m={}).lines()
    assert "tracking: not measured (nothing was recorded)" in lines
