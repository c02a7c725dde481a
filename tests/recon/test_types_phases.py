"""Per-phase figures of a trajectory, on an analytic case."""

from __future__ import annotations

import numpy as np
import pytest

from recon.paths import Phase
from recon.trajectory import JointTrajectory


def test_the_fastest_tcp_speed_of_each_phase_is_that_of_its_samples():
    """1 s at 0.1 m/s along x (approach), then 0.5 s at 0.3 m/s along y (process), at 100 Hz:
    each phase's fastest speed is its own, exactly."""
    dt = 0.01
    t = np.arange(151) * dt
    x = np.minimum(t, 1.0) * 0.1
    y = np.maximum(t - 1.0, 0.0) * 0.3
    tcp = np.c_[x, y, np.zeros_like(t)]
    phase = np.where(t <= 1.0 + 1e-9, int(Phase.APPROACH), int(Phase.PROCESS)).astype(np.int8)
    zeros = np.zeros((len(t), 6))
    trajectory = JointTrajectory(
        robot="ur5e", t_s=t, q_rad=zeros, qd_rad_s=zeros, qdd_rad_s2=zeros, tcp_m=tcp,
        tcp_rotvec=np.zeros((len(t), 3)), arc_length_m=np.zeros(len(t)),
        requested_speed_m_s=0.3, phase=phase,
    )  # fmt: skip
    fastest = trajectory.phase_max_tcp_speed_m_s()
    assert list(fastest) == ["approach", "process"]
    assert fastest["approach"] == pytest.approx(0.1, rel=1e-9)
    assert fastest["process"] == pytest.approx(0.3, rel=1e-9)
    single = JointTrajectory(
        robot="ur5e", t_s=t[:1], q_rad=zeros[:1], qd_rad_s=zeros[:1], qdd_rad_s2=zeros[:1],
        tcp_m=tcp[:1], tcp_rotvec=np.zeros((1, 3)), arc_length_m=np.zeros(1),
        requested_speed_m_s=0.3, phase=phase[:1],
    )  # fmt: skip
    assert single.phase_max_tcp_speed_m_s() == {"approach": 0.0}
