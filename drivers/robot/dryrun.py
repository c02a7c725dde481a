"""Dry runs (a trajectory executed on the simulated arm) and the report of any execution:
what it showed against its plan, measured the same way for the sim and a real arm."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from drivers.errors import RobotError
from drivers.robot.base import ExecutionRecord
from drivers.robot.clock import FakeClock
from drivers.robot.sim import SimBackend, SimConfig
from recon import kinematics
from recon.arrays import FloatArray
from recon.metrics import distance_to_curve
from recon.paths import Phase, SpeedDrop, speed_drop_lines
from recon.trajectory import JointTrajectory


@dataclass(frozen=True)
class ExecutionReport:
    """What an execution showed, on the simulated arm (a dry run) or on a real one.

    Attributes
    ----------
    robot : str
    completed : bool
    mode : {"servoj", "movepath"}
        How it ran: every sample streamed, or coarse waypoints run by the controller.
    duration_s, planned_duration_s : float
        How long the arm was driven (:func:`motion_time_s`: the recorded samples, the same
        for a simulation and a real arm) and the plan's duration.
    max_path_deviation_m : float or None
        Largest distance of the executed TCP from the planned TCP path (across the path)
        along the process phase (the path itself; all of the motion for a trajectory without
        phases); None when nothing of it was recorded.
    max_lag_m : float or None
        Largest distance between executed and planned TCP at the same instant (along it too),
        along the process phase.
    max_joint_error_rad : float or None
        Largest joint difference from the plan delayed by servoJ's lookahead.
    min_limit_margin_rad : float
        Closest approach of any joint to its position limit (planned).
    min_wrist_singularity, min_elbow_singularity : float
        Smallest |sin q5| and |sin q3| where the tool moves straight or along the path (0 at the
        singularity; a joint move may pass one harmlessly).
    requested_speed_m_s, mean_speed_m_s : float
        The path's speed: asked for, and the process phase's length over its duration.
    speed_drops : tuple of SpeedDrop
        Where the plan is slower than requested, and why.
    faults : tuple of str
    n_samples : int
        Samples recorded.
    dry_run : bool
        Whether it ran on the simulated arm.
    phase_durations_s : dict of str to float
        Planned seconds per phase.
    executed_phase_durations_s : dict of str to float
        Seconds of each phase the arm got through (:func:`executed_phase_durations_s`): the
        planned ones for a completed execution, the phases up to where it stopped otherwise.
    max_deviation_by_phase_m : dict of str to float
        Largest distance of the executed TCP from the planned TCP path, per phase recorded.
    """

    robot: str
    completed: bool
    mode: str
    duration_s: float
    planned_duration_s: float
    max_path_deviation_m: float | None
    max_lag_m: float | None
    max_joint_error_rad: float | None
    min_limit_margin_rad: float
    min_wrist_singularity: float
    min_elbow_singularity: float
    requested_speed_m_s: float
    mean_speed_m_s: float
    speed_drops: tuple[SpeedDrop, ...] = ()
    faults: tuple[str, ...] = field(default=())
    n_samples: int = 0
    dry_run: bool = True
    phase_durations_s: dict[str, float] = field(default_factory=dict)
    executed_phase_durations_s: dict[str, float] = field(default_factory=dict)
    max_deviation_by_phase_m: dict[str, float] = field(default_factory=dict)
    #: servoJ on a real arm: the longest time between two samples sent, and how many periods
    #: took over :data:`OVERRUN_FACTOR` times the controller's (None: not streamed in real time).
    max_period_s: float | None = None
    period_overruns: int | None = None

    def lines(self) -> list[str]:
        """The report as short lines for a terminal."""
        mm = 1e3
        where = f"a simulated {self.robot}" if self.dry_run else f"the {self.robot}"
        process = Phase.PROCESS.label
        # The path's figures only where the arm reached the path (a run stopped in the transit
        # has none: its deviations are in the phases' line).
        on_path = not self.phase_durations_s or process in self.executed_phase_durations_s
        has_path = process in self.phase_durations_s or not self.phase_durations_s
        speed = (
            f"mean TCP speed along the path {self.mean_speed_m_s * mm:.1f} mm/s of "
            f"{self.requested_speed_m_s * mm:.1f} requested"
            if on_path and has_path
            else "the path was not reached"
            if has_path
            else "no path: a joint move"
        )
        out = [
            f"{'dry run' if self.dry_run else 'run'} on {where} ({self.mode}): "
            + ("completed" if self.completed else "DID NOT COMPLETE"),
            f"duration {self.duration_s:.2f} s (planned {self.planned_duration_s:.2f} s); " + speed,
        ]
        if self.max_path_deviation_m is None or self.max_lag_m is None:
            if self.max_deviation_by_phase_m:
                phase, worst = max(self.max_deviation_by_phase_m.items(), key=lambda kv: kv[1])
                out.append(
                    "tracking along the path: not measured (the arm was not on it); "
                    f"elsewhere {worst * mm:.3f} mm off at most ({phase})"
                    if has_path
                    else f"tracking: {worst * mm:.3f} mm off the planned way at most ({phase})"
                )
            else:
                out.append("tracking: not measured (nothing was recorded)")
        else:
            out.append(
                f"tracking: {self.max_path_deviation_m * mm:.3f} mm off the path at most, "
                f"{self.max_lag_m * mm:.2f} mm from the planned point of the same instant at "
                "most "
                + (
                    "(servoJ's lookahead)"
                    if self.mode == "servoj"
                    else "(the controller times a movePath itself)"
                )
            )
        if self.phase_durations_s:
            out.append(
                "phases: "
                + ", ".join(
                    f"{name} {self.executed_phase_durations_s.get(name, 0.0):.2f} of "
                    f"{planned:.2f} s"
                    + (
                        f" ({self.max_deviation_by_phase_m[name] * mm:.3f} mm off)"
                        if name in self.max_deviation_by_phase_m
                        else ""
                    )
                    for name, planned in self.phase_durations_s.items()
                )
            )
        out.append(
            f"margins: joint limits {np.degrees(self.min_limit_margin_rad):.1f} deg; where the "
            f"tool moves straight, wrist |sin q5| {self.min_wrist_singularity:.2f}, elbow "
            f"|sin q3| {self.min_elbow_singularity:.2f}"
        )
        if self.max_period_s is not None:
            out.append(
                f"servoJ periods: longest {self.max_period_s * mm:.2f} ms, "
                f"{self.period_overruns} over {OVERRUN_FACTOR:g} times the controller's"
            )
        out += speed_drop_lines(self.speed_drops)
        out += [f"fault: {fault}" for fault in self.faults]
        return out


#: The name earlier versions used for a simulated execution's report.
DryRunReport = ExecutionReport


def dry_run(
    trajectory: JointTrajectory,
    *,
    config: SimConfig | None = None,
    backend: SimBackend | None = None,
    mode: str = "servoj",
    tolerance_m: float = 5e-4,
) -> ExecutionReport:
    """Execute ``trajectory`` on a simulated arm (fake clock: faster than real time).

    Parameters
    ----------
    trajectory : JointTrajectory
    config : SimConfig, optional
        Servo settings; the arm model and start pose are taken from the trajectory.
    backend : SimBackend, optional
        A prepared simulator (for injecting faults); otherwise one is made.
    mode : {"servoj", "movepath"}
        Stream every sample (servoJ), or run coarse waypoints within ``tolerance_m`` of the
        plan as the controller's own path (movePath).
    tolerance_m : float
        For ``movepath``: largest TCP deviation of the waypoints' path from the plan.
    """
    if mode not in ("servoj", "movepath"):
        raise ValueError(f"mode must be 'servoj' or 'movepath', got {mode!r}")
    if backend is None:
        base = config or SimConfig()
        settings = base.model_copy(
            update={"robot": trajectory.robot, "q_start_rad": tuple(trajectory.q_rad[0])}
        )
        backend = SimBackend(settings, clock=FakeClock())
    faults: list[str] = []
    record = None
    try:
        backend.connect()
        backend.enable()
        if mode == "servoj":
            record = backend.execute(trajectory)
        else:
            record = backend.execute_path(trajectory, tolerance_m=tolerance_m)
        if record.fault:
            faults.append(record.fault)
    except RobotError as error:
        faults.append(str(error))
        record = getattr(backend, "last_record", None)
    finally:
        backend.close()
    return execution_report(
        trajectory,
        record,
        mode=mode,
        lookahead_s=backend.config.lookahead_s,
        faults=faults,
        dry_run=True,
    )


def off_path_m(
    arm: kinematics.URModel, actual_flange: FloatArray, plan_q_rad: FloatArray
) -> FloatArray:
    """How far the arm was from its planned path at each recorded sample.

    The planned TCP may sit off the flange; the tracking error is the same rigid offset either
    way, so it is measured on the flange, against the whole planned path.

    Parameters
    ----------
    arm : recon.kinematics.URModel
    actual_flange : ndarray of shape (S, 4, 4)
        Where the flange was (forward kinematics of the recorded joints).
    plan_q_rad : ndarray of shape (M, 6)
        The plan's joints.

    Returns
    -------
    ndarray of shape (S,), metres
    """
    plan_flange = kinematics.forward(arm, plan_q_rad)[:, :3, 3]
    return distance_to_curve(actual_flange[:, :3, 3], plan_flange)


def stream_lag_s(mode: str, lookahead_s: float) -> float:
    """How far the arm runs behind the sample recorded with it: servoJ's lookahead when every
    sample is streamed; none for movePath, whose record pairs each sample with the plan's at
    the same time."""
    return lookahead_s if mode == "servoj" else 0.0


def recorded_plan_index(
    trajectory: JointTrajectory, planned_index: ArrayLike, lookahead_s: float
) -> NDArray[np.int64]:
    """Which sample of the plan the arm was at for each recorded sample.

    servoJ runs the stream a lookahead behind the sample sent with it, so the arm is at the
    plan's sample sent ``lookahead_s`` earlier: the recorded sample that many controller
    periods before (in a run slowed or paused, fewer of the plan's samples than periods). The
    one rule for the report's phases, the phase a stopped run stopped in and the phases'
    executed seconds.

    Parameters
    ----------
    trajectory : JointTrajectory
    planned_index : ndarray of shape (S,)
        The plan's sample sent with each recorded one, one per controller period, in order.
    lookahead_s : float

    Returns
    -------
    ndarray of shape (S,), int
    """
    lag = int(round(lookahead_s / trajectory.period_s))
    planned = np.asarray(planned_index, dtype=np.int64).reshape(-1)
    if lag > 0:
        # Before the first lookahead has passed, the arm is still at the plan's start.
        planned = np.concatenate([np.zeros(min(lag, len(planned)), np.int64), planned[:-lag]])
    return np.clip(planned, 0, len(trajectory) - 1)


def reached_phase(trajectory: JointTrajectory, record: ExecutionRecord, lookahead_s: float) -> str:
    """The phase the arm was in at the record's last sample (see :func:`recorded_plan_index`);
    "before moving" for an empty record."""
    if record is None or len(record) == 0:
        return "before moving"
    last = recorded_plan_index(trajectory, record.planned(), lookahead_s)[-1]
    return Phase(int(trajectory.phases[last])).label


def executed_phase_durations_s(trajectory: JointTrajectory, reached: int) -> dict[str, float]:
    """Seconds of each phase the arm got through, up to the plan's sample ``reached``: counted
    as :meth:`JointTrajectory.phase_durations_s` counts the plan's, so a completed execution
    shows its plan's figures and no phase shows more than planned."""
    phases = trajectory.phases[: reached + 1]
    out: dict[str, float] = {}
    for value in dict.fromkeys(phases.tolist()):
        out[Phase(value).label] = float(np.count_nonzero(phases == value) * trajectory.period_s)
    return out


def motion_time_s(record: ExecutionRecord | None) -> float:
    """How long the arm was driven: from the first recorded sample to the last, measured as
    the plan's duration is (its first sample to its last). The one definition of an
    execution's duration, for the simulated arm, a real one and a record recovered from a
    journal: connecting, enabling and settling are not motion; servoJ's lookahead at the end
    is (the arm still moves)."""
    if record is None or len(record) == 0:
        return 0.0
    t_s = np.asarray(record.t_s, dtype=np.float64)
    return float(t_s[-1] - t_s[0])


#: A streamed period counts as an overrun when it takes this many times the controller's: the
#: controller then repeats the last setpoint and the arm slows (or, with a watchdog, stops).
OVERRUN_FACTOR = 1.25


def execution_report(
    trajectory: JointTrajectory,
    record: ExecutionRecord | None,
    *,
    mode: str,
    lookahead_s: float,
    faults: list[str],
    dry_run: bool,
) -> ExecutionReport:
    """Measure an execution's record against its plan (the same for the sim and a real arm).

    Parameters
    ----------
    trajectory : JointTrajectory
        The plan.
    record : ExecutionRecord or None
        What was executed (None or empty: nothing moved).
    mode : {"servoj", "movepath"}
    lookahead_s : float
        servoJ's lookahead: the executed joints are compared with the plan delayed by it.
    faults : list of str
    dry_run : bool
    """
    arm = trajectory.arm
    planned_tcp = trajectory.tcp_m
    deviation = lag = joint_error = None
    completed = False
    by_phase: dict[str, float] = {}
    executed: dict[str, float] = {}
    if record is not None and len(record):
        actual_flange = kinematics.forward(arm, record.q_actual_rad)
        planned_flange = kinematics.forward(arm, record.q_planned_rad)
        off_path = off_path_m(arm, actual_flange, trajectory.q_rad)
        # Which phase each recorded sample belongs to: the arm runs the plan a lookahead
        # behind the sample sent with it.
        index = recorded_plan_index(trajectory, record.planned(), stream_lag_s(mode, lookahead_s))
        recorded_phase = trajectory.phases[index]
        for value in dict.fromkeys(trajectory.phases.tolist()):
            mine = recorded_phase == value
            if mine.any():
                by_phase[Phase(value).label] = float(off_path[mine].max())
        # What the arm got through: the whole plan once completed (its last samples are the
        # lookahead's, sent while the arm caught up).
        reached = len(trajectory) - 1 if record.completed else int(index.max())
        executed = executed_phase_durations_s(trajectory, reached)
        deviation = by_phase.get(Phase.PROCESS.label)
        # The lag grows with speed; along the path is what matters (the transit runs faster).
        on_path = recorded_phase == int(Phase.PROCESS)
        behind = np.linalg.norm(actual_flange[:, :3, 3] - planned_flange[:, :3, 3], axis=1)
        lag = float(behind[on_path].max()) if on_path.any() else None
        # servoJ follows the stream a lookahead behind: compare joints with the plan delayed so.
        delay = max(1, int(round(lookahead_s * arm.control_rate_hz)))
        joint_error = float(
            np.abs(record.q_actual_rad[delay:] - record.q_planned_rad[:-delay]).max(initial=0.0)
        )
        completed = record.completed
    q = trajectory.q_rad
    margin = float(np.min(kinematics.limit_margins_rad(arm, q)))
    # Singularities matter where the tool moves in straight lines and along the path; a joint
    # move (transit, return) may pass through one (the elbow stretched) harmlessly.
    phases = trajectory.phases
    tool_moves = ~np.isin(phases, [int(Phase.TRANSIT), int(Phase.RETURN)])
    q_tool = q[tool_moves] if tool_moves.any() else q
    # The mean speed is the path's: the process phase's length over its duration.
    process = phases == int(Phase.PROCESS)
    along = process[1:] & process[:-1]
    path_length = float(np.sum(np.linalg.norm(np.diff(planned_tcp, axis=0), axis=1)[along]))
    process_s = float(np.count_nonzero(along) * trajectory.period_s)
    max_period = overruns = None
    if not dry_run and mode == "servoj" and record is not None and len(record) > 1:
        # The samples' times are when each was sent (the streaming loop's clock).
        periods = np.diff(np.asarray(record.t_s, dtype=np.float64))
        max_period = float(periods.max())
        overruns = int(np.count_nonzero(periods > OVERRUN_FACTOR * trajectory.period_s))
    return ExecutionReport(
        robot=trajectory.robot,
        completed=completed,
        mode=mode,
        duration_s=motion_time_s(record),
        planned_duration_s=trajectory.duration_s,
        max_path_deviation_m=deviation,
        max_lag_m=lag,
        max_joint_error_rad=joint_error,
        min_limit_margin_rad=margin,
        min_wrist_singularity=float(kinematics.wrist_singularity(q_tool).min()),
        min_elbow_singularity=float(kinematics.elbow_singularity(q_tool).min()),
        requested_speed_m_s=trajectory.requested_speed_m_s,
        mean_speed_m_s=path_length / process_s if process_s > 0 else 0.0,
        speed_drops=trajectory.speed_drops,
        faults=tuple(faults),
        n_samples=0 if record is None else len(record),
        dry_run=dry_run,
        phase_durations_s=trajectory.phase_durations_s(),
        executed_phase_durations_s=executed,
        max_deviation_by_phase_m=by_phase,
        max_period_s=max_period,
        period_overruns=overruns,
    )
