"""The simulated arm's own promises: physics, fault injection, a fake clock."""

import numpy as np
import pytest

from drivers.errors import (
    ConnectionLostError,
    EmergencyStopError,
    NotConnectedError,
    ProtectiveStopError,
    RobotTimeoutError,
)
from drivers.robot.base import RobotState
from drivers.robot.clock import FakeClock
from drivers.robot.dryrun import dry_run
from drivers.robot.sim import SimBackend, SimConfig
from tests.motion_fixtures import line_plan, line_process


@pytest.fixture
def ready():
    trajectory = line_process("ur5e", 0.1)
    sim = SimBackend(SimConfig(q_start_rad=tuple(trajectory.q_rad[0])), clock=FakeClock())
    sim.connect()
    sim.enable()
    yield sim, trajectory
    sim.close()


def test_the_state_is_integrated_not_copied(ready):
    sim, trajectory = ready
    target = trajectory.q_rad[0] + 0.2
    sim._advance(sim.clock.now() + sim._dt, target=target)  # one period of servoing
    q = sim.status().q_rad
    assert not np.allclose(q, target)
    assert np.all(np.abs(q - trajectory.q_rad[0]) < 0.2)


def test_joint_speed_limits_hold_in_simulation(ready):
    sim, _ = ready
    sim.move_joints(
        np.array(sim.status().q_rad) + [2.0, 0, 0, 0, 0, 0],
        speed_rad_s=3.0,
        acceleration_rad_s2=10.0,
    )
    assert np.abs(sim._qd).max() <= sim.arm.qd_max_rad_s.max() + 1e-9


def test_protective_stop_during_execution(ready):
    sim, trajectory = ready
    sim.inject(ProtectiveStopError, after_s=0.5)
    with pytest.raises(ProtectiveStopError):
        sim.execute(trajectory)
    assert sim.state is RobotState.PROTECTIVE_STOP
    assert 0 < len(sim.last_record) < len(trajectory)
    with pytest.raises(ProtectiveStopError):
        sim.move_joints(trajectory.q_rad[0])
    sim.unlock_protective_stop()
    assert sim.state is RobotState.ENABLED
    sim.move_joints(trajectory.q_rad[0])


def test_emergency_stop(ready):
    sim, trajectory = ready
    sim.inject(EmergencyStopError, after_s=0.2)
    with pytest.raises(EmergencyStopError):
        sim.execute(trajectory)
    assert sim.state is RobotState.EMERGENCY_STOP
    with pytest.raises(EmergencyStopError):
        sim.enable()


@pytest.mark.parametrize("fault", [ConnectionLostError, RobotTimeoutError])
def test_a_lost_link_fails_every_call_until_reconnected(ready, fault):
    sim, trajectory = ready
    sim.inject(fault, after_s=0.3)
    with pytest.raises(fault):
        sim.execute(trajectory)
    sim.close()  # still safe
    with pytest.raises(NotConnectedError):
        sim.status()
    sim.connect()
    assert sim.status().q_rad.shape == (6,)


def test_injecting_an_unsupported_fault_is_refused(ready):
    sim, _ = ready
    with pytest.raises(ValueError, match="cannot inject"):
        sim.inject(ValueError, after_s=0.1)


def test_running_into_a_joint_limit_is_a_protective_stop():
    sim = SimBackend(
        SimConfig(q_start_rad=(6.2, -1.57, 1.57, -1.57, -1.57, 0.0)), clock=FakeClock()
    )
    sim.connect()
    sim.enable()
    with pytest.raises(ProtectiveStopError, match="position limit"):
        sim._advance(sim.clock.now() + 1.0, target=np.array([7.0, -1.57, 1.57, -1.57, -1.57, 0]))


def test_dry_run_report():
    trajectory = line_plan("ur5e", 0.1).trajectory
    report = dry_run(trajectory)
    assert report.completed and not report.faults
    assert report.max_path_deviation_m < 1e-4  # on the path, a lookahead behind
    # The whole motion was run and measured phase by phase (servoJ's lookahead rounds the
    # stops between phases a little).
    assert set(report.max_deviation_by_phase_m) == {"transit", "approach", "process", "retract"}
    assert max(report.max_deviation_by_phase_m.values()) < 5e-4
    assert report.max_lag_m < 0.1 * 0.2  # speed x (lookahead + settling)
    assert report.duration_s >= report.planned_duration_s
    assert report.min_limit_margin_rad > 0
    assert any("completed" in line for line in report.lines())


def test_dry_run_reports_an_injected_fault():
    trajectory = line_process("ur5e", 0.1)
    sim = SimBackend(SimConfig(q_start_rad=tuple(trajectory.q_rad[0])), clock=FakeClock())
    sim.inject(ProtectiveStopError, after_s=0.3)
    report = dry_run(trajectory, backend=sim)
    assert not report.completed
    assert report.faults and "protective stop" in report.faults[0]
