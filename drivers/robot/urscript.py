"""A planned motion as a standalone URScript program, for UR's teach pendant.

The program runs the plan's phases the way the controller runs them itself: the TCP and the
payload set first, ``movej`` to the approach pose (the same straight joint-space move as the
plan's transit), ``movel`` down the tool axis onto the path, the path as ``servoj`` at the
controller rate (every planned sample) or as ``movep`` through coarse waypoints blended within a
tolerance, ``movel`` back up, and ``movej`` back to the start if the plan returns there. Its
header comment names the session, the plan and the checks it passed.

The program starts with a joint move from wherever the arm stands: it is the plan's transit
only if the arm is at the plan's start joints. The program therefore checks that first and
halts with a popup when the arm is farther than :data:`START_TOLERANCE_RAD` from them.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from drivers.robot.base import START_TOLERANCE_RAD
from recon import kinematics
from recon.types import FloatArray, JointTrajectory, Phase
from recon.waypoints import coarse_waypoints

Mode = Literal["servoj", "movep"]
#: servoJ's lookahead and gain in the program (as the ur_rtde backend streams).
LOOKAHEAD_S = 0.1
GAIN = 300
#: Acceleration the program stops the servo stream with (rad/s^2).
STOP_ACCELERATION_RAD_S2 = 2.0


def _list(values) -> str:
    return "[" + ", ".join(f"{float(v):.6f}" for v in values) + "]"


def _pose(values) -> str:
    return "p" + _list(values)


def _phase(trajectory: JointTrajectory, phase: Phase) -> JointTrajectory | None:
    try:
        return trajectory.of_phase(phase)
    except ValueError:
        return None


def _lead_rates(part: JointTrajectory) -> tuple[float, float]:
    """The leading joint's largest speed and acceleration in a joint move (movej's v and a)."""
    speed = float(np.abs(part.qd_rad_s).max(initial=0.0))
    acceleration = float(np.abs(part.qdd_rad_s2).max(initial=0.0))
    return max(speed, 1e-3), max(acceleration, 1e-3)


def _tool_rates(part: JointTrajectory) -> tuple[float, float]:
    """The TCP's largest speed and acceleration along a straight line (movel's v and a)."""
    dt = part.period_s
    speed = np.linalg.norm(np.diff(part.tcp_m, axis=0), axis=1) / dt
    acceleration = np.abs(np.diff(speed)) / dt if len(speed) > 1 else np.zeros(1)
    return max(float(speed.max(initial=0.0)), 1e-3), max(float(acceleration.max(initial=0.0)), 1e-3)


def program_header(meta: dict, source: str) -> list[str]:
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
    tcp_pose: FloatArray,
    payload_kg: float = 0.0,
    payload_cog_m: FloatArray = (0.0, 0.0, 0.0),
    mode: Mode = "servoj",
    tolerance_m: float = 5e-4,
    header: list[str] = (),
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
        The payload and its centre of gravity in the flange frame.
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
    """
    if mode not in ("servoj", "movep"):
        raise ValueError(f"mode must be 'servoj' or 'movep', got {mode!r}")
    if not tolerance_m > 0:
        raise ValueError(f"tolerance_m must be positive, got {tolerance_m}")
    arm = kinematics.model(trajectory.robot)
    lines = [f"# {line}" for line in header]
    lines += [
        f"# planned for a {trajectory.robot} at {1 / trajectory.period_s:.0f} Hz; the path as "
        f"{mode}",
        "# it starts where the plan starts: the arm must stand at the start joints below",
        f"def {name}():",
        f"  set_tcp({_pose(tcp_pose)})",
        f"  set_payload({payload_kg:.4f}, {_list(payload_cog_m)})",
    ]
    start = trajectory.q_rad[0]
    lines += [
        f"  start = {_list(start)}",
        "  here = get_actual_joint_positions()",
        f"  if norm(here - start) > {START_TOLERANCE_RAD:.4f}:",
        '    popup("teachpath: the arm is not at the start of this program; plan again from '
        'where it stands", "teachpath", error=True)',
        "    halt",
        "  end",
    ]
    transit = _phase(trajectory, Phase.TRANSIT)
    if transit is not None and len(transit) > 1:
        v, a = _lead_rates(transit)
        lines += [
            f"  # transit: joint move to the approach pose ({transit.duration_s:.2f} s planned)",
            f"  movej({_list(transit.q_rad[-1])}, a={a:.4f}, v={v:.4f})",
        ]
    approach = _phase(trajectory, Phase.APPROACH)
    if approach is not None and len(approach) > 1:
        v, a = _tool_rates(approach)
        end = np.r_[approach.tcp_m[-1], approach.tcp_rotvec[-1]]
        lines += [
            f"  # approach: straight down the tool axis ({approach.duration_s:.2f} s planned)",
            f"  movel({_pose(end)}, a={a:.4f}, v={v:.4f})",
        ]
    process = _phase(trajectory, Phase.PROCESS) or trajectory
    lines += _process_lines(arm, process, mode, tolerance_m)
    retract = _phase(trajectory, Phase.RETRACT)
    if retract is not None and len(retract) > 1:
        v, a = _tool_rates(retract)
        end = np.r_[retract.tcp_m[-1], retract.tcp_rotvec[-1]]
        lines += [
            f"  # retract: straight up the tool axis ({retract.duration_s:.2f} s planned)",
            f"  movel({_pose(end)}, a={a:.4f}, v={v:.4f})",
        ]
    back = _phase(trajectory, Phase.RETURN)
    if back is not None and len(back) > 1:
        v, a = _lead_rates(back)
        lines += [
            f"  # return: joint move back to the start ({back.duration_s:.2f} s planned)",
            f"  movej({_list(back.q_rad[-1])}, a={a:.4f}, v={v:.4f})",
        ]
    lines += ["end", f"{name}()", ""]
    return "\n".join(lines)


def _process_lines(arm, process: JointTrajectory, mode: Mode, tolerance_m: float) -> list[str]:
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
    path = coarse_waypoints(arm, process, tolerance_m=tolerance_m)
    speed = float(np.linalg.norm(np.diff(process.tcp_m, axis=0), axis=1).max() / process.period_s)
    _, acceleration = _tool_rates(process)
    lines = [
        f"  # process: {len(path)} movep waypoints within {tolerance_m * 1e3:.2f} mm of the "
        f"plan ({process.duration_s:.2f} s planned)"
    ]
    blend = min(tolerance_m, 0.001)
    for k, i in enumerate(path.sample_index):
        pose = np.r_[process.tcp_m[i], process.tcp_rotvec[i]]
        r = 0.0 if k in (0, len(path) - 1) else blend  # stop on the path's ends
        lines.append(
            f"  movep({_pose(pose)}, a={acceleration:.4f}, v={max(speed, 1e-3):.4f}, r={r:.4f})"
        )
    return lines
