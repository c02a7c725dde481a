"""From a reconstructed path to a timed joint trajectory: orientation, IK, timing, report.

The scan enters planning only through the tool axis: :func:`normals_from_scan` looks the normals
up in the scan model the reconstruction built, at the transform it used (``Reconstruction
.scan_model`` and ``.T_scan_tracker``), so planning neither registers nor rebuilds anything.
Where only a stored path and the scan are at hand (the command line), :func:`scan_model_for_path`
builds the model around the path at a known transform, again without registering.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from recon import kinematics, motion
from recon.arrays import FloatArray, piece_labels, piece_slices
from recon.collision import Cell, CollisionReport, ContactZone, ObstacleKind, check_motion
from recon.errors import CollisionError, InfeasibleTrajectoryError
from recon.inputs import Scan
from recon.orient import ScanNormals, fill_along_path, scan_normals, tool_path
from recon.paths import JointPath, Phase, ToolPath, speed_drop_lines
from recon.plan_params import PlanParams
from recon.recon_params import ReconParams
from recon.scan_model import ScanModel, build_scan_model
from recon.timing import Limits, limits_for, time_parameterize
from recon.trajectory import JointTrajectory
from recon.transforms import (
    apply_transform,
    check_rigid,
    invert_transform,
    rotate_vectors,
    rotation_angle_deg,
    translation_m,
)

#: Where the tool axis came from, in the report's words.
TOOL_AXIS_WORDS = {
    "scan": "from the scan",
    "pen": "from the pen",
    "fixed": "fixed (along the approach, no scan normals or pen orientations)",
}


@dataclass(frozen=True)
class Plan:
    """A planned motion with everything that led to it.

    Attributes
    ----------
    tool : ToolPath
        The process path's TCP poses (base frame).
    joints : JointPath
        Its joints, one IK branch throughout.
    trajectory : JointTrajectory
        The whole motion (transit, approach, process, retract, return), labelled per sample.
    params : PlanParams
    T_scan_tracker : ndarray of shape (4, 4), or None
        The transform the scan's normals were looked up with, when the tool axis came from the
        scan; None otherwise.
    start_q_rad : ndarray of shape (6,)
        Where the motion starts.
    start_from : str
        Where ``start_q_rad`` came from ("given" or "home").
    configuration : Configuration
        The configuration of the branch kept, every field named.
    approach_m : float
        The approach height used (more than asked when the transit had to come in higher).
    collision : CollisionReport or None
        The check of the whole motion against the cell (None: no cell given).
    n_pieces : int
        Process runs: the trace's pieces, with a retract, a transit and an approach between two.
    """

    tool: ToolPath
    joints: JointPath
    trajectory: JointTrajectory
    params: PlanParams
    start_q_rad: FloatArray
    configuration: kinematics.Configuration
    T_scan_tracker: FloatArray | None = None
    start_from: str = "given"
    approach_m: float = 0.0
    collision: CollisionReport | None = None
    n_pieces: int = 1

    def report_lines(self) -> list[str]:
        """The feasibility report for a terminal."""
        traj, joints, mm = self.trajectory, self.joints, 1e3
        length = float(self.tool.arc_length_m[-1])
        process = traj.phase_durations_s().get(Phase.PROCESS.label, traj.duration_s)
        lines = [
            f"{self.params.robot}: {length * mm:.0f} mm of path in {process:.2f} s "
            f"({len(traj)} samples at {1 / traj.period_s:.0f} Hz in all), requested "
            f"{traj.requested_speed_m_s * mm:.0f} mm/s, mean {length / process * mm:.1f}"
            + (
                f"; in {self.n_pieces} pieces, the arm lifts between them"
                if self.n_pieces > 1
                else ""
            ),
            "phases: "
            + ", ".join(f"{name} {t:.2f} s" for name, t in traj.phase_durations_s().items())
            + f" ({traj.duration_s:.2f} s in all; approach {self.approach_m * mm:.0f} mm)",
            f"starts from {self.start_from} "
            + (
                "(joints not given)"
                if self.start_q_rad is None
                else f"[{', '.join(f'{np.degrees(v):.1f}' for v in self.start_q_rad)}] deg"
            ),
            f"tool axis {TOOL_AXIS_WORDS.get(self.tool.source, self.tool.source)}; "
            + ("" if self.configuration is None else f"{self.configuration.words()} ")
            + f"(IK branch {joints.branch})",
            f"kinematics: {traj.arm.kinematics_words}",
            f"margins: joint limits {np.degrees(joints.limit_margin_rad.min()):.1f} deg, wrist "
            f"|sin q5| {joints.wrist_singularity.min():.2f}, elbow |sin q3| "
            f"{joints.elbow_singularity.min():.2f}, shoulder "
            f"{joints.shoulder_margin_m.min() * mm:.0f} mm",
        ]
        if self.collision is not None:
            lines.append(f"tool checked as {_tool_words(self.params)}")
            lines += self.collision.lines()
        if self.T_scan_tracker is not None:
            lines.append(
                f"scan normals at T_scan_tracker: "
                f"{np.linalg.norm(translation_m(self.T_scan_tracker)) * mm:.2f} mm and "
                f"{rotation_angle_deg(self.T_scan_tracker):.2f} deg from the tracker frame"
            )
        return lines + speed_drop_lines(traj.speed_drops)


#: Approach heights tried, as multiples of the one asked for, when the transit or the approach
#: would hit something: coming in higher clears a workpiece the direct joint move sweeps through.
APPROACH_LIFTS = (1.0, 2.0, 4.0, 8.0)
#: Never lift the approach beyond this.
MAX_APPROACH_M = 0.5


#: The longest process a plan may take at its requested speed: the samples (500 Hz) of a longer
#: one are a burden to store, check and stream (3,600 s: 1.8 million samples, 0.3 GB of CSV)
#: and no demonstrated path needs it.
MAX_PROCESS_DURATION_S = 3600.0


def _check_duration(points_m: FloatArray, pieces: list[slice], speed_m_s: float) -> None:
    """Refuse, before any work, a path that would take longer than the bound at its speed."""
    length_m = sum(
        float(np.linalg.norm(np.diff(points_m[rows], axis=0), axis=1).sum()) for rows in pieces
    )
    duration_s = length_m / speed_m_s
    if duration_s > MAX_PROCESS_DURATION_S:
        raise ValueError(
            f"the path ({length_m:.3f} m) would take {duration_s:.0f} s at speed_m_s "
            f"{speed_m_s:g}, more than the {MAX_PROCESS_DURATION_S:.0f} s a plan may take: "
            f"raise speed_m_s to at least {length_m / MAX_PROCESS_DURATION_S:.4f} m/s, or plan "
            "the path in parts"
        )


def plan_path(
    points_tracker_m: FloatArray,
    *,
    params: PlanParams,
    T_base_tracker: FloatArray | None = None,
    normals: ScanNormals | None = None,
    pen_xyzw: FloatArray | None = None,
    cell: Cell | None = None,
    piece: NDArray[np.int64] | None = None,
    start_from: str | None = None,
    calibration: kinematics.DHCalibration | None = None,
) -> Plan:
    """Plan the whole motion along a path given in the tracker frame.

    Parameters
    ----------
    points_tracker_m : ndarray of shape (N, 3)
    params : PlanParams
    T_base_tracker : ndarray of shape (4, 4), optional
        Where the tracker frame is in the robot base frame (identity: the same frame).
    normals : ScanNormals, optional
        Outward surface directions at the points, tracker frame (see
        :func:`normals_from_scan`); its ``T_scan_tracker`` is recorded in the plan when the
        tool axis comes from it.
    pen_xyzw : ndarray of shape (N, 4), optional
        Pen orientations at the points, tracker frame.
    cell : recon.collision.Cell, optional
        What the arm must not touch (mounting plane, keep-out boxes, the scan); without it no
        collision check is made.
    piece : ndarray of shape (N,), int, optional
        The trace's pieces (``Reconstruction.piece``): each is a process run of its own, and
        between two the arm retracts, transits and approaches again. None: one piece.
    start_from : str, optional
        Where ``params.start_q_rad`` came from, for the report ("arm": read from the arm at
        planning time); default "given", or "home" without start joints.
    calibration : recon.kinematics.DHCalibration, optional
        The arm's own kinematics calibration (its controller's): the joints then put the flange
        where the controller will, not millimetres off as the nominal model would. None: UR's
        nominal model. The trajectory carries it.

    Raises
    ------
    ValueError
        Inconsistent inputs (the requested orientation source is missing, bad shapes), or a
        calibration that is not this arm type's.
    InfeasibleTrajectoryError
        The arm cannot follow the path (the message names the waypoint and why), no solution
        has the configuration asked for, or the motion collides (:class:`CollisionError`).
    """
    arm = kinematics.model(params.robot)
    if calibration is not None:
        arm = kinematics.with_calibration(arm, calibration)
    T = np.eye(4) if T_base_tracker is None else check_rigid(T_base_tracker, name="T_base_tracker")
    points = np.asarray(points_tracker_m, dtype=np.float64)
    pieces = piece_slices(piece_labels(piece, len(points)))
    _check_duration(points, pieces, params.speed_m_s)
    source = _orientation_source(params, normals, pen_xyzw)
    tools = [
        _process_tool_path(points[rows], T, params, source, _rows(normals, rows), pen_xyzw, rows)
        for rows in pieces
    ]
    T_flange_tcp = params.T_flange_tcp
    if start_from is None or params.start_q_rad is None:
        start_from = "given" if params.start_q_rad is not None else "home"
    q_start = np.asarray(params.start_q_rad or kinematics.HOME_Q_RAD, dtype=np.float64)
    flanges = [tool.poses() @ invert_transform(T_flange_tcp) for tool in tools]
    allowed = _configuration_branches(arm, flanges[0][0], params.configuration)
    limits = limits_for(
        arm,
        params.speed_m_s,
        velocity_scale=params.velocity_scale,
        acceleration_scale=params.acceleration_scale,
    )
    # A configuration whose motion collides is not the end when the request leaves a choice
    # (elbow "any", ...): the next best configuration is tried (elbow up was clear where the
    # branch chosen first, elbow down, collided and the plan was refused).
    candidates = list(range(8)) if allowed is None else list(allowed)
    first_refusal: InfeasibleTrajectoryError | None = None
    while candidates:
        try:
            return _plan_in(
                arm, tools, flanges, pieces, tuple(candidates), q_start, start_from, limits,
                params, cell, normals, source,
            )  # fmt: skip
        except _BranchRefused as refused:
            first_refusal = first_refusal or refused.error
            candidates.remove(refused.branch)
        except InfeasibleTrajectoryError:
            if first_refusal is None:
                raise
            break  # no other configuration follows the path: the first refusal is the reason
    if first_refusal is None:  # no branch allowed at all
        raise InfeasibleTrajectoryError("no IK configuration was allowed: check the request")
    raise first_refusal


class _BranchRefused(Exception):
    """The motion in IK branch ``branch`` collides or comes too near a joint limit (``error``
    says where)."""

    def __init__(self, branch: int, error: InfeasibleTrajectoryError) -> None:
        super().__init__(str(error))
        self.branch, self.error = branch, error


def _plan_in(
    arm: kinematics.URModel,
    tools: list[ToolPath],
    flanges: list[FloatArray],
    pieces: list[slice],
    allowed: tuple[int, ...],
    q_start: FloatArray,
    start_from: str,
    limits: Limits,
    params: PlanParams,
    cell: Cell | None,
    normals: ScanNormals | None,
    source: str,
) -> Plan:
    """The plan in the best of the ``allowed`` IK branches (see :func:`plan_path`).

    Raises
    ------
    _BranchRefused
        Its motion collides whichever way onto the path is taken, or passes nearer a joint
        limit than ``params.joint_margin_deg``.
    InfeasibleTrajectoryError
        No allowed branch follows the path.
    """
    T_flange_tcp = params.T_flange_tcp

    # One configuration for every piece: the first piece's branch is kept for the others.
    joints_per_piece, processes, q_near = [], [], q_start
    for k, (tool, flange) in enumerate(zip(tools, flanges, strict=True)):
        try:
            joints = kinematics.follow_path(
                arm, flange, q_near_rad=q_near, allowed_branches=allowed
            )
        except InfeasibleTrajectoryError as error:
            if len(tools) == 1:
                raise
            raise InfeasibleTrajectoryError(f"piece {k} of the path: {error}") from error
        allowed, q_near = (joints.branch,), joints.q_rad[-1]
        joints_per_piece.append(joints)
        processes.append(
            time_parameterize(
                arm,
                joints,
                tool,
                limits,
                T_flange_tcp=T_flange_tcp,
                point_speed_max_m_s=params.point_speed_max_m_s,
            )
        )
    tool, joints = _joined_tools(tools), _joined_joints(joints_per_piece)
    offsets_m = tool.arc_length_m[[rows.start for rows in pieces]]
    heights = [params.approach_m * lift for lift in APPROACH_LIFTS]
    heights = [h for h in heights if h <= max(MAX_APPROACH_M, params.approach_m)]
    report = None
    # The ways onto the path, in order of preference: the direct joint move, the base's turn
    # first, and both from higher up.
    for height in heights:
        for base_first in (False, True):
            try:
                trajectory = _whole_motion(
                    arm,
                    processes,
                    offsets_m,
                    joints.branch,
                    q_start,
                    height,
                    params,
                    base_first=base_first,
                )
            except InfeasibleTrajectoryError:
                if report is None:
                    raise  # the approach asked for itself cannot be followed
                break  # lifted higher the approach leaves the arm's reach
            if cell is not None:
                report = check_cell(arm, trajectory, cell, params)
            if report is None or report.first_collision is None:
                _require_joint_margin(arm, trajectory, joints.branch, params.joint_margin_deg)
                return Plan(
                    tool=tool,
                    joints=joints,
                    trajectory=trajectory,
                    params=params,
                    T_scan_tracker=normals.T_scan_tracker
                    if source == "scan" and normals is not None
                    else None,
                    start_q_rad=q_start,
                    start_from=start_from,
                    configuration=kinematics.configuration_of(arm, joints.q_rad[0]),
                    approach_m=height,
                    collision=report,
                    n_pieces=len(pieces),
                )
            if report.first_collision.phase not in (Phase.TRANSIT, Phase.APPROACH):
                # Another way onto the path cannot help.
                raise _BranchRefused(joints.branch, _collision_error(report))
    raise _BranchRefused(joints.branch, _collision_error(report))


def _require_joint_margin(
    arm: kinematics.URModel, trajectory: JointTrajectory, branch: int, margin_deg: float
) -> None:
    """Refuse (for this branch) a motion that passes nearer a joint's limit than the margin.

    Raises
    ------
    _BranchRefused
    """
    q = trajectory.q_rad
    to_limit = kinematics.limit_margins_rad(arm, q)  # (M, 6), inf: no limit
    i, j = np.unravel_index(int(np.argmin(to_limit)), to_limit.shape)
    if to_limit[i, j] < np.radians(margin_deg):
        raise _BranchRefused(
            branch,
            InfeasibleTrajectoryError(
                f"joint {j + 1} comes {np.degrees(to_limit[i, j]):.1f} deg from its limit "
                f"during {Phase(int(trajectory.phases[i])).label} at {trajectory.t_s[i]:.2f} s "
                f"(sample {i}), within the {margin_deg:g} deg margin (joint_margin_deg): "
                "change the tool orientation, the configuration or the start pose"
            ),
        )


def _configuration_branches(
    arm: kinematics.URModel, T_flange: FloatArray, want: kinematics.Configuration
) -> tuple[int, ...] | None:
    """The IK branches of the configuration asked for at the path's first pose (None: let
    :func:`kinematics.follow_path` name why the pose is out of reach in any configuration).

    Raises
    ------
    InfeasibleTrajectoryError
        The pose is reachable, but not in that configuration.
    """
    branches = kinematics.branches_for(arm, T_flange, want)
    if not branches and kinematics.branches_for(
        arm, T_flange, kinematics.Configuration(elbow=None)
    ):
        x, y, z = T_flange[:3, 3]
        raise InfeasibleTrajectoryError(
            f"no solution of the {arm.name} in the configuration asked for ({want.words()}) "
            f"reaches the path's first point at ({x:.3f}, {y:.3f}, {z:.3f}) m: choose another "
            "configuration (shoulder, elbow, wrist) or move the workpiece"
        )
    return tuple(branches) or None


def _rows(normals: ScanNormals | None, rows: slice) -> ScanNormals | None:
    if normals is None:
        return None
    return replace(normals, normals=normals.normals[rows], known=normals.known[rows])


def _joined_tools(tools: list[ToolPath]) -> ToolPath:
    """The pieces' tool paths end to end; arc length runs on along the traced path only."""
    if len(tools) == 1:
        return tools[0]
    offsets = np.cumsum([0.0] + [t.arc_length_m[-1] for t in tools[:-1]])
    return ToolPath(
        points_m=np.concatenate([t.points_m for t in tools]),
        orientations_xyzw=np.concatenate([t.orientations_xyzw for t in tools]),
        arc_length_m=np.concatenate(
            [t.arc_length_m + o for t, o in zip(tools, offsets, strict=True)]
        ),
        source=tools[0].source,
    )


def _joined_joints(paths: list[JointPath]) -> JointPath:
    if len(paths) == 1:
        return paths[0]
    return JointPath(
        q_rad=np.concatenate([p.q_rad for p in paths]),
        branch=paths[0].branch,
        **{
            name: np.concatenate([getattr(p, name) for p in paths])
            for name in (
                "limit_margin_rad",
                "wrist_singularity",
                "elbow_singularity",
                "shoulder_margin_m",
            )
        },
    )


def _tool_words(params: PlanParams) -> str:
    """The tool's collision shape in words, millimetres (for the plan's report)."""
    if not params.tool_spheres_m:
        return f"a capsule of radius {params.tool_radius_m * 1e3:.1f} mm from the flange to the TCP"
    spheres = np.reshape(np.asarray(params.tool_spheres_m), (-1, 4)) * 1e3
    listed = "; ".join(", ".join(f"{v:.1f}" for v in sphere) for sphere in spheres)
    return f"{len(spheres)} sphere(s), X, Y, Z, R in the flange frame (mm): {listed}"


def check_cell(
    arm: kinematics.URModel, trajectory: JointTrajectory, cell: Cell, params: PlanParams
) -> CollisionReport:
    """The collision check of a whole motion: the arm's links and the tool (``params.tool``:
    its spheres, or a capsule of ``tool_radius_m`` from the flange to the TCP) against the
    cell; the tool may touch the workpiece along the process path only, and where a motion
    starts with a retract (a move off the workpiece from where a stopped run left the tool),
    at its first pose.

    The contact zone comes from the samples themselves (their phases and kinematics), never
    from a stored verdict. As along a plan's own retracts, the touch at the start is allowed
    only within the first contact radius of TCP travel, and only on what lies no higher than
    the band above the tip (see :func:`recon.collision.check_motion`).
    """
    phases = trajectory.phases
    touching = phases == int(Phase.PROCESS)
    if len(phases) > 1 and phases[0] == int(Phase.RETRACT):
        # The first period (a piece needs two points; the arm leaves rest, so microns long).
        touching[:2] = True
    run = np.cumsum(np.r_[True, np.diff(touching.astype(np.int8)) != 0])  # 1, 2, ... per run
    zone = None  # no process samples: the tool may touch the workpiece nowhere
    if touching.any():
        zone = ContactZone.of_process(
            arm,
            trajectory.q_rad[touching],
            params.T_flange_tcp,
            piece=np.unique(run[touching], return_inverse=True)[1],
        )
    return check_motion(
        arm,
        trajectory.q_rad,
        trajectory.phases,
        cell,
        T_flange_tcp=params.T_flange_tcp,
        tool=params.tool,
        margin_m=params.clearance_m,
        contact_zone=zone,
        t_s=trajectory.t_s,
    )


def _collision_error(report: CollisionReport | None) -> CollisionError:
    first = None if report is None else report.first_collision
    assert first is not None  # called for a motion found to collide
    return CollisionError(
        f"the motion collides: {first.describe()}. Change the tool orientation (lead, tilt), "
        "the configuration, the start pose or the cell (keep-out boxes, cell planes), or move the "
        "workpiece",
        detail={
            "phase": Phase(int(first.phase)).label,
            "t_s": first.t_s,
            "sample": first.sample,
            "link": first.link,
            "obstacle": first.obstacle,
            "point_m": [float(v) for v in first.point_m],
            "clearance_m": float(first.clearance_m),
            "margin_m": float(first.margin_m),
        },
    )


def _orientation_source(
    params: PlanParams, normals: ScanNormals | None, pen_xyzw: FloatArray | None
) -> str:
    """Where the tool axis comes from: the one asked for, or for "auto" the best there is."""
    if params.orientation != "auto":
        return params.orientation
    if normals is not None and normals.known.any():
        return "scan"
    return "pen" if pen_xyzw is not None else "fixed"


def _process_tool_path(
    points_tracker_m: FloatArray,
    T_base_tracker: FloatArray,
    params: PlanParams,
    source: str,
    normals: ScanNormals | None,
    pen_xyzw: FloatArray | None,
    rows: slice,
) -> ToolPath:
    """One piece's TCP poses in the base frame (``pen_xyzw`` is the whole path's, cut to
    ``rows`` here)."""
    R = T_base_tracker[:3, :3]
    points = apply_transform(T_base_tracker, points_tracker_m)
    kwargs: dict[str, FloatArray] = {}
    if source == "scan":
        if normals is None or not normals.known.any():
            raise ValueError(
                "orientation 'scan' needs a scan with surfaces or edges along the path"
                + ("" if rows.start == 0 and normals is not None else " (along every piece)")
            )
        kwargs["normals"] = fill_along_path(normals.normals, normals.known) @ R.T
    elif source == "pen":
        if pen_xyzw is None:
            raise ValueError("orientation 'pen' needs a trace with pen orientations (qx..qw)")
        from scipy.spatial.transform import Rotation

        kwargs["pen_xyzw"] = (
            Rotation.from_matrix(R) * Rotation.from_quat(np.asarray(pen_xyzw)[rows])
        ).as_quat()
    return tool_path(
        points,
        approach=params.approach_direction,
        lead_deg=params.lead_deg,
        tilt_deg=params.tilt_deg,
        smooth_m=params.smooth_m,
        heading=params.heading,
        **kwargs,
    )


def _whole_motion(
    arm: kinematics.URModel,
    processes: list[JointTrajectory],
    offsets_m: FloatArray,
    branch: int,
    q_start: FloatArray,
    approach_m: float,
    params: PlanParams,
    *,
    base_first: bool = False,
) -> JointTrajectory:
    """Transit, approach, the timed process path, retract, for each piece in turn, and (if
    asked) the return.

    ``offsets_m``: where each piece starts along the traced path (its speed drops are placed
    there). ``base_first``: each transit turns the base alone first (the arm keeps its shape,
    and its heights), then moves the other joints: a joint move that turns the base a long way
    while it unfolds the arm may sweep low through the cell.
    """
    joint_move = _joint_move(params)
    phases: list[motion.PhaseSamples] = []
    q_here = q_start
    for process, offset_m in zip(processes, offsets_m, strict=True):
        approach, retract = _approach_and_retract(arm, process, branch, approach_m, params)
        drops = tuple(
            replace(d, start_m=d.start_m + offset_m, end_m=d.end_m + offset_m)
            for d in process.speed_drops
        )
        phases += _transit(arm, q_here, approach.q_rad[0], base_first, joint_move)
        phases += [
            approach,
            replace(motion.PhaseSamples.of(Phase.PROCESS, process), speed_drops=drops),
            retract,
        ]
        q_here = retract.q_rad[-1]
    if params.return_to_start:
        back = motion.joint_move(arm, q_here, q_start, **joint_move)
        phases.append(replace(back, phase=Phase.RETURN))
    return motion.assemble(
        arm, phases, T_flange_tcp=params.T_flange_tcp, requested_speed_m_s=params.speed_m_s
    )


def _approach_and_retract(
    arm: kinematics.URModel,
    process: JointTrajectory,
    branch: int,
    approach_m: float,
    params: PlanParams,
) -> tuple[motion.PhaseSamples, motion.PhaseSamples]:
    """The straight moves along the tool axis onto a process run's first pose and off its last."""
    ends = kinematics.forward(arm, process.q_rad[[0, -1]]) @ params.T_flange_tcp
    line = _lift_line(params, branch)
    approach = motion.line_move(
        arm,
        motion.tool_line(motion.lifted(ends[0], approach_m), ends[0]),
        q_end_rad=process.q_rad[0],
        q_start_rad=None,
        phase=Phase.APPROACH,
        **line,
    )
    retract = motion.line_move(
        arm,
        motion.tool_line(ends[1], motion.lifted(ends[1], approach_m)),
        q_end_rad=None,
        q_start_rad=process.q_rad[-1],
        phase=Phase.RETRACT,
        **line,
    )
    return approach, retract


def _lift_line(params: PlanParams, branch: int) -> dict[str, Any]:
    """How every straight lift along the tool axis moves (approach, retract, the move off the
    workpiece): ``motion.line_move``'s settings but the line, its join and its phase."""
    return {
        "branch": branch,
        "T_flange_tcp": params.T_flange_tcp,
        "speed_m_s": params.approach_speed_m_s,
        "velocity_scale": params.velocity_scale,
        "acceleration_scale": params.acceleration_scale,
        "point_speed_max_m_s": params.point_speed_max_m_s,
    }


def _joint_move(params: PlanParams) -> dict[str, Any]:
    """How every joint move goes (a plan's transits and returns, a move to a plan's start):
    ``motion.joint_move``'s settings but its ends."""
    return {
        "speed_scale": params.transit_speed_scale,
        "acceleration_scale": params.transit_acceleration_scale,
        "tcp_speed_max_m_s": params.transit_tcp_speed_m_s,
        "T_flange_tcp": params.T_flange_tcp,
    }


def _transit(
    arm: kinematics.URModel,
    q_start: FloatArray,
    q_goal: FloatArray,
    base_first: bool,
    joint_move: dict[str, Any],
) -> list[motion.PhaseSamples]:
    """The joint moves from the start to the approach pose (one, or the base's turn first)."""
    if not base_first or abs(q_goal[0] - q_start[0]) < 1e-6:
        return [motion.joint_move(arm, q_start, q_goal, **joint_move)]
    turned = np.array(q_start, dtype=np.float64)
    turned[0] = q_goal[0]
    return [
        motion.joint_move(arm, q_start, turned, **joint_move),
        motion.joint_move(arm, turned, q_goal, **joint_move),
    ]


def approach_in(T_base_tracker: FloatArray | None, approach_base: ArrayLike) -> FloatArray:
    """The approach direction expressed in the tracker frame."""
    R = np.eye(3) if T_base_tracker is None else np.asarray(T_base_tracker)[:3, :3]
    return R.T @ np.asarray(approach_base, dtype=np.float64)


def scan_model_for_path(
    scan: Scan,
    points_tracker_m: FloatArray,
    *,
    T_scan_tracker: FloatArray | None = None,
    recon_params: ReconParams | None = None,
) -> ScanModel:
    """The scan model around a stored path at a known transform, without registering.

    For callers that have a path and the scan but not the reconstruction's own model (the
    command line reads a reconstruction CSV). The model is built around the path itself, so it
    differs a little from the reconstruction's (built around the raw trace), not in substance.

    Parameters
    ----------
    scan : Scan
        Scan frame.
    points_tracker_m : ndarray of shape (N, 3), metres
        The path, tracker frame.
    T_scan_tracker : ndarray of shape (4, 4), optional
        The transform to use (a calibration, or the one the reconstruction used); identity if
        not given: path and scan already in one frame.
    recon_params : ReconParams, optional
        Crop, voxel and curvature settings (defaults if not given).

    Returns
    -------
    ScanModel
        Scan frame.

    Raises
    ------
    ValueError
        ``T_scan_tracker`` is not a rigid transform.
    NoOverlapError
        The scan has too few points near the path at that transform.
    """
    T = np.eye(4) if T_scan_tracker is None else check_rigid(T_scan_tracker, name="T_scan_tracker")
    points = apply_transform(T, np.asarray(points_tracker_m, dtype=np.float64))
    return build_scan_model(scan, points, recon_params or ReconParams())


def normals_from_scan(
    points_tracker_m: FloatArray,
    mode: np.ndarray,
    scan_model: ScanModel,
    *,
    T_scan_tracker: FloatArray,
    approach_tracker: FloatArray,
    recon_params: ReconParams | None = None,
) -> ScanNormals:
    """Outward surface directions of the scan at a reconstructed path's points (tracker frame).

    Nothing is registered or recomputed: the path is mapped into the scan frame by
    ``T_scan_tracker`` and looked up in ``scan_model``. Edge points get the bisector of the two
    faces, surface points the local normal, turned towards ``approach_tracker``.

    Parameters
    ----------
    points_tracker_m : ndarray of shape (N, 3), metres
        The reconstructed path, tracker frame.
    mode : ndarray of shape (N,), int8
        :class:`recon.results.PointMode` of each point (``Reconstruction.mode``).
    scan_model : ScanModel
        Scan frame: ``Reconstruction.scan_model``, a stored one
        (:meth:`ScanModel.from_arrays`) or :func:`scan_model_for_path`.
    T_scan_tracker : ndarray of shape (4, 4)
        The transform the model is used with (``Reconstruction.T_scan_tracker``).
    approach_tracker : ndarray of shape (3,)
        Where the tool comes from, tracker frame (see :func:`approach_in`).
    recon_params : ReconParams, optional
        ``radius_m`` is the radius of the surface-normal fits (defaults if not given).

    Returns
    -------
    ScanNormals
        Tracker frame, with ``T_scan_tracker`` recorded.

    Raises
    ------
    ValueError
        ``T_scan_tracker`` is not a rigid transform, or ``mode`` does not match the points.
    """
    params = recon_params or ReconParams()
    T = check_rigid(T_scan_tracker, name="T_scan_tracker")
    points = np.asarray(points_tracker_m, dtype=np.float64)
    mode = np.asarray(mode)
    if mode.shape != (len(points),):
        raise ValueError(f"mode has shape {mode.shape} for {len(points)} points")
    found = scan_normals(
        apply_transform(T, points),
        scan_model,
        mode=mode,
        approach=rotate_vectors(T, np.asarray(approach_tracker, dtype=np.float64)[None])[0],
        radius_m=params.radius_m,
    )
    # Back to the tracker frame: rotate by R^T (row vectors times R).
    return ScanNormals(
        normals=rotate_vectors(invert_transform(T), found.normals),
        known=found.known,
        T_scan_tracker=T.copy(),
    )


# -- a move to a plan's start ----------------------------------------------------------------------


@dataclass(frozen=True)
class MovePlan:
    """A joint move of its own from where the arm is to where a plan starts, checked against
    the joint limits at every sample and the cell (not against the planning margin to the
    limits: the move starts where the arm stands), to be dry-run and approved before it runs.

    Attributes
    ----------
    trajectory : JointTrajectory
        One transit (two when the base turns first), at rest at both ends; after a retract when
        the arm stands with the tool on the workpiece.
    params : PlanParams
        The target plan's (its tool, payload, transit speeds and clearance).
    start_q_rad, goal_q_rad : ndarray of shape (6,)
        Where the arm is, and the target plan's first sample.
    base_first : bool
        Whether the base turns alone first (the direct move collided).
    collision : CollisionReport or None
        The check against the cell (None: no cell given).
    retract_m : float
        How far the tool first moves straight back along its own axis, off the workpiece it
        stands on (metres; 0: no retract, the joint move starts at once).
    via_q_rad : ndarray of shape (V, 6), or None
        Where the move stops at rest on the way, in order (one of :func:`plan_move`'s ``ways``:
        the direct ways collided); None: straight to the start.
    """

    trajectory: JointTrajectory
    params: PlanParams
    start_q_rad: FloatArray
    goal_q_rad: FloatArray
    base_first: bool = False
    collision: CollisionReport | None = None
    retract_m: float = 0.0
    via_q_rad: FloatArray | None = None

    def margins(self) -> dict[str, float]:
        """The smallest joint-limit margin (rad), wrist and elbow |sin| and shoulder margin (m)
        over every sample.

        Returns
        -------
        dict of str to float
            ``min_limit_margin_rad``, ``min_wrist_singularity``, ``min_elbow_singularity``,
            ``min_shoulder_margin_m``, as a plan's summary names them.
        """
        arm, q = self.trajectory.arm, self.trajectory.q_rad
        return {
            "min_limit_margin_rad": float(kinematics.limit_margins_rad(arm, q).min()),
            "min_wrist_singularity": float(kinematics.wrist_singularity(q).min()),
            "min_elbow_singularity": float(kinematics.elbow_singularity(q).min()),
            "min_shoulder_margin_m": float(
                kinematics.shoulder_margin_m(arm, kinematics.forward(arm, q)).min()
            ),
        }

    def report_lines(self) -> list[str]:
        """The move's report for a terminal and the pendant, one line per entry."""
        traj = self.trajectory
        moved = np.degrees(np.abs(self.goal_q_rad - self.start_q_rad))
        tcp = traj.phase_max_tcp_speed_m_s().get(Phase.TRANSIT.label, 0.0)
        lines = [
            f"{traj.robot}: {'a move' if self.retract_m > 0 else 'a joint move'} of "
            f"{traj.duration_s:.2f} s to the plan's start "
            f"({len(traj)} samples at {1 / traj.period_s:.0f} Hz), the largest joint turn "
            f"{moved.max():.1f} deg (joint {int(np.argmax(moved)) + 1}), fastest TCP "
            f"{tcp * 1e3:.0f} mm/s" + ("; the base turns alone first" if self.base_first else ""),
        ]
        if self.via_q_rad is not None:
            last = self.via_q_rad[-1]
            lines.append(
                f"by way of {len(self.via_q_rad)} stop(s) at rest, the last at "
                f"[{', '.join(f'{v:.1f}' for v in np.degrees(last))}] deg: the direct joint "
                "move collided"
            )
        if self.retract_m > 0:
            lines.append(
                f"first straight off the workpiece: {self.retract_m * 1e3:.0f} mm back along the "
                f"tool's axis at {self.params.approach_speed_m_s * 1e3:.0f} mm/s (the tool stands "
                "on it: a joint move from there would drag it)"
            )
        lines += [
            f"from [{', '.join(f'{v:.1f}' for v in np.degrees(self.start_q_rad))}] deg",
            f"to [{', '.join(f'{v:.1f}' for v in np.degrees(self.goal_q_rad))}] deg",
            f"kinematics: {traj.arm.kinematics_words}",
        ]
        if self.collision is not None:
            lines.append(f"tool checked as {_tool_words(self.params)}")
            lines += self.collision.lines()
        return lines


#: Joint angles given to a move must be within this of the arm's limits (rad): a reading of
#: the arm is never outside them by more than its noise.
MOVE_LIMIT_TOLERANCE_RAD = 1e-6


def plan_move(
    q_from_rad: FloatArray,
    q_to_rad: FloatArray,
    *,
    params: PlanParams,
    cell: Cell | None = None,
    calibration: kinematics.DHCalibration | None = None,
    ways: Sequence[ArrayLike] = (),
) -> MovePlan:
    """A joint move (UR's ``movej``: every joint on one trapezoidal profile) from ``q_from_rad``
    to ``q_to_rad`` at the plan's transit speeds, checked against ``cell``; if the direct move
    collides, the base turns alone first, as a plan's transit does; if that collides too, each
    of ``ways`` in turn: joint moves through its configurations, at rest at each, then on to the
    start as before.

    :func:`ways_back` gives the ways for a run stopped on a plan's path: by the plan's approach
    start (from there the plan's own transit leads back), and back along the path lifted off
    the workpiece. A direct joint move from the middle of a path may swing the wrist past the
    arm's own links: 38 of 104 stops along the cylinder demo's path were refused before the
    ways were tried (tests/recon/test_move_to_start.py).

    Where the arm stands with the tool on the workpiece (a run stopped in its process or
    approach: the joint move's first period touches the scan with the tool), the move first
    retracts straight back along the tool's axis by the plan's ``approach_m``, at its approach
    speed, as a plan's own retract leaves the path; the joint move starts from there.

    Parameters
    ----------
    q_from_rad, q_to_rad : array-like of shape (6,)
        Where the arm is and where the target plan starts (rad).
    params : PlanParams
        The target plan's parameters: robot, tool, transit speed scales and TCP speed, clearance.
    cell : recon.collision.Cell, optional
        What the arm must not touch (the tool touches nothing on a move).
    calibration : recon.kinematics.DHCalibration, optional
        The arm's own kinematics calibration (default: UR's nominal model).
    ways : sequence of array-like of shape (V, 6)
        Configurations the move may stop at on the way, one array per way, tried in order after
        the direct ways (:func:`ways_back`).

    Returns
    -------
    MovePlan

    Raises
    ------
    ValueError
        Joints that are not six finite numbers within the arm's limits.
    CollisionError
        Both ways of moving collide (the message names where and with what).
    """
    arm = kinematics.model(params.robot)
    if calibration is not None:
        arm = kinematics.with_calibration(arm, calibration)
    q_from = _move_joints(arm, "the arm's joints", q_from_rad)
    q_to = _move_joints(arm, "the plan's start", q_to_rad)
    ways_checked = [_move_way(arm, w, way) for w, way in enumerate(ways)]
    joint_move = _joint_move(params)
    # Every way, in the order tried: (stop on the way or None, the base turns first on the way
    # to the start).
    routes: list[tuple[FloatArray | None, bool]] = [(None, False), (None, True)]
    routes += [
        (way, base_first) for way in ways_checked if len(way) for base_first in (False, True)
    ]

    def legs(q_start: FloatArray, way: FloatArray | None, base_first: bool) -> list[Any]:
        if way is None:
            return _transit(arm, q_start, q_to, base_first, joint_move)
        stops = np.vstack([q_start[None], way])
        return [
            *(motion.joint_move(arm, a, b, **joint_move) for a, b in itertools.pairwise(stops)),
            *_transit(arm, way[-1], q_to, base_first, joint_move),
        ]

    report = None
    for via, base_first in routes:
        trajectory = motion.assemble(
            arm,
            legs(q_from, via, base_first),
            T_flange_tcp=params.T_flange_tcp,
            requested_speed_m_s=params.transit_tcp_speed_m_s,
        )
        if cell is not None:
            report = check_cell(arm, trajectory, cell, params)
        if report is None or report.first_collision is None:
            return MovePlan(trajectory, params, q_from, q_to, base_first, report, via_q_rad=via)
        if _tool_stands_on_scan(report):
            break  # no joint move leaves from here: the tool first moves off the workpiece
    if not _tool_stands_on_scan(report):
        raise _collision_error(report)
    assert cell is not None  # the tool stands on the scan: the cell has one
    retract = _retract_from(arm, q_from, params)
    first_report = None
    for via, base_first in routes:
        trajectory = motion.assemble(
            arm,
            [retract, *legs(retract.q_rad[-1], via, base_first)],
            T_flange_tcp=params.T_flange_tcp,
            requested_speed_m_s=params.transit_tcp_speed_m_s,
        )
        report = check_cell(arm, trajectory, cell, params)
        first_report = first_report or report
        if report.first_collision is None:
            return MovePlan(
                trajectory,
                params,
                q_from,
                q_to,
                base_first,
                report,
                retract_m=params.approach_m,
                via_q_rad=via,
            )
    # The direct way's collision: what the operator would see moving the arm straight there.
    raise _collision_error(first_report)


#: A way back along a stopped plan's path stops at rest each time a joint has turned this much
#: since the last stop: a joint move between two poses this close stays near the lifted path.
WAY_BACK_TURN_RAD = float(np.radians(10.0))
#: The arm stands on a plan's path when its joints are within this of one of the path's samples
#: (a stop on the path decelerates along it).
ON_PATH_TOLERANCE_RAD = float(np.radians(2.0))


def ways_back(
    target: JointTrajectory,
    q_from_rad: ArrayLike,
    params: PlanParams,
    *,
    calibration: kinematics.DHCalibration | None = None,
) -> list[FloatArray]:
    """Ways from where a run of ``target`` stopped back to its start, for :func:`plan_move`.

    Only where a stopped run leaves the arm: within :data:`ON_PATH_TOLERANCE_RAD` of one of
    the target's approach, process or retract samples (none from anywhere else):

    1. By the target's first approach start: from there the target's own transit (checked
       with the target) leads to its start.
    2. When the arm stands on the target's path (its joints within
       :data:`ON_PATH_TOLERANCE_RAD` of a process sample): back along the path to the start of
       its piece, lifted off the workpiece by the approach distance along the tool's axis, at
       rest every :data:`WAY_BACK_TURN_RAD` of joint turn, in the arm's IK branch; then the
       first approach start.

    Parameters
    ----------
    target : JointTrajectory
        The plan the move goes to the start of.
    q_from_rad : array-like of shape (6,)
        Where the arm stands.
    params : PlanParams
        The target's (its tool and approach distance).
    calibration : recon.kinematics.DHCalibration, optional

    Returns
    -------
    list of ndarray of shape (V, 6)
        The ways, in the order to try them (none when the target has no approach).
    """
    arm = kinematics.model(params.robot)
    if calibration is not None:
        arm = kinematics.with_calibration(arm, calibration)
    q_from = np.asarray(q_from_rad, dtype=np.float64).reshape(-1)
    phases, q = target.phases, target.q_rad
    approach = np.flatnonzero(phases == int(Phase.APPROACH))
    if len(approach) == 0 or q_from.shape != (6,):
        return []
    # Only from the target's own way (where a stopped run leaves the arm): from anywhere else
    # (a jog) a detour by the workpiece is no way back, and the direct moves' verdict stands.
    moving = np.flatnonzero(
        np.isin(phases, [int(Phase.APPROACH), int(Phase.PROCESS), int(Phase.RETRACT)])
    )
    if np.abs(q[moving] - q_from).max(axis=1).min() > ON_PATH_TOLERANCE_RAD:
        return []
    first_approach = q[approach[0]]
    ways = [first_approach[None].copy()]
    process = np.flatnonzero(phases == int(Phase.PROCESS))
    if len(process) == 0:
        return ways
    gap = np.abs(q[process] - q_from).max(axis=1)
    if gap.min() > ON_PATH_TOLERANCE_RAD:
        return ways
    stop = int(process[np.argmin(gap)])
    start = stop
    while start > 0 and phases[start - 1] == int(Phase.PROCESS):
        start -= 1
    picked, last = [], q[stop]
    for i in range(stop - 1, start - 1, -1):
        if np.abs(q[i] - last).max() >= WAY_BACK_TURN_RAD:
            picked.append(i)
            last = q[i]
    if start != stop and (not picked or picked[-1] != start):
        picked.append(start)
    if not picked:
        return ways
    T_tcp = kinematics.forward(arm, q[picked]) @ params.T_flange_tcp
    lifted = np.array([motion.lifted(T, params.approach_m) for T in T_tcp])
    try:
        joints = kinematics.follow_path(
            arm,
            lifted @ invert_transform(params.T_flange_tcp),
            q_near_rad=q_from,
            allowed_branches=(_branch_at(arm, q_from),),
        )
    except InfeasibleTrajectoryError:
        return ways  # the lifted path leaves the arm's reach or branch: the first way only
    back = joints.q_rad
    if np.abs(back[-1] - first_approach).max() > 1e-6:
        back = np.vstack([back, first_approach])
    return [*ways, back]


def _move_joints(arm: kinematics.URModel, name: str, q_rad: ArrayLike) -> FloatArray:
    """Six finite joint angles within the arm's limits, or a ValueError naming ``name``."""
    q = np.asarray(q_rad, dtype=np.float64).reshape(-1)
    if q.shape != (6,) or not np.all(np.isfinite(q)):
        raise ValueError(f"{name} must be six finite joint angles (rad), got {q}")
    if np.any(kinematics.limit_margins_rad(arm, q[None]) < -MOVE_LIMIT_TOLERANCE_RAD):
        raise ValueError(
            f"{name} [{', '.join(f'{v:.1f}' for v in np.degrees(q))}] deg are outside the "
            f"{arm.name}'s joint limits"
        )
    return q


def _move_way(arm: kinematics.URModel, index: int, way: ArrayLike) -> FloatArray:
    """One of :func:`plan_move`'s ways as checked configurations (V, 6)."""
    rows = np.asarray(way, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1:] != (6,):
        raise ValueError(f"way {index + 1} must be configurations of six joints, shape (V, 6)")
    return np.array(
        [_move_joints(arm, f"way {index + 1}'s stop {i + 1}", q) for i, q in enumerate(rows)]
    ).reshape(-1, 6)


def _tool_stands_on_scan(report: CollisionReport | None) -> bool:
    """Whether a joint move's check failed in its first period, the tool against the scan: the
    arm stands with the tool on (or within the margin of) the workpiece."""
    first = None if report is None else report.first_collision
    return (
        first is not None
        and first.sample == 0
        and first.link == "tool"
        and (first.kind == ObstacleKind.SCAN)
    )


def _retract_from(
    arm: kinematics.URModel, q_rad: FloatArray, params: PlanParams
) -> motion.PhaseSamples:
    """The straight line from the arm's TCP ``params.approach_m`` back along the tool's axis,
    in the IK branch the arm stands in.

    Raises
    ------
    CollisionError
        The arm cannot follow the line (a joint limit or singularity on the way): the tool
        stays on the workpiece, and the operator frees it by hand.
    """
    T_tcp = kinematics.forward(arm, q_rad[None])[0] @ params.T_flange_tcp
    try:
        return motion.line_move(
            arm,
            motion.tool_line(T_tcp, motion.lifted(T_tcp, params.approach_m)),
            q_end_rad=None,
            q_start_rad=q_rad,
            phase=Phase.RETRACT,
            **_lift_line(params, _branch_at(arm, q_rad)),
        )
    except InfeasibleTrajectoryError as error:
        raise CollisionError(
            "the tool stands on the workpiece and cannot be moved straight off it along its "
            f"axis ({error}): jog it clear at the UR pendant (freedrive or the Move tab), then "
            "move to the start again"
        ) from None


def _branch_at(arm: kinematics.URModel, q_rad: FloatArray) -> int:
    """The IK branch (see :class:`recon.kinematics.IKSolutions`) whose solution at the arm's
    own flange pose is the arm's joints (each joint compared modulo a turn)."""
    solutions = kinematics.inverse(arm, kinematics.forward(arm, q_rad[None]))
    turned = np.angle(np.exp(1j * (solutions.q_rad[0] - q_rad)))  # (8, 6), in (-pi, pi]
    distance = np.where(solutions.valid[0], np.abs(turned).max(axis=1), np.inf)
    return int(np.argmin(distance))
