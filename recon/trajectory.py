"""The time-parameterized joint trajectory (:class:`JointTrajectory`) the arm runs: samples,
phases, its checks and its summaries.

Units, frames and quaternion order as docs/architecture.md's conventions say; the arrays held
here are read-only (:func:`recon.arrays.frozen_array`).
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from recon import kinematics
from recon.arrays import FloatArray
from recon.kinematics import DHCalibration, URModel
from recon.paths import Phase, SpeedDrop
from recon.sample_check import tcp_speeds_m_s

#: The per-sample arrays of a :class:`JointTrajectory` (what is stored of one, with its phases).
SAMPLE_FIELDS = ("t_s", "q_rad", "qd_rad_s", "qdd_rad_s2", "tcp_m", "tcp_rotvec", "arc_length_m")


@dataclass(frozen=True)
class JointTrajectory:
    """A timed joint trajectory, sampled at the controller rate.

    Attributes
    ----------
    robot : str
        The UR model it was planned for.
    t_s : ndarray of shape (M,), seconds
    q_rad, qd_rad_s, qdd_rad_s2 : ndarray of shape (M, 6)
    tcp_m : ndarray of shape (M, 3)
        Planned TCP position at each sample (base frame).
    tcp_rotvec : ndarray of shape (M, 3)
        Planned TCP orientation as a rotation vector (UR's pose convention).
    arc_length_m : ndarray of shape (M,)
        Path parameter at each sample: how far the TCP has travelled since the start.
    requested_speed_m_s : float
        The speed asked for along the process path.
    speed_drops : tuple of SpeedDrop
        Where the process path is slower than requested (metres of process path).
    phase : ndarray of shape (M,), int8, or None
        :class:`Phase` of each sample; None for a trajectory that is the process path alone
        (one read from a file that does not say).
    calibration : recon.kinematics.DHCalibration or None
        The arm's own kinematics calibration it was planned with (None: UR's nominal model);
        :attr:`arm` is the model with it.
    """

    robot: str
    t_s: FloatArray
    q_rad: FloatArray
    qd_rad_s: FloatArray
    qdd_rad_s2: FloatArray
    tcp_m: FloatArray
    tcp_rotvec: FloatArray
    arc_length_m: FloatArray
    requested_speed_m_s: float
    speed_drops: tuple[SpeedDrop, ...] = ()
    phase: NDArray[np.int8] | None = None
    calibration: DHCalibration | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        n = len(self.t_s)
        for name in SAMPLE_FIELDS:
            arr = np.array(getattr(self, name), dtype=np.float64)
            if len(arr) != n:
                raise ValueError(f"{name} has {len(arr)} rows for {n} samples")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} has NaN or infinite values")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        if self.phase is not None:
            phase = np.array(self.phase, dtype=np.int8)
            if phase.shape != (n,):
                raise ValueError(f"phase has shape {phase.shape} for {n} samples")
            if not np.isin(phase, [int(p) for p in Phase]).all():
                raise ValueError("phase holds values that name no Phase")
            phase.setflags(write=False)
            object.__setattr__(self, "phase", phase)

    def __len__(self) -> int:
        return len(self.t_s)

    @functools.cached_property
    def arm(self) -> URModel:
        """The arm model it was planned with: its robot, with its calibration if it had one.

        Made once per trajectory: the calibration's plausibility check solves 500 poses."""

        arm = kinematics.model(self.robot)
        if self.calibration is None:
            return arm
        return kinematics.with_calibration(arm, self.calibration)

    @property
    def phases(self) -> NDArray[np.int8]:
        """:class:`Phase` per sample (all PROCESS when the trajectory does not say)."""
        if self.phase is None:
            return np.full(len(self), int(Phase.PROCESS), dtype=np.int8)
        return self.phase

    def of_phase(self, phase: Phase) -> JointTrajectory:
        """The samples of one phase, as a trajectory of their own (times from 0).

        Raises
        ------
        ValueError
            The trajectory has no sample of that phase, or several runs of it (a trace in
            pieces: see :meth:`runs` and :meth:`part`).
        """
        rows = [r for p, r in self.runs() if p is phase]
        if not rows:
            raise ValueError(f"the trajectory has no {phase.label} phase")
        if len(rows) > 1:
            raise ValueError(
                f"the trajectory has {len(rows)} {phase.label} runs (a trace in pieces); "
                "take them one by one with runs() and part()"
            )
        return self.part(rows[0])

    def part(self, rows: slice) -> JointTrajectory:
        """Consecutive samples as a trajectory of their own (times and arc length from 0)."""
        first = rows.start or 0
        process = bool(np.all(self.phases[rows] == int(Phase.PROCESS)))
        return JointTrajectory(
            robot=self.robot,
            t_s=self.t_s[rows] - self.t_s[first],
            q_rad=self.q_rad[rows],
            qd_rad_s=self.qd_rad_s[rows],
            qdd_rad_s2=self.qdd_rad_s2[rows],
            tcp_m=self.tcp_m[rows],
            tcp_rotvec=self.tcp_rotvec[rows],
            arc_length_m=self.arc_length_m[rows] - self.arc_length_m[first],
            requested_speed_m_s=self.requested_speed_m_s,
            speed_drops=self.speed_drops if process else (),
            phase=self.phases[rows],
            calibration=self.calibration,
        )

    def runs(self) -> list[tuple[Phase, slice]]:
        """The phases in the order they run, each contiguous run with its samples: a motion over
        a trace in two pieces has two approach, process and retract runs."""
        phases = self.phases
        starts = np.r_[0, np.flatnonzero(np.diff(phases)) + 1, len(phases)]
        return [
            (Phase(int(phases[a])), slice(int(a), int(b))) for a, b in itertools.pairwise(starts)
        ]

    def phase_durations_s(self) -> dict[str, float]:
        """Seconds spent in each phase present, in the order they run."""
        phases, dt = self.phases, self.period_s
        out: dict[str, float] = {}
        for value in dict.fromkeys(phases.tolist()):
            out[Phase(value).label] = float(np.count_nonzero(phases == value) * dt)
        return out

    def phase_max_tcp_speed_m_s(self) -> dict[str, float]:
        """The fastest TCP speed (m/s) of each phase present, between consecutive samples (a
        period belongs to the phase of its later sample), in the order they run."""
        if len(self) < 2:
            return {Phase(v).label: 0.0 for v in dict.fromkeys(self.phases.tolist())}
        # The real-arm gate's own measure of the TCP's speed, so that the two agree.

        speed = tcp_speeds_m_s(self.arm, self.q_rad, tcp_m=self.tcp_m, rate_hz=1.0 / self.period_s)
        later = self.phases[1:]
        out: dict[str, float] = {}
        for value in dict.fromkeys(self.phases.tolist()):
            mine = later == value
            out[Phase(value).label] = float(speed[mine].max()) if mine.any() else 0.0
        return out

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1]) if len(self.t_s) else 0.0

    @property
    def period_s(self) -> float:
        return float(self.t_s[1] - self.t_s[0]) if len(self.t_s) > 1 else 0.0
