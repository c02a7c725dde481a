"""servoJ streaming through the ur_rtde adapter against the fake UR controller (``make bench``).

The adapter's worker process paces servoJ with ur_rtde's initPeriod/waitPeriod; the record's
sample times are taken in that loop, so their differences are the streaming period the
controller sees (a real controller would see the same client, plus the network). Printed, never
asserted: the machines are shared and noisy.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from drivers.robot.ur_rtde import URRtdeBackend, URRtdeConfig
from recon import kinematics
from tests.drivers.fake_ur_fixture import FakeURProcess
from tests.motion_fixtures import line_plan

pytestmark = [pytest.mark.bench, pytest.mark.timeout(300)]


def _run(tmp_path, robot: str, length_m: float, repeats: int = 2):
    trajectory = line_plan(robot, 0.1, length_m).trajectory
    fake = FakeURProcess(tmp_path / f"fake_{robot}.log", robot).start()
    backend = URRtdeBackend(URRtdeConfig(host=fake.host, robot=robot))
    periods, deviation, lag = [], [], []
    arm = kinematics.model(robot)
    try:
        fake.control("reset", q_rad=trajectory.q_rad[0].tolist())
        backend.connect()
        backend.enable()
        for _ in range(repeats):
            # Journalled, as the service runs a real arm.
            record = backend.execute(trajectory, journal=tmp_path / f"{robot}.journal")
            periods.append(np.diff(record.t_s))
            flange = lambda q: kinematics.forward(arm, q)[:, :3, 3]  # noqa: E731
            planned, actual = flange(record.q_planned_rad), flange(record.q_actual_rad)
            deviation.append(cKDTree(flange(trajectory.q_rad)).query(actual)[0].max())
            lag.append(np.linalg.norm(actual - planned, axis=1).max())
            backend.move_joints(trajectory.q_rad[0], speed_rad_s=1.0, acceleration_rad_s2=2.0)
    finally:
        backend.close()
        fake.stop()
    return trajectory, np.concatenate(periods), max(deviation), max(lag)


def test_servoj_streaming_jitter_through_the_adapter(tmp_path):
    print("\n## servoJ streaming through the ur_rtde adapter against the fake controller\n")
    print(
        "| robot | rate Hz | periods | period p50 ms | p99 ms | max ms | |dev| p99 ms "
        "| late > 1 period | off the path, max mm | behind, max mm |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for robot, length_m in (("ur5e", 0.3), ("ur5", 0.3)):
        trajectory, periods, deviation_m, lag_m = _run(tmp_path, robot, length_m)
        nominal = trajectory.period_s
        p50, p99 = np.percentile(periods, [50, 99])
        dev99 = np.percentile(np.abs(periods - nominal), 99)
        late = np.mean(periods > 2 * nominal) * 100
        print(
            f"| {robot} | {1 / nominal:.0f} | {len(periods)} | {p50 * 1e3:.3f} | "
            f"{p99 * 1e3:.3f} | {periods.max() * 1e3:.2f} | {dev99 * 1e3:.3f} | {late:.2f} % | "
            f"{deviation_m * 1e3:.3f} | {lag_m * 1e3:.1f} |"
        )
