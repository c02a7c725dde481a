"""Whether the joint samples an arm is about to be sent keep that arm's limits.

The real-arm gate runs this on the very arrays it will stream (servoj) or turn into waypoints
(movePath), in its own process, whatever a stored summary says about them: a trajectory read
from disk, imported from another site or made by an older version is judged the same way.

Every check works on the samples as the controller sees them, by finite differences on the
controller's grid: the joints' positions within their ranges, their speeds and accelerations
within the arm's limits, a start and an end at rest, and the TCP's speed (forward kinematics of
the samples, whatever phase a sample is labelled with) within a cap. A sampled profile is judged
against its limit with a small tolerance for the sampling itself (:data:`SPEED_TOLERANCE`,
:data:`ACCELERATION_TOLERANCE`); a planned trajectory keeps well inside them (the planner's own
check is analytic, to 0.1 %).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from recon import kinematics
from recon.arrays import FloatArray
from recon.errors import InfeasibleTrajectoryError
from recon.kinematics import URModel

if TYPE_CHECKING:
    # Annotations only: recon.trajectory imports this module.
    from recon.trajectory import JointTrajectory

#: Fraction by which a sampled joint or TCP speed may exceed its limit (finite differences of a
#: planned profile stay within 0.5 % of it).
SPEED_TOLERANCE = 0.02
#: Fraction by which a sampled joint acceleration (second differences) may exceed its limit.
ACCELERATION_TOLERANCE = 0.05
#: The samples' spacing may differ from the controller's period by this much (float rounding of
#: a cumulative time axis is ~1e-12 s).
PERIOD_TOLERANCE_S = 1e-6
#: A start or end "at rest": the first and last step move no joint by more than what the arm's
#: acceleration allows from standstill in one period, times this factor.
REST_FACTOR = 2.0


@dataclass(frozen=True)
class SampleProblem:
    """One limit the samples break, where first, and by how much.

    Attributes
    ----------
    check : str
        Stable name: ``shape``, ``period``, ``position``, ``speed``, ``acceleration``, ``rest``,
        ``tcp_speed``, ``link_speed`` (the elbow, a wrist or the flange over the cap).
    sample : int
        The first sample that breaks it (-1: the arrays as a whole).
    t_s : float
        Its time (NaN where there is none).
    message : str
        What is wrong, in words an operator can act on.
    """

    check: str
    sample: int
    t_s: float
    message: str


def sample_problems(
    arm: URModel,
    t_s: FloatArray,
    q_rad: FloatArray,
    *,
    tcp_speed_max_m_s: float,
    T_flange_tcp: FloatArray,
    rate_hz: float | None = None,
) -> list[SampleProblem]:
    """Every limit the samples break (the first sample of each), or an empty list.

    Parameters
    ----------
    arm : URModel
        The arm that will run them (the server's configured model, not the one the trajectory
        names).
    t_s : ndarray of shape (K,)
        Sample times, seconds.
    q_rad : ndarray of shape (K, 6)
        Joint positions, radians.
    tcp_speed_max_m_s : float
        The largest TCP speed allowed on any sample.
    T_flange_tcp : ndarray of shape (4, 4)
        The TCP the controller will be given, in the flange frame.
    rate_hz : float, optional
        The rate the samples are sent at (default the arm's control rate).

    Returns
    -------
    list of SampleProblem
        Empty when every check passes. Arrays of the wrong shape or with non-finite values
        return one ``shape`` problem and nothing else is judged.
    """
    t = np.asarray(t_s)
    q = np.asarray(q_rad)
    shape = _shape_problem(t, q)
    if shape is not None:
        return [shape]
    t = t.astype(np.float64)
    q = q.astype(np.float64)
    period_s = 1.0 / float(rate_hz or arm.control_rate_hz)
    problems: list[SampleProblem] = []

    dt = np.diff(t)
    off = np.abs(dt - period_s) > PERIOD_TOLERANCE_S
    if off.any():
        i = int(np.argmax(off))
        problems.append(
            SampleProblem(
                "period",
                i + 1,
                float(t[i + 1]),
                f"sample {i + 1} comes {dt[i] * 1e3:.4g} ms after the one before; the controller "
                f"takes one every {period_s * 1e3:.4g} ms: plan it again for the {arm.name}",
            )
        )
        return problems  # speeds on a wrong grid would be judged wrongly

    low, high = q < arm.q_min_rad - 1e-9, q > arm.q_max_rad + 1e-9
    outside = low | high
    if outside.any():
        i, j = (int(v) for v in np.unravel_index(int(np.argmax(outside)), outside.shape))
        problems.append(
            SampleProblem(
                "position",
                int(i),
                float(t[i]),
                f"joint {j + 1} is at {np.degrees(q[i, j]):.1f} deg, outside its range "
                f"[{np.degrees(arm.q_min_rad[j]):.0f}, {np.degrees(arm.q_max_rad[j]):.0f}] deg",
            )
        )

    speed = np.abs(np.diff(q, axis=0)) / period_s  # (K-1, 6), rad/s
    over = _first_over(speed, arm.qd_max_rad_s, SPEED_TOLERANCE)
    if over is not None:
        i, j, share = over
        problems.append(
            SampleProblem(
                "speed",
                i + 1,
                float(t[i + 1]),
                f"joint {j + 1} moves at {speed[i, j]:.3f} rad/s, {share * 100:.0f} % of "
                f"the {arm.name}'s {arm.qd_max_rad_s[j]:.3f} rad/s",
            )
        )
    acceleration = np.abs(np.diff(q, n=2, axis=0)) / period_s**2  # (K-2, 6), rad/s^2
    over = _first_over(acceleration, arm.qdd_max_rad_s2, ACCELERATION_TOLERANCE)
    if over is not None:
        i, j, share = over
        problems.append(
            SampleProblem(
                "acceleration",
                i + 1,
                float(t[i + 1]),
                f"joint {j + 1} accelerates at {acceleration[i, j]:.2f} rad/s^2, "
                f"{share * 100:.0f} % of the {arm.qdd_max_rad_s2[j]:.2f} rad/s^2 planning limit",
            )
        )

    rest_step = REST_FACTOR * arm.qdd_max_rad_s2 * period_s**2
    for where, step, sample in (("starts", q[1] - q[0], 0), ("ends", q[-1] - q[-2], len(q) - 1)):
        if np.any(np.abs(step) > rest_step):
            j = int(np.argmax(np.abs(step) / rest_step))
            problems.append(
                SampleProblem(
                    "rest",
                    sample,
                    float(t[sample]),
                    f"the motion {where} with joint {j + 1} moving at "
                    f"{abs(step[j]) / period_s:.3f} rad/s: a motion must start and end at rest",
                )
            )

    if np.isinf(tcp_speed_max_m_s):
        return problems  # no cap to judge the TCP against (a file checked offline)
    # One forward kinematics for every point the cap holds for (the TCP last).
    points = kinematics.speed_points_m(arm, q, T_flange_tcp)  # (K, 6, 3)
    speeds = np.linalg.norm(np.diff(points, axis=0), axis=-1) / period_s  # (K-1, 6), m/s
    tcp_speed, point_speed = speeds[:, -1], speeds[:, :-1]
    if tcp_speed.max() > tcp_speed_max_m_s * (1.0 + SPEED_TOLERANCE):
        i = int(np.argmax(tcp_speed))
        problems.append(
            SampleProblem(
                "tcp_speed",
                i + 1,
                float(t[i + 1]),
                f"the TCP moves at {tcp_speed[i] * 1e3:.0f} mm/s, above the "
                f"{tcp_speed_max_m_s * 1e3:.0f} mm/s cap",
            )
        )
    # The cap is on every point of the arm, as UR's safety limits are on the elbow's speed.
    if point_speed.max() > tcp_speed_max_m_s * (1.0 + SPEED_TOLERANCE):
        i, k = (int(v) for v in np.unravel_index(int(np.argmax(point_speed)), point_speed.shape))
        problems.append(
            SampleProblem(
                "link_speed",
                int(i) + 1,
                float(t[i + 1]),
                f"the {kinematics.SPEED_POINT_NAMES[k]} moves at {point_speed[i, k] * 1e3:.0f} "
                f"mm/s, above the {tcp_speed_max_m_s * 1e3:.0f} mm/s cap (it holds for every "
                "point of the arm)",
            )
        )
    return problems


def require_within_limits(trajectory: JointTrajectory, *, what: str) -> None:
    """Refuse a trajectory whose samples break its arm's limits, before it is used: joint
    ranges, speeds and accelerations on the controller's grid, continuity, a start and an end
    at rest (:func:`sample_problems` without a TCP cap). For every consumer of a trajectory
    file (the dry run, the URScript export): a file is not trusted for having been planned.

    Parameters
    ----------
    trajectory : recon.trajectory.JointTrajectory
    what : str
        What was about to be done with it, for the message ("dry-run it", "export it").

    Raises
    ------
    InfeasibleTrajectoryError
        Naming each broken limit's first sample, its time and joint.
    """
    arm = trajectory.arm
    problems = sample_problems(
        arm,
        trajectory.t_s,
        trajectory.q_rad,
        tcp_speed_max_m_s=float("inf"),
        T_flange_tcp=np.eye(4),
        rate_hz=1.0 / trajectory.period_s,
    )
    if problems:
        said = "; ".join(
            f"sample {p.sample}"
            + ("" if np.isnan(p.t_s) else f" ({p.t_s:.3f} s)")
            + f": {p.message}"
            for p in problems
        )
        raise InfeasibleTrajectoryError(
            f"the trajectory's samples break the {arm.name}'s limits, so teachpath will not "
            f"{what}: {said}. Plan it again (a planned trajectory keeps them); an edited or "
            "damaged file is not run"
        )


def _first_over(
    values: FloatArray, limit: FloatArray, tolerance: float
) -> tuple[int, int, float] | None:
    """``(row, joint, share of the limit)`` of the largest value above ``limit * (1 +
    tolerance)`` in ``values`` (R, 6), or None (also for no rows)."""
    if len(values) == 0:
        return None
    ratio = values / limit
    i, j = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
    if ratio[i, j] <= 1.0 + tolerance:
        return None
    return int(i), int(j), float(ratio[i, j])


def tcp_positions_m(arm: URModel, q_rad: FloatArray, T_flange_tcp: FloatArray) -> FloatArray:
    """The TCP's position at each sample (forward kinematics), shape (K, 3), metres."""
    q = np.asarray(q_rad, dtype=np.float64)
    return (kinematics.forward(arm, q) @ np.asarray(T_flange_tcp, dtype=np.float64))[:, :3, 3]


def tcp_speeds_m_s(
    arm: URModel,
    q_rad: FloatArray,
    *,
    T_flange_tcp: FloatArray | None = None,
    rate_hz: float | None = None,
    tcp_m: FloatArray | None = None,
) -> FloatArray:
    """The TCP's speed between consecutive samples, m/s, shape (K-1,): from ``tcp_m`` (K, 3)
    when the caller has the positions, else by forward kinematics with ``T_flange_tcp``."""
    period_s = 1.0 / float(rate_hz or arm.control_rate_hz)
    if tcp_m is not None:
        tcp = tcp_m
    elif T_flange_tcp is not None:
        tcp = tcp_positions_m(arm, q_rad, T_flange_tcp)
    else:
        raise ValueError("give the TCP's positions (tcp_m) or the tool (T_flange_tcp)")
    speeds: FloatArray = np.linalg.norm(np.diff(tcp, axis=0), axis=1) / period_s
    return speeds


def _shape_problem(t: np.ndarray, q: np.ndarray) -> SampleProblem | None:
    def problem(message: str) -> SampleProblem:
        return SampleProblem("shape", -1, float("nan"), message + ": plan it again")

    if t.ndim != 1 or q.ndim != 2 or q.shape != (len(t), 6):
        return problem(f"the samples have shapes {t.shape} (times) and {q.shape} (joints)")
    if len(t) < 2:
        return problem(f"the trajectory has {len(t)} sample(s)")
    real = (np.floating, np.integer)
    if not all(any(np.issubdtype(a.dtype, kind) for kind in real) for a in (t, q)):
        return problem("the samples are not numbers")
    if not (np.isfinite(t).all() and np.isfinite(q).all()):
        return problem("the samples hold values that are not finite numbers")
    return None
