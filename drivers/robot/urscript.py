"""A planned motion as a standalone URScript program, for UR's teach pendant.

The program runs the plan's phases the way the controller runs them itself: the TCP and the
payload set first, ``movej`` to the approach pose (the same straight joint-space move as the
plan's transit), ``movel`` down the tool axis onto the path, the path as ``servoj`` at the
controller rate (every planned sample) or as ``movep`` through coarse waypoints blended within a
tolerance, ``movel`` back up, and ``movej`` back to the start if the plan returns there. Its
header comment names the session, the plan and the checks it passed.

The program starts with a joint move from wherever the arm stands: it is the plan's transit
only if the arm is at the plan's start joints. The program therefore checks that first and
halts with a popup when any joint is farther than :data:`START_TOLERANCE_RAD` from its start.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from drivers.robot.base import START_TOLERANCE_RAD
from recon.arrays import FloatArray
from recon.kinematics import URModel
from recon.paths import Phase
from recon.trajectory import JointTrajectory

Mode = Literal["servoj", "movep"]
#: servoJ's lookahead and gain in the program (as the ur_rtde backend streams).
LOOKAHEAD_S = 0.1
GAIN = 300
#: Acceleration the program stops the servo stream with (rad/s^2).
STOP_ACCELERATION_RAD_S2 = 2.0


def _list(values: ArrayLike) -> str:
    return "[" + ", ".join(f"{float(v):.6f}" for v in np.asarray(values)) + "]"


def _pose(values: ArrayLike) -> str:
    return "p" + _list(values)


def joint_stops(part: JointTrajectory) -> list[int]:
    """Indices of the samples where a joint-move phase comes to rest, its first and last included.

    A phase made of several joint moves (the transit that turns the base first, then the rest of
    the arm) rests between them; each move becomes its own ``movej``, so the controller follows
    the planned (checked) way and not one straight joint move that cuts across it.
    """
    resting = np.flatnonzero(np.all(np.abs(part.qd_rad_s) < 1e-9, axis=1))
    stops = [0]
    for i in resting:
        if np.abs(part.q_rad[i] - part.q_rad[stops[-1]]).max() > 1e-9:
            stops.append(int(i))
    if stops[-1] != len(part) - 1 and np.abs(part.q_rad[-1] - part.q_rad[stops[-1]]).max() > 1e-9:
        stops.append(len(part) - 1)
    return stops


def _joint_move_lines(part: JointTrajectory | None, label: str, goal: str) -> list[str]:
    """One ``movej`` per joint move of a transit or return phase, at the plan's rates."""
    if part is None or len(part) < 2:
        return []
    stops = joint_stops(part)
    lines = [f"  # {label}: joint moves to {goal} ({part.duration_s:.2f} s planned)"]
    for begin, end in itertools.pairwise(stops):
        rows = slice(begin, end + 1)
        v, a = _lead_rates(part.qd_rad_s[rows], part.qdd_rad_s2[rows])
        lines.append(f"  movej({_list(part.q_rad[end])}, a={a:.4f}, v={v:.4f})")
    return lines


def _line_lines(part: JointTrajectory, what: str) -> list[str]:
    """A straight TCP move (approach or retract) as one ``movel`` at the plan's rates."""
    if len(part) < 2:
        return []
    v, a = _tool_rates(part)
    end = np.r_[part.tcp_m[-1], part.tcp_rotvec[-1]]
    return [
        f"  # {what} ({part.duration_s:.2f} s planned)",
        f"  movel({_pose(end)}, a={a:.4f}, v={v:.4f})",
    ]


def _lead_rates(qd_rad_s: FloatArray, qdd_rad_s2: FloatArray) -> tuple[float, float]:
    """The leading joint's largest speed and acceleration in a joint move (movej's v and a).

    ``qd_rad_s``, ``qdd_rad_s2``: arrays of shape (n, 6), the move's samples.
    """
    speed = float(np.abs(qd_rad_s).max(initial=0.0))
    acceleration = float(np.abs(qdd_rad_s2).max(initial=0.0))
    return max(speed, 1e-3), max(acceleration, 1e-3)


def _tool_rates(part: JointTrajectory) -> tuple[float, float]:
    """The TCP's largest speed and acceleration along a straight line (movel's v and a)."""
    dt = part.period_s
    speed = np.linalg.norm(np.diff(part.tcp_m, axis=0), axis=1) / dt
    acceleration = np.abs(np.diff(speed)) / dt if len(speed) > 1 else np.zeros(1)
    return max(float(speed.max(initial=0.0)), 1e-3), max(float(acceleration.max(initial=0.0)), 1e-3)


def program_header(meta: dict[str, Any], source: str) -> list[str]:
    """The program's header comment: what the plan is and what it passed."""
    lines = [f"teachpath {meta.get('teachpath', '')} program from {source}".strip()]
    for key in ("session_id", "id", "source"):
        if meta.get(key):
            lines.append(f"{key}: {meta[key]}")
    if meta.get("configuration"):
        lines.append(f"configuration: {meta['configuration']}")
    if meta.get("phase_durations_s"):
        phases = ", ".join(f"{k} {v:.2f} s" for k, v in meta["phase_durations_s"].items())
        lines.append(f"phases: {phases}")
    lines += [f"checked: {check}" for check in meta.get("checks") or ()]
    return lines


def urscript_program(
    trajectory: JointTrajectory,
    *,
    tcp_pose: ArrayLike,
    payload_kg: float | None = None,
    payload_cog_m: ArrayLike = (0.0, 0.0, 0.0),
    mode: Mode = "servoj",
    tolerance_m: float = 5e-4,
    header: Sequence[str] = (),
    name: str = "teachpath_program",
) -> str:
    """The program (text) for a planned whole motion.

    Parameters
    ----------
    trajectory : JointTrajectory
        The whole motion, with its phases (a process-only trajectory is run as the path alone,
        from where the arm stands).
    tcp_pose : array_like of shape (6,)
        The TCP in the flange frame, x, y, z (m), rx, ry, rz (rotation vector).
    payload_kg, payload_cog_m :
        The payload and its centre of gravity in the flange frame; ``payload_kg`` None: the
        program sets none (the installation's stays, and a comment says so).
    mode : {"servoj", "movep"}
        The path as every planned sample, or as blended moves within ``tolerance_m``.
    header : list of str
        Lines for the header comment (session, plan, checks).
    name : str
        The program's function name.

    Raises
    ------
    ValueError
        An unknown mode, or a tolerance that is not positive.
    InfeasibleTrajectoryError
        The samples break the arm's limits (a spike, a jump, a joint out of range).
    """
    from recon.sample_check import require_within_limits

    if mode not in ("servoj", "movep"):
        raise ValueError(f"mode must be 'servoj' or 'movep', got {mode!r}")
    require_within_limits(trajectory, what="export it")
    if not tolerance_m > 0:
        raise ValueError(f"tolerance_m must be positive, got {tolerance_m}")
    arm = trajectory.arm
    lines = [f"# {line}" for line in header]
    lines += [
        f"# planned for a {trajectory.robot} at {1 / trajectory.period_s:.0f} Hz; the path as "
        f"{mode}",
        "# it starts where the plan starts: the arm must stand at the start joints below",
        f"def {name}():",
        f"  set_tcp({_pose(tcp_pose)})",
        f"  set_payload({payload_kg:.4f}, {_list(payload_cog_m)})"
        if payload_kg is not None
        else "  # payload: not set here, the installation's is kept (plan with payload_kg)",
    ]
    # The start check, joint by joint (scalar arithmetic only: URScript has no list maths).
    message = (
        '"teachpath: the arm is not at the start of this program; plan again from where it '
        'stands", "teachpath", error=True'
    )
    for joint, value in enumerate(trajectory.q_rad[0]):
        lines += [
            f"  if norm(get_actual_joint_positions()[{joint}] - ({float(value):.6f})) > "
            f"{START_TOLERANCE_RAD:.4f}:",
            f"    popup({message})",
            "    halt",
            "  end",
        ]
    if trajectory.phase is None:  # a trajectory without phases is a process path alone
        lines += _process_lines(arm, trajectory, mode, tolerance_m)
    for phase, rows in () if trajectory.phase is None else trajectory.runs():
        part = trajectory.part(rows)
        if phase is Phase.TRANSIT:
            lines += _joint_move_lines(part, "transit", "the approach pose")
        elif phase is Phase.RETURN:
            lines += _joint_move_lines(part, "return", "the start")
        elif phase is Phase.APPROACH:
            lines += _line_lines(part, "approach: straight down the tool axis")
        elif phase is Phase.RETRACT:
            lines += _line_lines(part, "retract: straight up the tool axis")
        else:
            lines += _process_lines(arm, part, mode, tolerance_m)
    lines += ["end", f"{name}()", ""]
    return "\n".join(lines)


#: movep waypoints turn the tool by at most this much from one to the next (the controller
#: interpolates the orientation between them by itself).
MAX_TURN_DEG = 5.0


def tool_waypoints(
    trajectory: JointTrajectory, *, tolerance_m: float, max_turn_deg: float = MAX_TURN_DEG
) -> np.ndarray:
    """Sample indices of waypoints such that straight TCP lines between them (what ``movep``
    runs) stay within ``tolerance_m`` of every planned TCP sample, and the tool turns at most
    ``max_turn_deg`` from one waypoint to the next. First and last samples included.

    Returns
    -------
    ndarray of shape (K,), int
    """
    from scipy.spatial.transform import Rotation

    p = trajectory.tcp_m
    rotations = Rotation.from_rotvec(np.array(trajectory.tcp_rotvec))  # a writable copy
    n = len(p)

    def fits(i: int, j: int) -> bool:
        if j - i < 2:
            return True
        turn = np.degrees((rotations[i].inv() * rotations[j]).magnitude())
        if turn > max_turn_deg:
            return False
        chord = p[j] - p[i]
        length2 = float(chord @ chord)
        inner = p[i + 1 : j] - p[i]
        u = np.clip(inner @ chord / length2, 0.0, 1.0) if length2 > 0 else np.zeros(len(inner))
        return float(np.linalg.norm(inner - u[:, None] * chord, axis=1).max()) <= tolerance_m

    index = [0]
    i = 0
    while i < n - 1:
        good, span = i + 1, 2
        bad = None
        while good < n - 1:
            j = min(i + span, n - 1)
            if not fits(i, j):
                bad = j
                break
            good, span = j, 2 * span
        while bad is not None and bad - good > 1:
            mid = (good + bad) // 2
            good, bad = (mid, bad) if fits(i, mid) else (good, mid)
        index.append(good)
        i = good
    return np.array(index)


def continuous_rotvecs(rotvecs: FloatArray) -> FloatArray:
    """The same orientations, each rotation vector written the way nearest the one before (at
    half a turn two opposite vectors name one orientation; a controller told both in turn may
    turn the tool a full half turn between them)."""
    out = np.array(rotvecs, dtype=np.float64)
    for k in range(1, len(out)):
        angle = float(np.linalg.norm(out[k]))
        if angle < 1e-9:
            continue
        other = out[k] / angle * (angle - 2.0 * np.pi)
        if np.linalg.norm(other - out[k - 1]) < np.linalg.norm(out[k] - out[k - 1]):
            out[k] = other
    return out


def _process_lines(
    arm: URModel, process: JointTrajectory, mode: Mode, tolerance_m: float
) -> list[str]:
    if mode == "servoj":
        t = process.period_s
        lines = [
            f"  # process: {len(process)} servoj samples every {t * 1e3:.1f} ms "
            f"({process.duration_s:.2f} s planned)"
        ]
        lines += [
            f"  servoj({_list(q)}, 0, 0, {t:.4f}, {LOOKAHEAD_S}, {GAIN})" for q in process.q_rad
        ]
        # Hold the last target for the lookahead so the arm arrives, then stop the stream.
        hold = int(np.ceil((LOOKAHEAD_S + 0.1) / t))
        lines += [
            f"  servoj({_list(process.q_rad[-1])}, 0, 0, {t:.4f}, {LOOKAHEAD_S}, {GAIN})"
        ] * hold
        lines.append(f"  stopj({STOP_ACCELERATION_RAD_S2})")
        return lines
    index = tool_waypoints(process, tolerance_m=tolerance_m)
    _, acceleration = _tool_rates(process)
    lines = [
        f"  # process: {len(index)} movep waypoints within {tolerance_m * 1e3:.2f} mm of the "
        f"plan ({process.duration_s:.2f} s planned)"
    ]
    blend = min(tolerance_m, 0.001)
    rotvecs = continuous_rotvecs(process.tcp_rotvec[index])
    # Each move at the plan's own mean speed over it: where the plan slows down (a tight
    # curve, the tool turning fast) so does the program, and the joints stay within what the
    # plan checked.
    distance = np.linalg.norm(np.diff(process.tcp_m[index], axis=0), axis=1)
    duration = np.diff(process.t_s[index])
    speed = np.concatenate(([0.0], distance / np.maximum(duration, process.period_s)))
    for k, i in enumerate(index):
        pose = np.r_[process.tcp_m[i], rotvecs[k]]
        r = 0.0 if k in (0, len(index) - 1) else blend  # stop on the path's ends
        v = max(float(speed[max(k, 1)]), 1e-3)
        lines.append(f"  movep({_pose(pose)}, a={acceleration:.4f}, v={v:.4f}, r={r:.4f})")
    return lines
