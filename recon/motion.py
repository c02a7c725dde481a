"""The whole motion of a plan: from where the arm is, onto the path, along it, and away.

A process path alone is not a program an arm can run: the arm stands somewhere else when the
operator presses play, and the path starts on the workpiece. The whole motion is, in order:

* **transit** — a joint move (every joint on one synchronised trapezoidal profile, as UR's
  ``movej``) from the start joints to the approach pose;
* **approach** — a straight line down the tool axis from ``approach_m`` above the path's first
  point onto it, at ``approach_speed_m_s``;
* **process** — the path, timed by :func:`recon.timing.time_parameterize`;
* **retract** — a straight line up the tool axis from the path's last point;
* **return** (optional) — a joint move back to the start joints.

Each phase starts and ends at rest, is timed within the arm's limits (the joint moves at a
fraction of them: ``transit_speed_scale``), and labels its samples with its
:class:`recon.paths.Phase`. The approach and retract keep the process path's IK branch, so the
arm does not change configuration anywhere; the joint moves go straight in joint space, which is
what the collision check of :mod:`recon.collision` then looks at.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon import kinematics
from recon.arrays import FloatArray
from recon.errors import InfeasibleTrajectoryError
from recon.kinematics import URModel
from recon.paths import JointPath, Phase, SpeedDrop, ToolPath
from recon.timing import limits_for, time_parameterize
from recon.trajectory import JointTrajectory
from recon.transforms import invert_transform, pose_from_transform

#: Spacing of the waypoints of the straight approach and retract lines.
LINE_STEP_M = 0.001
#: Largest joint difference at a phase boundary that still counts as the same configuration.
BOUNDARY_TOLERANCE_RAD = 1e-6


@dataclass(frozen=True)
class PhaseSamples:
    """One phase, sampled at the controller rate from its own start (t = 0, at rest).

    Attributes
    ----------
    phase : Phase
    t_s : ndarray of shape (K,)
    q_rad, qd_rad_s, qdd_rad_s2 : ndarray of shape (K, 6)
    speed_drops : tuple of SpeedDrop
        Where the phase is slower than requested (the process phase only).
    """

    phase: Phase
    t_s: FloatArray
    q_rad: FloatArray
    qd_rad_s: FloatArray
    qdd_rad_s2: FloatArray
    speed_drops: tuple[SpeedDrop, ...] = ()

    @classmethod
    def of(cls, phase: Phase, trajectory: JointTrajectory) -> PhaseSamples:
        return cls(
            phase,
            trajectory.t_s,
            trajectory.q_rad,
            trajectory.qd_rad_s,
            trajectory.qdd_rad_s2,
            trajectory.speed_drops,
        )


def trapezoid_duration(distance: float, speed: float, acceleration: float) -> float:
    """How long a rest-to-rest move of ``distance`` takes at most ``speed`` and
    ``acceleration`` (triangular when it is too short to reach the speed)."""
    t_acc = speed / acceleration
    if acceleration * t_acc**2 >= distance:
        return 2.0 * float(np.sqrt(distance / acceleration))
    return distance / speed + t_acc


def trapezoid(
    distance: float, speed: float, acceleration: float, t_s: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Position, speed and acceleration at times ``t_s`` of a rest-to-rest trapezoidal profile
    (the time-optimal one within ``speed`` and ``acceleration``; triangular when the move is
    too short to reach the speed); at rest at ``distance`` after the end.

    Parameters
    ----------
    distance, speed, acceleration : float
        In one unit of length (or of a path parameter) and seconds.
    t_s : ndarray of shape (K,)

    Returns
    -------
    position, speed, acceleration : ndarray of shape (K,)
    """
    t_total = trapezoid_duration(distance, speed, acceleration)
    t_acc = min(speed / acceleration, 0.5 * t_total)
    peak = acceleration * t_acc
    t = np.minimum(np.asarray(t_s, dtype=np.float64), t_total)
    rising, falling = t < t_acc, t > t_total - t_acc
    cruise = 0.5 * acceleration * t_acc**2 + peak * (t - t_acc)
    position = np.where(
        rising,
        0.5 * acceleration * t**2,
        np.where(falling, distance - 0.5 * acceleration * (t_total - t) ** 2, cruise),
    )
    rate = np.where(rising, acceleration * t, np.where(falling, acceleration * (t_total - t), peak))
    accel = np.where(rising, acceleration, np.where(falling, -acceleration, 0.0))
    after = np.asarray(t_s) >= t_total
    rate[after], accel[after] = 0.0, 0.0
    return np.clip(position, 0.0, distance), rate, accel


def joint_move(
    arm: URModel,
    q_from_rad: FloatArray,
    q_to_rad: FloatArray,
    *,
    speed_scale: float,
    acceleration_scale: float,
    rate_hz: float | None = None,
    tcp_speed_max_m_s: float | None = None,
    T_flange_tcp: FloatArray | None = None,
) -> PhaseSamples:
    """A straight joint-space move, every joint on one trapezoidal profile (UR's ``movej``).

    The common profile runs a path parameter s from 0 to 1 at the largest rate and acceleration
    every joint allows: ``ds/dt <= v_j / |dq_j|`` and ``d2s/dt2 <= a_j / |dq_j|`` with ``v_j``,
    ``a_j`` the arm's limits times the scales. A move of zero length is one sample.

    With ``tcp_speed_max_m_s`` the rate is also held so that neither the TCP (``T_flange_tcp``
    from the flange) nor the elbow or a wrist (:func:`recon.kinematics.speed_points_m`) ever
    moves faster: a point's speed is ``|dx/ds| * ds/dt``, and ``|dx/ds|`` is taken at its
    largest along the move (:data:`TCP_SPEED_SEGMENTS` chords, with a margin for the chords'
    shortfall against the tangent).

    Returns
    -------
    PhaseSamples
        Phase TRANSIT (the caller relabels a return).
    """
    q0 = np.asarray(q_from_rad, dtype=np.float64)
    q1 = np.asarray(q_to_rad, dtype=np.float64)
    delta = q1 - q0
    dt = 1.0 / float(rate_hz or arm.control_rate_hz)
    moving = np.abs(delta) > 1e-12
    if not moving.any():
        zero = np.zeros((1, 6))
        return PhaseSamples(Phase.TRANSIT, np.zeros(1), q0[None], zero, zero)
    v = arm.qd_max_rad_s * speed_scale
    a = arm.qdd_max_rad_s2 * acceleration_scale
    s_rate = float(np.min(v[moving] / np.abs(delta[moving])))
    s_acc = float(np.min(a[moving] / np.abs(delta[moving])))
    if tcp_speed_max_m_s is not None:
        s_rate = min(
            s_rate, _rate_for_point_speeds(arm, q0, delta, tcp_speed_max_m_s, T_flange_tcp)
        )
    t_total = trapezoid_duration(1.0, s_rate, s_acc)
    t = np.arange(int(np.ceil(t_total / dt - 1e-9)) + 1, dtype=np.float64) * dt
    s, sd, sdd = trapezoid(1.0, s_rate, s_acc, t)
    s[-1] = 1.0
    q = q0 + s[:, None] * delta
    # q0 + (q1 - q0) can miss q1 by a rounding: the move ends exactly where it was asked to (the
    # next phase starts there, and a gate compares the two).
    q[-1] = q1
    return PhaseSamples(Phase.TRANSIT, t, q, sd[:, None] * delta, sdd[:, None] * delta)


#: Chords along a joint move over which its largest TCP speed per unit of s is taken.
TCP_SPEED_SEGMENTS = 512
#: What the rate keeps below the cap: the chords' shortfall against the tangent is far below
#: 1 % at 512 chords for any joint move (|dq| <= 2 pi per joint); the rest is headroom for the
#: sampled check of the executed samples.
TCP_SPEED_MARGIN = 0.97


def _rate_for_point_speeds(
    arm: URModel,
    q0: FloatArray,
    delta: FloatArray,
    tcp_speed_max_m_s: float,
    T_flange_tcp: FloatArray | None,
) -> float:
    """The largest ds/dt at which the TCP, the elbow and the wrists (every point of
    :func:`recon.kinematics.speed_points_m`) keep below ``tcp_speed_max_m_s`` along
    q0 + s delta: a real arm's cap is on all of them, as UR's safety limits are."""
    if not tcp_speed_max_m_s > 0:
        raise ValueError(f"tcp_speed_max_m_s must be positive, got {tcp_speed_max_m_s}")
    T = np.eye(4) if T_flange_tcp is None else np.asarray(T_flange_tcp, dtype=np.float64)
    s = np.linspace(0.0, 1.0, TCP_SPEED_SEGMENTS + 1)
    points = kinematics.speed_points_m(arm, q0 + s[:, None] * delta, T)  # (S, P, 3)
    per_s = float(np.max(np.linalg.norm(np.diff(points, axis=0), axis=-1))) * TCP_SPEED_SEGMENTS
    if per_s <= 0.0:
        return float("inf")  # the TCP stays put (a turn of the last joint about the tool axis)
    return TCP_SPEED_MARGIN * tcp_speed_max_m_s / per_s


def tool_line(T_from_tcp: FloatArray, T_to_tcp: FloatArray) -> ToolPath:
    """A straight TCP line between two poses of the same orientation, every :data:`LINE_STEP_M`
    (at least three waypoints), keeping ``T_to_tcp``'s orientation."""
    from scipy.spatial.transform import Rotation

    start, end = T_from_tcp[:3, 3], T_to_tcp[:3, 3]
    length = float(np.linalg.norm(end - start))
    n = max(3, int(np.ceil(length / LINE_STEP_M)) + 1)
    f = np.linspace(0.0, 1.0, n)
    points = start + f[:, None] * (end - start)
    q = Rotation.from_matrix(T_to_tcp[:3, :3]).as_quat()
    return ToolPath(
        points_m=points,
        orientations_xyzw=np.tile(q, (n, 1)),
        arc_length_m=f * length,
        source="line",
    )


def lifted(T_tcp: FloatArray, height_m: float) -> FloatArray:
    """The pose ``height_m`` back along its own tool axis (the tool's z points into the work)."""
    T = np.array(T_tcp, dtype=np.float64)
    T[:3, 3] -= height_m * T[:3, 2]
    return T


def line_move(
    arm: URModel,
    tool: ToolPath,
    *,
    branch: int,
    q_end_rad: FloatArray | None,
    q_start_rad: FloatArray | None,
    T_flange_tcp: FloatArray,
    speed_m_s: float,
    velocity_scale: float,
    acceleration_scale: float,
    phase: Phase,
    point_speed_max_m_s: float | None = None,
) -> PhaseSamples:
    """A straight TCP line in one IK branch, joined to a neighbouring phase's joints exactly.

    Exactly one of ``q_end_rad`` (the line ends where the next phase starts: the approach) and
    ``q_start_rad`` (it starts where the previous phase ends: the retract) is given; with
    ``point_speed_max_m_s`` the elbow, wrists and flange keep below it too.

    Raises
    ------
    InfeasibleTrajectoryError
        The branch cannot follow the line, or it does not meet the neighbouring joints.
    """
    flange = tool.poses() @ invert_transform(T_flange_tcp)
    if q_end_rad is not None:
        # Solved from the joined end, so the joint turns (2 pi shifts) are chosen there.
        joints = kinematics.follow_path(
            arm, flange[::-1], q_near_rad=q_end_rad, allowed_branches=(branch,)
        )
        joined, q_joined = joints.q_rad[0], q_end_rad
        joints = _reversed(joints)
    elif q_start_rad is not None:
        joints = kinematics.follow_path(
            arm, flange, q_near_rad=q_start_rad, allowed_branches=(branch,)
        )
        joined, q_joined = joints.q_rad[0], q_start_rad
    else:
        raise ValueError("a line move joins a neighbouring phase: give q_end_rad or q_start_rad")
    gap = float(np.abs(joined - q_joined).max())
    if gap > BOUNDARY_TOLERANCE_RAD:
        raise InfeasibleTrajectoryError(
            f"the {phase.label} line does not join the path ({np.degrees(gap):.2f} deg apart at "
            "the path's end): shorten approach_m or change the tool orientation"
        )
    limits = limits_for(
        arm, speed_m_s, velocity_scale=velocity_scale, acceleration_scale=acceleration_scale
    )
    timed = time_parameterize(
        arm,
        joints,
        tool,
        limits,
        T_flange_tcp=T_flange_tcp,
        point_speed_max_m_s=point_speed_max_m_s,
    )
    # toppra's end samples hold the waypoints to rounding: put them exactly on the joins.
    q = np.array(timed.q_rad)
    if q_end_rad is not None:
        q[-1] = q_end_rad
    else:
        q[0] = q_start_rad
    return PhaseSamples(phase, timed.t_s, q, timed.qd_rad_s, timed.qdd_rad_s2)


def _reversed(joints: JointPath) -> JointPath:
    return JointPath(
        q_rad=joints.q_rad[::-1],
        branch=joints.branch,
        limit_margin_rad=joints.limit_margin_rad[::-1],
        wrist_singularity=joints.wrist_singularity[::-1],
        elbow_singularity=joints.elbow_singularity[::-1],
        shoulder_margin_m=joints.shoulder_margin_m[::-1],
    )


def assemble(
    arm: URModel,
    phases: list[PhaseSamples],
    *,
    T_flange_tcp: FloatArray,
    requested_speed_m_s: float,
) -> JointTrajectory:
    """One trajectory from phases that each start where the previous one ends, at rest.

    Every phase keeps all its samples: where two meet, the arm rests on the joining pose for
    one controller period (the last sample of one, then the first of the next), so each phase
    read back with :meth:`JointTrajectory.of_phase` starts and ends at rest, as it was planned.

    Raises
    ------
    ValueError
        Phases that do not join (a bug of the caller).
    """
    dt = 1.0 / arm.control_rate_hz
    t: list[FloatArray] = []
    q: list[FloatArray] = []
    qd: list[FloatArray] = []
    qdd: list[FloatArray] = []
    label: list[np.ndarray] = []
    offset = 0.0
    drops: tuple[SpeedDrop, ...] = ()
    for index, part in enumerate(phases):
        if index:
            gap = float(np.abs(part.q_rad[0] - q[-1][-1]).max())
            if gap > BOUNDARY_TOLERANCE_RAD:
                raise ValueError(
                    f"the {part.phase.label} phase starts {gap:.2e} rad from where the "
                    "previous one ends"
                )
        t.append(part.t_s + offset)
        q.append(part.q_rad)
        qd.append(part.qd_rad_s)
        qdd.append(part.qdd_rad_s2)
        label.append(np.full(len(part.t_s), int(part.phase), dtype=np.int8))
        offset += float(part.t_s[-1]) + dt
        if part.phase is Phase.PROCESS:
            drops += part.speed_drops
    q_all = np.concatenate(q)
    tcp = pose_from_transform(kinematics.forward(arm, q_all) @ np.asarray(T_flange_tcp))
    travel = np.linalg.norm(np.diff(tcp[:, :3], axis=0), axis=1)
    # On the grid: the sum of phase durations carries float error into later phases.
    t_all = np.round(np.concatenate(t) / dt) * dt
    return JointTrajectory(
        robot=arm.name,
        t_s=t_all,
        q_rad=q_all,
        qd_rad_s=np.concatenate(qd),
        qdd_rad_s2=np.concatenate(qdd),
        tcp_m=tcp[:, :3],
        tcp_rotvec=tcp[:, 3:],
        arc_length_m=np.concatenate(([0.0], np.cumsum(travel))),
        requested_speed_m_s=requested_speed_m_s,
        speed_drops=drops,
        phase=np.concatenate(label),
        calibration=arm.calibration,
    )
