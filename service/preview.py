"""What the pendant draws of a plan and of an execution: a plan's samples thinned for a browser
(the arm's joint positions from its DH chain, the TCP, its speed and every margin per waypoint),
and an execution's planned-against-actual tracking along the path.

The browser draws and animates; every number comes from here, computed with the same
kinematics (:mod:`recon.kinematics`) that planned the motion, so the page never re-implements
the arm.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np
from numpy.typing import ArrayLike

from recon.arrays import FloatArray
from recon.paths import Phase

if TYPE_CHECKING:
    from recon.trajectory import JointTrajectory
    from service.artifacts import ExecutionSamples

#: The most samples a preview sends by default (a 30 s plan at 500 Hz has 15 000).
DEFAULT_SAMPLES = 1500


def thinned(n: int, max_samples: int, phases: np.ndarray | None = None) -> np.ndarray:
    """Indices of at most about ``max_samples`` of ``n`` samples, evenly spaced, keeping the
    first, the last and the first sample of each phase (so no phase is lost)."""
    keep = np.linspace(0, n - 1, min(n, max_samples)).round().astype(np.int64)
    if phases is not None and n > 1:
        keep = np.r_[keep, np.flatnonzero(np.diff(phases)) + 1]
    return np.unique(np.clip(keep, 0, n - 1))


def window_min(values: FloatArray, keep: np.ndarray) -> FloatArray:
    """The smallest value from each kept sample up to the next one: a thinned margin never
    hides a dip between the samples sent. (K,) for K kept indices."""
    return np.minimum.reduceat(values, keep)


class SpeedDropTimes(TypedDict):
    """A slow-down of the process path and when it happens (see :func:`speed_drop_times`)."""

    start_s: float
    end_s: float
    min_speed_m_s: float
    cause: str


def speed_drop_times(trajectory: JointTrajectory) -> list[SpeedDropTimes]:
    """Each slow-down of the process path with the times it starts and ends.

    The drops are counted in metres of process path (the moves between pieces left out);
    the times are those of the first and last sample inside the stretch.

    Returns
    -------
    list of SpeedDropTimes
        ``start_s``, ``end_s``, ``min_speed_m_s``, ``cause`` per drop that lies on the path.
    """
    t = trajectory.t_s
    process = np.flatnonzero(trajectory.phases == int(Phase.PROCESS))
    if not len(process):
        return []
    step = np.linalg.norm(np.diff(trajectory.tcp_m[process], axis=0), axis=1)
    step[np.diff(process) != 1] = 0.0
    arc = np.r_[0.0, np.cumsum(step)]
    out: list[SpeedDropTimes] = []
    for drop in trajectory.speed_drops:
        inside = process[(arc >= drop.start_m) & (arc <= drop.end_m)]
        if len(inside):
            out.append(
                {
                    "start_s": float(t[inside[0]]),
                    "end_s": float(t[inside[-1]]),
                    "min_speed_m_s": float(drop.min_speed_m_s),
                    "cause": drop.cause,
                }
            )
    return out


def tcp_speed_m_s(trajectory: JointTrajectory) -> FloatArray:
    """The planned TCP's speed at each sample, (M,) m/s."""
    speed: FloatArray = np.linalg.norm(
        np.gradient(trajectory.tcp_m, trajectory.t_s, axis=0), axis=1
    )
    return speed


def _rounded(values: ArrayLike, decimals: int) -> list[Any]:
    """An array rounded, as (nested) lists of numbers."""
    rounded: list[Any] = np.round(np.asarray(values, dtype=np.float64), decimals).tolist()
    return rounded


def _finite_or_none(values: ArrayLike, decimals: int) -> list[float | None]:
    """A 1-D series rounded, with null for what is not finite (JSON has no inf or NaN)."""
    values = np.asarray(values, dtype=np.float64)
    return [round(float(v), decimals) if np.isfinite(v) else None for v in values]


def trajectory_preview(
    trajectory: JointTrajectory,
    clearance_m: FloatArray | None = None,
    *,
    max_samples: int = DEFAULT_SAMPLES,
) -> dict[str, Any]:
    """A plan for the pendant: the arm at each kept sample and the margins per waypoint.

    Parameters
    ----------
    trajectory : recon.trajectory.JointTrajectory
        ``t_s`` (M,), ``q_rad`` and ``qd_rad_s`` (M, 6), ``tcp_m`` (M, 3), phases.
    clearance_m : ndarray of shape (M,), optional
        The smallest clearance of the arm and tool to the cell per sample (when checked).
    max_samples : int
        About how many samples to send (K below).

    Returns
    -------
    dict
        ``t_s`` (K,); ``phase`` (K,) labels' indices into ``phases``; ``joints_m`` (K, 8, 3):
        base, the origins of the DH frames 1..6 (frame 6: the flange) and the TCP, base
        frame; ``tcp_m`` (K, 3); ``tool_axis`` (K, 3) the TCP frame's z (unit, base frame);
        ``speed_m_s`` (K,); ``q_deg`` (K, 6); the margins (K,),
        each the smallest over the samples up to the next kept one: ``limit_margin_deg``,
        ``wrist_singularity`` (|sin q5|), ``elbow_singularity`` (|sin q3|), ``clearance_m``
        (null when not checked, null per sample where nothing of the cell is in reach);
        ``qd_share`` (K,) the largest joint speed as a share of its limit; the arm's joint
        limits ``q_min_deg``, ``q_max_deg`` (null: endless);
        ``speed_drops`` with their times; ``requested_speed_m_s``; ``duration_s``.
    """
    from recon import kinematics

    arm = trajectory.arm
    phases = trajectory.phases
    keep = thinned(len(trajectory.t_s), max_samples, phases)
    q = trajectory.q_rad
    frames = kinematics.joint_frames(arm, q[keep])
    joints = np.concatenate([frames[:, :, :3, 3], trajectory.tcp_m[keep][:, None, :]], axis=1)
    limit_margin = kinematics.limit_margins_rad(arm, q).min(axis=1)
    qd_share = (np.abs(trajectory.qd_rad_s) / arm.qd_max_rad_s).max(axis=1)
    clearance = None
    if clearance_m is not None and len(clearance_m) == len(q):
        # inf: nothing in the cell to be near (sent as null, as "not measured" would be).
        clearance = _finite_or_none(window_min(np.asarray(clearance_m, float), keep), 5)
    from scipy.spatial.transform import Rotation

    # The tool's axis (the TCP frame's z) at each kept sample, for the glyphs along the path.
    tool_axis = Rotation.from_rotvec(trajectory.tcp_rotvec[keep]).as_matrix()[:, :, 2]
    labels = [p.label for p in Phase]
    return {
        "robot": trajectory.robot,
        "duration_s": float(trajectory.t_s[-1] - trajectory.t_s[0]),
        "requested_speed_m_s": float(trajectory.requested_speed_m_s),
        "phases": labels,
        "t_s": _rounded(trajectory.t_s[keep], 4),
        "phase": phases[keep].astype(int).tolist(),
        "joints_m": _rounded(joints, 5),
        "tcp_m": _rounded(trajectory.tcp_m[keep], 5),
        "tool_axis": _rounded(tool_axis, 4),
        "speed_m_s": _rounded(tcp_speed_m_s(trajectory)[keep], 5),
        "q_deg": _rounded(np.degrees(q[keep]), 3),
        "qd_share": _rounded(np.maximum.reduceat(qd_share, keep), 4),
        "limit_margin_deg": _rounded(np.degrees(window_min(limit_margin, keep)), 3),
        "wrist_singularity": _rounded(window_min(kinematics.wrist_singularity(q), keep), 4),
        "elbow_singularity": _rounded(window_min(kinematics.elbow_singularity(q), keep), 4),
        "clearance_m": clearance,
        # An endless joint (the UR3's wrist 3) has no limit: null.
        "q_min_deg": _finite_or_none(np.degrees(arm.q_min_rad), 3),
        "q_max_deg": _finite_or_none(np.degrees(arm.q_max_rad), 3),
        "speed_drops": speed_drop_times(trajectory),
    }


def execution_review(
    trajectory: JointTrajectory, samples: ExecutionSamples, *, max_samples: int = DEFAULT_SAMPLES
) -> dict[str, Any]:
    """What an execution did against its plan, for the pendant.

    Parameters
    ----------
    trajectory : recon.trajectory.JointTrajectory
        The plan that ran.
    samples : service.artifacts.ExecutionSamples
        ``t_s`` (S,), ``q_planned_rad`` and ``q_actual_rad`` (S, 6) as recorded.
    max_samples : int

    Returns
    -------
    dict
        ``t_s`` (K,); ``actual_tcp_m`` (K, 3) the TCP where the arm was (base frame);
        ``off_path_m`` (K,) its distance from the whole planned path, the largest over the
        samples up to the next kept one (measured on the flange: the TCP's rigid offset
        moves both alike); ``max_off_path_m`` and where (``at_s``) over all samples.
    """
    from drivers.robot.dryrun import off_path_m
    from recon import kinematics

    arm = trajectory.arm
    actual = np.asarray(samples.q_actual_rad)
    recorded = np.all(np.isfinite(actual), axis=1)
    t = np.asarray(samples.t_s)[recorded]
    actual = actual[recorded]
    if not len(t):
        return {"t_s": [], "actual_tcp_m": [], "off_path_m": [], "max_off_path_m": None}
    actual_flange = kinematics.forward(arm, actual)
    off_path = off_path_m(arm, actual_flange, trajectory.q_rad)
    # The planned TCP's offset from the flange, in the flange's frame, carried to the actual.
    first_flange = kinematics.forward(arm, trajectory.q_rad[0])
    tcp_in_flange = np.linalg.solve(first_flange, np.r_[trajectory.tcp_m[0], 1.0])
    actual_tcp = np.einsum("kij,j->ki", actual_flange, tcp_in_flange)[:, :3]
    keep = thinned(len(t), max_samples)
    worst = int(np.argmax(off_path))
    return {
        "t_s": _rounded(t[keep], 4),
        "actual_tcp_m": _rounded(actual_tcp[keep], 5),
        "off_path_m": _rounded(np.maximum.reduceat(off_path, keep), 7),
        "max_off_path_m": float(off_path[worst]),
        "at_s": float(t[worst]),
    }


def reconstruction_difference(points_m: FloatArray, other_m: FloatArray) -> dict[str, Any]:
    """How far each point of one reconstruction lies from another's path, for an overlay.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3)
        The reconstruction drawn (tracker frame).
    other_m : ndarray of shape (G, 3)
        The one it is compared with, in order (its polyline is the reference).

    Returns
    -------
    dict
        ``points_m`` (N, 3); ``difference_m`` (N,) each point's distance from the other's path;
        ``mean_m``, ``max_m`` and ``at_index`` (where the largest is).
    """
    from recon.metrics import distance_to_curve

    difference = distance_to_curve(points_m, other_m)
    worst = int(np.argmax(difference))
    return {
        "points_m": _rounded(points_m, 7),
        "difference_m": _rounded(difference, 7),
        "mean_m": float(difference.mean()),
        "max_m": float(difference[worst]),
        "at_index": worst,
    }
