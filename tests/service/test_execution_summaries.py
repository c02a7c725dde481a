"""An execution's figures agree with each other wherever the pendant shows them: the job's
verdict and the record's, the phase a stopped run stopped in and the phases it got through,
its duration and the phases' seconds, the table's deviation and the review's.

The runs go through the real-arm runner (:class:`service.arm_runner.ExecutionRunner`) on the
simulated arm with a fake clock, stopped where a test says.
"""

from __future__ import annotations

import pytest

from drivers.robot.base import backend_config, create_backend
from drivers.robot.clock import FakeClock
from service import pipelines
from service.arm_runner import ExecutionRunner
from service.artifacts import ExecutionCodec
from service.executions import _real_summary
from service.preview import execution_review
from service.schemas import ExecutionCreate
from tests.motion_fixtures import line_plan


class JobRows:
    """The store's job updates, kept (the runner's only use of the store here)."""

    def __init__(self) -> None:
        self.fields: dict = {}

    def update_job(self, job_id, **fields) -> None:
        self.fields.update(fields)


def _run(tmp_path, *, stop_at: float | None = None, stop_after_end: bool = False):
    """Run the line plan through the runner; returns (job fields, summary, record)."""
    trajectory = line_plan().trajectory
    config = backend_config("sim", robot=trajectory.robot, q_start_rad=tuple(trajectory.q_rad[0]))
    backend = create_backend(config, clock=FakeClock())
    request = ExecutionCreate(trajectory_id="trj_x", backend="sim", mode="servoj")
    kept: dict = {}

    def record(execution_record, faults, stopped_in):
        summary = _real_summary(trajectory, execution_record, faults, stopped_in, request, config)
        kept.update(summary=summary, record=execution_record)
        return {"completed": summary["completed"], "stopped_in": stopped_in}

    class Runner(ExecutionRunner):
        def _progress(self, fraction):
            super()._progress(fraction)
            if stop_at is not None and fraction >= stop_at and not self.stop_requested:
                self.stop()

    if stop_after_end:
        execute = backend.execute

        def execute_then_stop(*args, **kwargs):
            done = execute(*args, **kwargs)
            runner.stop()  # the Stop lands as the last sample has gone
            return done

        backend.execute = execute_then_stop
    jobs = JobRows()
    runner = Runner(
        jobs,
        "job_x",
        backend,
        trajectory,
        record,
        tool=([0.0] * 6, None, [0.0, 0.0, 0.0]),
        journal=str(tmp_path / "journal"),
    )
    runner.start()
    runner.thread.join(timeout=120)
    return jobs.fields, kept["summary"], kept["record"], trajectory


@pytest.mark.parametrize("stop_at", [0.3, 0.55, 0.8])
def test_a_stopped_run_reports_one_place_it_stopped_and_the_time_it_ran(tmp_path, stop_at):
    job, summary, _record, trajectory = _run(tmp_path, stop_at=stop_at)
    assert job["state"] == "cancelled" and not summary["completed"]
    planned = summary["phase_durations_s"]
    executed = summary["executed_phase_durations_s"]
    # The phases it got through run in the plan's order, the last one the one it stopped in;
    # none shows more seconds than planned, all before the last are whole.
    names = list(executed)
    assert names == list(planned)[: len(names)]
    assert names[-1] == summary["stopped_in"] == job["result"]["stopped_in"]
    for name in names[:-1]:
        assert executed[name] == pytest.approx(planned[name])
    assert executed[names[-1]] <= planned[names[-1]] + 1e-9
    # Its duration is the motion's until the stop: the seconds of the phases the arm got
    # through, and the lookahead it was behind the stream when the stop came.
    lookahead_s = 0.1
    assert summary["duration_s"] == pytest.approx(
        sum(executed.values()) + lookahead_s, abs=2 * trajectory.period_s
    )
    assert summary["duration_s"] < summary["planned_duration_s"]
    report = "\n".join(summary["report"])
    assert f"{names[-1]} {executed[names[-1]]:.2f} of" in report


def test_a_completed_run_shows_its_plans_phases_and_the_same_deviation_as_its_review(tmp_path):
    job, summary, record, trajectory = _run(tmp_path)
    assert job["state"] == "succeeded" and summary["completed"] and summary["stopped_in"] is None
    assert summary["executed_phase_durations_s"] == pytest.approx(summary["phase_durations_s"])
    # The motion lasts the plan, not the connecting and settling around it (before: 0.5 s
    # more).
    assert summary["duration_s"] == pytest.approx(
        summary["planned_duration_s"], abs=2 * trajectory.period_s
    )
    review = execution_review(trajectory, ExecutionCodec.decode(ExecutionCodec.encode(record)))
    by_phase = summary["max_deviation_by_phase_m"]
    assert review["max_off_path_m"] == pytest.approx(max(by_phase.values()), rel=1e-12)
    assert summary["max_path_deviation_m"] == by_phase["process"]


def test_a_stop_that_lands_as_the_motion_ends_leaves_one_verdict(tmp_path):
    job, summary, _, _ = _run(tmp_path, stop_after_end=True)
    assert job["state"] == "succeeded"
    assert summary["completed"] and summary["stopped_in"] is None and summary["faults"] == []


@pytest.mark.parametrize("mode", ["servoj", "movepath"])
def test_a_dry_run_measures_its_duration_and_phases_as_a_real_run_does(mode):
    trajectory = line_plan().trajectory
    summary = pipelines.dry_run(trajectory, mode=mode, tolerance_m=5e-4).summary()
    assert summary["completed"]
    assert summary["executed_phase_durations_s"] == pytest.approx(summary["phase_durations_s"])
    # No connecting or settling: within a second of the plan (movePath's controller times its
    # own blends).
    assert abs(summary["duration_s"] - summary["planned_duration_s"]) < 1.0


def test_a_stop_while_the_arm_settles_on_the_last_sample_is_a_stop(tmp_path):
    """The last sample sent is not the arm arrived: it follows a lookahead behind and settles.
    A Stop then brakes it short of the end (12 mrad measured), so the run did not complete."""
    job, summary, _record, _ = _run(tmp_path, stop_at=1.0)
    assert job["state"] == "cancelled"
    assert not summary["completed"] and summary["faults"] == ["stopped on request"]
    assert summary["stopped_in"] == job["result"]["stopped_in"] == "retract"
