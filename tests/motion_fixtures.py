"""Planned trajectories the motion tests share."""

from __future__ import annotations

import functools

import numpy as np

from recon.paths import Phase
from recon.plan import PlanParams, plan_path

#: Where the demo workpiece sits in front of a UR5e (base frame), metres.
WORKPIECE_IN_BASE = (0.45, 0.1, 0.05)


def base_from_tracker() -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = WORKPIECE_IN_BASE
    return T


@functools.lru_cache(maxsize=8)
def line_plan(robot: str = "ur5e", speed_m_s: float = 0.1, length_m: float = 0.15):
    """A straight line on a table in front of the arm, tool pointing down: the whole motion
    from the arm's home (transit, approach, the line, retract)."""
    s = np.linspace(0.0, length_m, int(length_m / 0.001) + 1)
    points = np.column_stack([0.4 + 0 * s, -length_m / 2 + s, np.full_like(s, 0.1)])
    return plan_path(points, params=PlanParams(robot=robot, speed_m_s=speed_m_s))


def line_process(robot: str = "ur5e", speed_m_s: float = 0.1):
    """The line itself: the process phase of :func:`line_plan`, at rest at both ends."""
    return line_plan(robot, speed_m_s).trajectory.of_phase(Phase.PROCESS)
