"""Coarse joint waypoints of a timed trajectory, for UR's movePath.

Streaming every controller sample with servoJ is the default. A controller can also run a path
itself: a list of moveJ targets blended into each other (ur_rtde's ``movePath``). That needs far
fewer, well-chosen waypoints: between two of them the controller moves the joints along a
straight line in joint space, so the waypoints are picked greedily as far apart as the
planned TCP allows -- every planned sample between two waypoints must lie within a tolerance of
where the joint-space line puts the TCP.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon import kinematics
from recon.arrays import FloatArray
from recon.kinematics import URModel
from recon.trajectory import JointTrajectory
from recon.transforms import invert_transform, transform_from_pose

#: Longest stretch (samples) considered between two waypoints: bounds the work per check.
MAX_SPAN_SAMPLES = 4000


@dataclass(frozen=True)
class CoarsePath:
    """Waypoints for a controller-run path.

    Attributes
    ----------
    sample_index : ndarray of shape (M,), int
        The trajectory sample each waypoint is taken from (first and last included).
    q_rad : ndarray of shape (M, 6)
    speed_rad_s : ndarray of shape (M,)
        Leading-joint speed for the move *to* each waypoint (the first entry repeats the second's),
        so the move takes as long as the planned samples between them.
    acceleration_rad_s2 : float
        Leading-joint acceleration for every move.
    blend_m : ndarray of shape (M,)
        Blend radius at each waypoint (TCP, metres); 0 at both ends, and never more than 40 % of
        the shorter neighbouring stretch (UR refuses overlapping blends).
    deviation_max_m : float
        Largest distance of a planned TCP sample from the joint-space line through its
        neighbouring waypoints.
    """

    sample_index: np.ndarray
    q_rad: FloatArray
    speed_rad_s: FloatArray
    acceleration_rad_s2: float
    blend_m: FloatArray
    deviation_max_m: float

    def __len__(self) -> int:
        return len(self.sample_index)


def coarse_waypoints(
    arm: URModel,
    trajectory: JointTrajectory,
    *,
    tolerance_m: float = 5e-4,
    blend_m: float = 1e-3,
) -> CoarsePath:
    """Pick waypoints so that straight joint moves between them keep the TCP on the plan.

    Parameters
    ----------
    arm : URModel
        The arm the trajectory was planned for.
    trajectory : JointTrajectory
    tolerance_m : float
        Largest allowed distance of a planned TCP sample from the coarse path.
    blend_m : float
        Blend radius asked for at the inner waypoints (the controller rounds the corner within
        it instead of stopping); 0 stops at every waypoint.

    Returns
    -------
    CoarsePath

    Raises
    ------
    ValueError
        A tolerance that is not positive, or a trajectory for another arm.
    """
    if not tolerance_m > 0:
        raise ValueError(f"tolerance_m must be positive, got {tolerance_m}")
    if not blend_m >= 0:
        raise ValueError(f"blend_m must be >= 0, got {blend_m}")
    if trajectory.robot != arm.name:
        raise ValueError(f"the trajectory is for a {trajectory.robot}, not a {arm.name}")
    q = trajectory.q_rad
    T_flange_tcp = _tcp_offset(arm, trajectory)
    n = len(q)

    def deviation(i: int, j: int) -> float:
        if j - i < 2:
            return 0.0
        dq = q[j] - q[i]
        inner = q[i + 1 : j]
        norm2 = float(dq @ dq)
        # Where each planned sample sits along the joint line (projection in joint space).
        u = np.clip((inner - q[i]) @ dq / norm2, 0.0, 1.0) if norm2 > 0 else np.zeros(len(inner))
        on_line = kinematics.forward(arm, q[i] + u[:, None] * dq) @ T_flange_tcp
        return float(np.linalg.norm(on_line[:, :3, 3] - trajectory.tcp_m[i + 1 : j], axis=1).max())

    indices = [0]
    worst = 0.0
    i = 0
    while i < n - 1:
        # Exponential search for a span that breaks the tolerance, then bisection.
        good, bad, span = i + 1, None, 2
        while True:
            j = min(i + span, n - 1, i + MAX_SPAN_SAMPLES)
            if j <= good:
                break  # the end of the trajectory, or the longest span considered
            if deviation(i, j) > tolerance_m:
                bad = j
                break
            good, span = j, 2 * span
        while bad is not None and bad - good > 1:
            mid = (good + bad) // 2
            if deviation(i, mid) <= tolerance_m:
                good = mid
            else:
                bad = mid
        worst = max(worst, deviation(i, good))
        indices.append(good)
        i = good
    index = np.array(indices)
    waypoints = q[index]
    lead_rad = np.abs(np.diff(waypoints, axis=0)).max(axis=1)
    duration_s = np.diff(trajectory.t_s[index])
    speed = np.maximum(lead_rad / np.maximum(duration_s, 1e-9), 1e-3)
    speed = np.minimum(speed, float(arm.qd_max_rad_s.min()))
    speed = np.concatenate([speed[:1], speed])
    acceleration = float(
        np.clip(np.abs(trajectory.qdd_rad_s2).max(), 0.5, arm.qdd_max_rad_s2.min())
    )
    stretch_m = np.linalg.norm(np.diff(trajectory.tcp_m[index], axis=0), axis=1)
    blend = np.zeros(len(index))
    if len(index) > 2:
        blend[1:-1] = np.minimum(blend_m, 0.4 * np.minimum(stretch_m[:-1], stretch_m[1:]))
    return CoarsePath(index, waypoints, speed, acceleration, blend, worst)


def _tcp_offset(arm: URModel, trajectory: JointTrajectory) -> FloatArray:
    """``T_flange_tcp`` recovered from the first sample's planned TCP pose, shape (4, 4)."""
    first_pose = np.concatenate([trajectory.tcp_m[0], trajectory.tcp_rotvec[0]])
    T_base_tcp = transform_from_pose(first_pose)
    return invert_transform(kinematics.forward(arm, trajectory.q_rad[0])) @ T_base_tcp
