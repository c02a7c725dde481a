"""The speed override and pause of a streamed trajectory (drivers.robot.timescale), against
analytic timing laws, the plan's own samples and the joints' acceleration limits; then in the
simulated arm, driven as the runner drives it."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.robot.clock import FakeClock
from drivers.robot.sim import SimBackend, SimConfig
from drivers.robot.timescale import MAX_PAUSE_S, MAX_RAMP_PER_S, PlanCursor
from tests.motion_fixtures import line_process

PERIOD_S = 0.002
QDD_MAX = np.full(6, 4.0)


def _cosine_plan(duration_s: float = 2.0, amplitude_rad: float = 0.5) -> np.ndarray:
    """q(t) = A (1 - cos(pi t / T)) / 2 on every joint, at rest at both ends (K, 6)."""
    t = np.arange(int(round(duration_s / PERIOD_S)) + 1) * PERIOD_S
    q = amplitude_rad * (1 - np.cos(np.pi * t / duration_s)) / 2
    return np.outer(q, np.linspace(1.0, 0.5, 6))


def _stream(cursor: PlanCursor, target_at) -> np.ndarray:
    """What a stream sends: ``target_at(k)`` is the dial at period k (M, 6)."""
    sent = []
    for k in range(200_000):
        sent.append(cursor.here())
        if cursor.done:
            return np.array(sent)
        cursor.advance(target_at(k))
    raise AssertionError("the stream never reached the plan's end")


def _accelerations(sent: np.ndarray) -> np.ndarray:
    return np.abs(np.diff(sent, n=2, axis=0)) / PERIOD_S**2


def test_at_full_speed_the_stream_is_the_plans_samples_bit_for_bit():
    plan = _cosine_plan()
    sent = _stream(PlanCursor(plan, PERIOD_S, QDD_MAX), lambda k: 1.0)
    assert np.array_equal(sent, plan)


@pytest.mark.parametrize("fraction", [0.5, 0.25, 0.1])
def test_a_constant_fraction_is_the_plan_slowed_by_that_factor(fraction):
    """Analytic: started at s, the k-th target is q(k s dt), the plan's law at a slower clock;
    between samples the straight segment is within the chord error of the cosine."""
    duration_s, amplitude = 2.0, 0.5
    plan = _cosine_plan(duration_s, amplitude)
    sent = _stream(PlanCursor(plan, PERIOD_S, QDD_MAX, start_fraction=fraction), lambda k: fraction)
    t_plan = np.arange(len(sent)) * fraction * PERIOD_S
    expected = np.outer(
        amplitude * (1 - np.cos(np.pi * np.minimum(t_plan, duration_s) / duration_s)) / 2,
        np.linspace(1.0, 0.5, 6),
    )
    # Chord error of a straight segment over one sample: curvature * dt^2 / 8.
    chord = amplitude / 2 * (np.pi / duration_s) ** 2 * PERIOD_S**2 / 8
    assert np.abs(sent - expected).max() <= chord + 1e-12
    assert len(sent) == int(np.ceil((len(plan) - 1) / fraction - 1e-9)) + 1
    assert np.array_equal(sent[-1], plan[-1])


def test_a_pause_comes_to_rest_on_the_path_within_the_acceleration_limits_and_resumes():
    plan = _cosine_plan()
    cursor = PlanCursor(plan, PERIOD_S, QDD_MAX)
    pause_at, resume_at = 300, 1200  # periods: paused in the middle of the motion
    sent = _stream(cursor, lambda k: 0.0 if pause_at <= k < resume_at else 1.0)
    # Every target lies on the planned polyline: the path does not change, only its timing.
    index = np.clip(np.searchsorted(plan[:, 0], sent[:, 0]), 1, len(plan) - 1)
    a, b = plan[index - 1], plan[index]
    part = np.where(b[:, 0] > a[:, 0], (sent[:, 0] - a[:, 0]) / (b[:, 0] - a[:, 0]), 0.0)
    assert np.abs(a + part[:, None] * (b - a) - sent).max() < 1e-12
    # It came to rest, and stood still, before it was resumed.
    still = np.abs(np.diff(sent, axis=0)).max(axis=1) == 0.0
    assert still[resume_at - 10 : resume_at - 1].all()
    # Slowing down and speeding up again stayed within the joints' acceleration limits (the
    # plan itself uses at most A (pi/T)^2 / 2 = 0.62 rad/s^2 of them).
    assert _accelerations(sent).max() <= QDD_MAX.max() * (1 + 1e-6)
    assert np.array_equal(sent[-1], plan[-1])


def test_the_ramp_waits_where_the_plan_uses_all_of_a_joints_acceleration():
    """Where the plan accelerates at the limit at full speed, there is no room to slow down:
    the fraction holds until there is (never a jolt over the limit)."""
    t = np.arange(501) * PERIOD_S
    plan = np.outer(QDD_MAX[0] * t**2 / 2, np.ones(6))  # full acceleration throughout
    cursor = PlanCursor(plan, PERIOD_S, QDD_MAX)
    cursor.position = 100.0
    cursor.advance(0.0)
    assert cursor.fraction > 1.0 - 1e-12  # the rounding of the plan's second differences
    assert cursor.max_ramp() < 1e-9


def test_the_ramp_is_never_quicker_than_the_operators_slider():
    plan = _cosine_plan()
    cursor = PlanCursor(plan, PERIOD_S, np.full(6, 1e6))  # limits that allow anything
    cursor.position = 500.0
    fractions = []
    for _ in range(100):
        cursor.advance(0.2)
        fractions.append(cursor.fraction)
    assert np.diff([1.0, *fractions]).min() >= -MAX_RAMP_PER_S * PERIOD_S - 1e-12
    assert fractions[-1] == pytest.approx(1.0 - 100 * MAX_RAMP_PER_S * PERIOD_S)


@pytest.mark.parametrize("dial", [float("nan"), float("inf"), -0.5, 1.5, 1e300])
def test_a_dial_value_no_one_could_set_counts_as_a_pause(dial):
    cursor = PlanCursor(_cosine_plan(), PERIOD_S, QDD_MAX, start_fraction=dial)
    assert cursor.fraction == 0.0
    cursor.advance(dial)
    assert cursor.fraction == 0.0 and cursor.position == 0.0


@pytest.mark.slow
def test_a_pause_left_for_too_long_is_reported():
    cursor = PlanCursor(_cosine_plan(), PERIOD_S, QDD_MAX, start_fraction=0.0)
    for _ in range(int(MAX_PAUSE_S / PERIOD_S) + 2):
        cursor.advance(0.0)
    assert cursor.paused_too_long
    cursor.advance(0.5)
    assert not cursor.paused_too_long


# -- the simulated arm, driven as the runner drives a real one ------------------------------------


@pytest.fixture
def sim():
    trajectory = line_process("ur5e", 0.1)
    backend = SimBackend(SimConfig(q_start_rad=tuple(trajectory.q_rad[0])), clock=FakeClock())
    backend.connect()
    backend.enable()
    yield backend, trajectory
    backend.close()


def test_the_sim_at_half_speed_takes_twice_as_long_and_records_the_plans_samples(sim):
    backend, trajectory = sim
    backend.set_speed(0.5)
    record = backend.execute(trajectory)
    assert record.completed
    k = len(trajectory)
    assert len(record) == pytest.approx(2 * (k - 1) + 1, abs=2)
    assert np.array_equal(record.planned()[[0, -1]], [0, k - 1])
    assert np.array_equal(record.q_planned_rad, trajectory.q_rad[record.planned()])
    assert np.abs(backend.status().q_rad - trajectory.q_rad[-1]).max() < 1e-3  # settled on it


@pytest.mark.slow
def test_the_sim_pauses_on_the_path_and_resumes_when_told(sim, tmp_path):
    from drivers.robot.journal import read_journal_with_plan

    backend, trajectory = sim
    reports: list[float] = []

    def operator(progress: float) -> None:
        """Pauses at a third of the way, resumes after ten reports standing still."""
        reports.append(progress)
        if progress > 0.33 and not backend.paused and len(reports) < 1000:
            backend.pause()
            reports.append(-1.0)  # marks the pause
        elif backend.paused and reports[-10:].count(progress) == 10:
            backend.resume()

    record = backend.execute(trajectory, on_progress=operator, journal=tmp_path / "j.journal")
    assert record.completed and -1.0 in reports
    held = [p for p in reports if p > 0][reports.index(-1.0) :]
    assert max(held.count(p) for p in set(held)) >= 10  # stood on one plan position
    assert len(record) > len(trajectory)  # the pause took time, the path no more samples
    index = record.planned()
    assert (np.diff(index) >= 0).all() and index[-1] == len(trajectory) - 1
    # The journal pairs each sample with the plan position it was sent to, as the record does.
    t_s, _, _, plan_s = read_journal_with_plan(tmp_path / "j.journal")
    assert len(t_s) == len(record)
    assert np.array_equal(np.rint(plan_s / trajectory.period_s).astype(int), index)


@pytest.mark.parametrize("bad", [0.0, 0.01, 1.01, float("nan"), -1.0, "fast"])
def test_a_speed_outside_five_to_a_hundred_percent_is_refused(sim, bad):
    backend, _ = sim
    with pytest.raises((ValueError, TypeError)):
        backend.set_speed(bad)
    assert backend.speed_fraction == 1.0


def test_the_arm_is_placed_on_the_plan_a_lookahead_of_periods_back_not_of_plan_samples():
    """servoJ follows what was sent a lookahead ago in time: in a paused run that is the same
    plan sample for as long as it stood still (a shift of plan samples would run ahead)."""
    from drivers.robot.dryrun import recorded_plan_index

    trajectory = line_process("ur5e", 0.1)
    lag_s = 2 * trajectory.period_s
    sent = np.array([0, 1, 2, 3, 3, 3, 3, 4, 5])  # paused at sample 3 for four periods
    assert recorded_plan_index(trajectory, sent, lag_s).tolist() == [0, 0, 0, 1, 2, 3, 3, 3, 3]
    # At the plan's own pace it is the plan sample a lookahead back, as before.
    assert recorded_plan_index(trajectory, np.arange(6), lag_s).tolist() == [0, 0, 0, 1, 2, 3]
    assert recorded_plan_index(trajectory, np.arange(1), lag_s).tolist() == [0]
