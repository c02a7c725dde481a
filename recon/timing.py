"""Time-parametrisation of a joint path within a UR arm's limits (toppra behind our own function).

The path parameter is the TCP's arc length in metres, so the TCP speed is the path speed. toppra
bounds joint velocities and accelerations; the TCP speed cap is expressed as a seventh path
coordinate equal to the arc length itself, whose "velocity" is the path speed, with the requested
speed as its velocity limit (and no acceleration limit). ``ParametrizeConstAccel`` turns toppra's
grid solution into a trajectory; the default spline parametrizer overshoots acceleration limits by
several percent. The result is sampled at the controller rate and every sample is checked against
the limits; if a check fails the grid is refined and the work repeated, and what still fails is an
error, never a silently clipped trajectory.

toppra's Python support may end: only this module imports it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from recon.arrays import FloatArray
from recon.errors import InfeasibleTrajectoryError
from recon.kinematics import SPEED_POINT_NAMES, URModel, forward, speed_points_m
from recon.paths import JointPath, SpeedDrop, ToolPath
from recon.toppra_import import import_toppra
from recon.trajectory import JointTrajectory
from recon.transforms import pose_from_transform

#: Samples may exceed a limit by this fraction (the parametrizer's own rounding).
LIMIT_TOLERANCE = 1e-3
#: A stretch is a speed drop when the TCP is slower than this fraction of the request.
DROP_FRACTION = 0.95
#: toppra grid points per metre of path on the first attempt (doubled on failure). Constant-
#: acceleration segments keep the limits at grid points only; in between the excess shrinks with
#: the spacing (measured on a 0.32 m path: 1.43x the limit at 100 points, 1.04x at 1000, 1.004x at
#: 3000; the spline parametrizer stayed at 1.09x whatever the grid).
GRID_PER_M = 2000.0
#: Acceleration limits are planned at this fraction, so that what happens between grid points
#: stays within the full limits the samples are checked against.
ACCELERATION_HEADROOM = 0.95
#: Knot spacing of the least-squares joint spline handed to toppra. Interpolating the IK
#: solutions of millimetre-spaced waypoints exactly turns micro-radians of noise into huge joint
#: accelerations between toppra's grid points (seen: joint 6 at 180-200 % of its limit).
KNOT_SPACING_M = 0.005


@dataclass(frozen=True)
class Limits:
    """The limits a trajectory is planned within.

    Attributes
    ----------
    qd_max_rad_s, qdd_max_rad_s2 : ndarray of shape (6,)
    speed_m_s : float
        Requested (and largest) TCP speed.
    """

    qd_max_rad_s: FloatArray
    qdd_max_rad_s2: FloatArray
    speed_m_s: float


def limits_for(
    arm: URModel, speed_m_s: float, *, velocity_scale: float = 1.0, acceleration_scale: float = 1.0
) -> Limits:
    """The arm's limits, scaled down if asked, with a TCP speed request.

    Raises
    ------
    ValueError
        A speed that is not positive or above the arm's planning cap, or a scale outside (0, 1].
    """
    if not (0 < speed_m_s <= arm.tcp_speed_max_m_s):
        raise ValueError(
            f"speed_m_s must be in (0, {arm.tcp_speed_max_m_s}] m/s for the {arm.name}, "
            f"got {speed_m_s}"
        )
    for name, scale in (
        ("velocity_scale", velocity_scale),
        ("acceleration_scale", acceleration_scale),
    ):
        if not (0 < scale <= 1):
            raise ValueError(f"{name} must be in (0, 1], got {scale}")
    return Limits(
        qd_max_rad_s=arm.qd_max_rad_s * velocity_scale,
        qdd_max_rad_s2=arm.qdd_max_rad_s2 * acceleration_scale,
        speed_m_s=float(speed_m_s),
    )


def time_parameterize(
    arm: URModel,
    joints: JointPath,
    tool: ToolPath,
    limits: Limits,
    *,
    T_flange_tcp: FloatArray | None = None,
    rate_hz: float | None = None,
    point_speed_max_m_s: float | None = None,
) -> JointTrajectory:
    """The fastest trajectory along ``joints`` within ``limits``, sampled at the controller rate.

    Parameters
    ----------
    arm : URModel
    joints : JointPath
        Joint angles at the tool path's waypoints.
    tool : ToolPath
        The TCP path (its arc length is the path parameter).
    limits : Limits
    T_flange_tcp : ndarray of shape (4, 4), optional
        The tool's TCP relative to the flange, for the planned TCP poses.
    rate_hz : float, optional
        Sample rate; default the arm's controller rate.
    point_speed_max_m_s : float, optional
        The largest speed of the elbow, the wrists and the flange
        (:func:`recon.kinematics.speed_points_m`; the TCP keeps ``limits.speed_m_s``): the
        path speed is held below it divided by how fast those points move per metre of TCP
        path, a bound that varies along the path (a tool turning about its tip moves the
        flange faster than the tip).

    Returns
    -------
    JointTrajectory
        Starts and ends at rest.

    Raises
    ------
    InfeasibleTrajectoryError
        No parametrisation exists within the limits, or the samples still break them after
        refining the grid.
    """
    toppra = import_toppra()
    toppra.setup_logging("WARNING")
    rate = float(rate_hz or arm.control_rate_hz)
    arc = np.asarray(tool.arc_length_m, dtype=np.float64)
    keep = np.concatenate(([True], np.diff(arc) > 1e-9))
    s, q = arc[keep], joints.q_rad[keep]
    if len(s) < 2:
        raise InfeasibleTrajectoryError("the path has no length to move along")
    knots_s, knots_q = smooth_joint_path(s, q, knot_spacing_m=KNOT_SPACING_M)
    path = toppra.SplineInterpolator(knots_s, np.column_stack([knots_q, knots_s]))
    vlim = np.vstack(
        [
            np.column_stack([-limits.qd_max_rad_s, limits.qd_max_rad_s]),
            [[-limits.speed_m_s, limits.speed_m_s]],
        ]
    )
    big = 1e6  # the arc-length coordinate has no acceleration limit
    planned_acc = ACCELERATION_HEADROOM * limits.qdd_max_rad_s2
    alim = np.vstack([np.column_stack([-planned_acc, planned_acc]), [[-big, big]]])
    velocity = toppra.constraint.JointVelocityConstraint(vlim)
    point_bound = None
    if point_speed_max_m_s is not None:
        point_bound = PointSpeedBound.along(
            arm, path, s[-1], limits.speed_m_s, point_speed_max_m_s, T_flange_tcp
        )
        velocity = point_bound.constraint(vlim)
    constraints = [velocity, toppra.constraint.JointAccelerationConstraint(alim)]
    n_grid = int(max(50, GRID_PER_M * s[-1]))
    failure: str | None = "toppra found no feasible parametrisation"
    for _ in range(3):
        grid = np.linspace(0.0, s[-1], n_grid)
        instance = toppra.algorithm.TOPPRA(
            constraints, path, gridpoints=grid, parametrizer="ParametrizeConstAccel"
        )
        if instance.compute_trajectory(0.0, 0.0) is None:
            break
        data = instance.problem_data
        samples = _sample(path, ConstAccelTiming(data.gridpoints, data.sd_vec), rate)
        failure = _check(samples, limits)
        if failure is None:
            return _assemble(arm, samples, limits, joints, tool, T_flange_tcp, point_bound)
        n_grid *= 2
    raise InfeasibleTrajectoryError(
        f"no trajectory within the {arm.name}'s limits at {limits.speed_m_s} m/s: {failure}. "
        "Lower the speed, smooth the tool orientation or move the path away from singularities"
    )


#: Spacing (m of TCP path) at which the arm's points' speed per metre of path is sampled for
#: their varying bound, and the margin kept below the cap (the samples' finite differences and
#: the interpolation between these stations).
POINT_SPEED_STATION_M = 0.001
POINT_SPEED_MARGIN = 0.95
#: Most stations on one path (a longer path gets them farther apart): the forward kinematics
#: of 20k configurations takes about 30 ms and 9 MB.
MAX_POINT_SPEED_STATIONS = 20_000


@dataclass(frozen=True)
class PointSpeedBound:
    """The path speed (TCP, m/s) at which no point of
    :func:`recon.kinematics.speed_points_m` but the TCP moves faster than a cap, station by
    station along the path.

    Attributes
    ----------
    stations_m : ndarray of shape (S,)
        Path positions (m of TCP path).
    bound_m_s : ndarray of shape (S,)
        The largest path speed there (at most the requested one).
    binding : ndarray of shape (S,), int
        Which point sets it (an index into :data:`recon.kinematics.SPEED_POINT_NAMES`).
    cap_m_s : float
    """

    stations_m: FloatArray
    bound_m_s: FloatArray
    binding: np.ndarray
    cap_m_s: float

    @classmethod
    def along(
        cls,
        arm: URModel,
        path: Any,
        length_m: float,
        speed_m_s: float,
        cap_m_s: float,
        T_flange_tcp: FloatArray | None,
    ) -> PointSpeedBound:
        if not cap_m_s > 0:
            raise ValueError(f"point_speed_max_m_s must be positive, got {cap_m_s}")
        T = np.eye(4) if T_flange_tcp is None else np.asarray(T_flange_tcp, dtype=np.float64)
        n = min(
            max(3, int(np.ceil(length_m / POINT_SPEED_STATION_M)) + 1), MAX_POINT_SPEED_STATIONS
        )
        stations = np.linspace(0.0, length_m, n)
        points = speed_points_m(arm, path(stations)[:, :6], T)[:, :-1]  # (S, 5, 3): not the TCP
        chord = np.linalg.norm(np.diff(points, axis=0), axis=-1) / np.diff(stations)[:, None]
        # A station takes the larger of the chords on its two sides (the bound holds across).
        per_m = np.maximum(np.vstack([chord, chord[-1:]]), np.vstack([chord[:1], chord]))
        worst = per_m.max(axis=1)
        bound = np.minimum(speed_m_s, POINT_SPEED_MARGIN * cap_m_s / np.maximum(worst, 1e-9))
        return cls(stations, bound, per_m.argmax(axis=1), float(cap_m_s))

    def at(self, s_m: float) -> tuple[float, int]:
        """The bound at path position ``s_m`` (the lower of the two stations around it) and
        the point that sets it."""
        bound, binding = self.along_grid(np.array([s_m], dtype=np.float64))
        return float(bound[0]), int(binding[0])

    def along_grid(self, s_m: FloatArray) -> tuple[FloatArray, NDArray[np.int64]]:
        """:meth:`at` for many positions at once.

        Parameters
        ----------
        s_m : ndarray of shape (N,)

        Returns
        -------
        bound_m_s : ndarray of shape (N,)
        binding : ndarray of shape (N,), int
        """
        last = len(self.stations_m) - 1
        i = np.clip(np.searchsorted(self.stations_m, s_m), 0, last)
        before = np.maximum(i - 1, 0)
        j = np.where(self.bound_m_s[i] <= self.bound_m_s[before], i, before)
        return self.bound_m_s[j], np.asarray(self.binding[j], dtype=np.int64)

    def velocity_limits(self, vlim: FloatArray, s_m: FloatArray) -> FloatArray:
        """``vlim`` at each of ``s_m`` with the arc-length coordinate's bound lowered to this one.

        Parameters
        ----------
        vlim : ndarray of shape (D, 2)
            Lower and upper velocity bounds; the last row is the arc-length coordinate's.
        s_m : ndarray of shape (N,)

        Returns
        -------
        ndarray of shape (N, D, 2)
        """
        speed = self.along_grid(s_m)[0]
        limits = np.repeat(np.asarray(vlim, dtype=np.float64)[None], len(speed), axis=0)
        limits[:, -1, 0] = -speed
        limits[:, -1, 1] = speed
        return limits

    def constraint(self, vlim: FloatArray) -> Any:
        """toppra's velocity constraint: ``vlim`` with the arc-length coordinate's bound
        lowered to this one.

        toppra asks a varying constraint for its limits one gridpoint at a time (a Python call
        each: 0.35 s for the 20k gridpoints of a 10 m path); this one computes them for the
        whole grid at once and answers toppra's calls from that table (0.02 s), with the same
        numbers (the plans are the same bit for bit, tests/recon/test_motion_planning.py).
        """
        varying: Any = import_toppra().constraint.JointVelocityConstraintVarying
        bound = self
        on_grid: dict[float, FloatArray] = {}  # the current grid's limits, by path position

        def limits_at(s_m: float) -> FloatArray:
            row = on_grid.get(s_m)
            return row if row is not None else bound.velocity_limits(vlim, np.array([s_m]))[0]

        class GridVelocityConstraint(varying):  # type: ignore[misc]
            def compute_constraint_params(self, path: Any, gridpoints: FloatArray) -> Any:
                grid = np.asarray(gridpoints, dtype=np.float64)
                on_grid.clear()
                on_grid.update(zip(grid.tolist(), bound.velocity_limits(vlim, grid), strict=True))
                return super().compute_constraint_params(path, gridpoints)

        return GridVelocityConstraint(limits_at)


def smooth_joint_path(
    s_m: FloatArray, q_rad: FloatArray, *, knot_spacing_m: float
) -> tuple[FloatArray, FloatArray]:
    """A least-squares cubic spline through joint waypoints, evaluated at its knots.

    Parameters
    ----------
    s_m : ndarray of shape (N,)
        Increasing path parameter (arc length).
    q_rad : ndarray of shape (N, 6)
    knot_spacing_m : float

    Returns
    -------
    knots_s : ndarray of shape (K,)
    knots_q : ndarray of shape (K, 6)
        The spline at its knots: a cubic spline through these follows the least-squares one.
    """
    from scipy.interpolate import make_lsq_spline

    length = float(s_m[-1] - s_m[0])
    n_inner = int(length / knot_spacing_m) - 1
    if n_inner < 1 or len(s_m) < n_inner + 8:
        return s_m, q_rad  # too short to smooth: interpolate as given
    inner = np.linspace(s_m[0], s_m[-1], n_inner + 2)[1:-1]
    knots = np.concatenate(([s_m[0]] * 4, inner, [s_m[-1]] * 4))
    spline = make_lsq_spline(s_m, q_rad, knots, k=3)
    at = np.concatenate(([s_m[0]], inner, [s_m[-1]]))
    return at, spline(at)


@dataclass(frozen=True)
class ConstAccelTiming:
    """The path position against time of toppra's ``ParametrizeConstAccel``, vectorised.

    toppra's parametrizer evaluates its samples in a Python loop (about 1 s for the 75k samples
    of a 10 m path at 500 Hz, three times over for positions, velocities and accelerations);
    these are the same formulas on whole arrays, in the same order of operations, so the
    samples are the same numbers (tested against toppra's own evaluation).

    Attributes
    ----------
    s : ndarray of shape (G,)
        Grid points (path position).
    sd : ndarray of shape (G,)
        Path velocity at the grid points (toppra's ``sd_vec``).
    """

    s: FloatArray
    sd: FloatArray

    @property
    def t_s(self) -> FloatArray:
        """Time at each grid point, shape (G,): constant acceleration between them."""
        step = 2.0 * np.diff(self.s) / (self.sd[:-1] + self.sd[1:])
        return np.concatenate(([0.0], np.cumsum(step)))

    @property
    def sdd(self) -> FloatArray:
        """Path acceleration on each grid interval, shape (G - 1,)."""
        x = self.sd**2
        return 0.5 * (x[1:] - x[:-1]) / np.diff(self.s)

    def __call__(self, t_s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Path position, velocity and acceleration at times ``t_s`` (shape (T,) each)."""
        grid_t, sdd = self.t_s, self.sdd
        index = np.searchsorted(grid_t, t_s, side="right") - 1
        index = np.minimum(index, len(sdd) - 1)  # the end itself: the last interval
        dt = t_s - grid_t[index]
        u, v0 = sdd[index], self.sd[index]
        return self.s[index] + dt * v0 + 0.5 * dt**2 * u, v0 + dt * u, u


def _sample(path: Any, timing: ConstAccelTiming, rate_hz: float) -> dict[str, FloatArray]:
    """Samples on the controller's grid (servoJ streams at a fixed period); the last one, at or
    just after the end, holds the final pose at rest.

    Parameters
    ----------
    path : toppra.SplineInterpolator
        Joint angles and arc length against the path position.
    timing : ConstAccelTiming
    rate_hz : float
    """
    duration = float(timing.t_s[-1])
    dt = 1.0 / rate_hz
    t = np.arange(int(np.ceil(duration / dt - 1e-9)) + 1) * dt
    s, sd, sdd = timing(np.minimum(t, duration))
    x, dx, ddx = path(s), path(s, 1), path(s, 2)
    xd = dx * sd[:, None]
    xdd = ddx * sd[:, None] ** 2 + dx * sdd[:, None]
    xd[t > duration], xdd[t > duration] = 0.0, 0.0
    return {"t": t, "x": x, "xd": xd, "xdd": xdd}


def _check(samples: dict[str, FloatArray], limits: Limits) -> str | None:
    """None if every sample keeps every limit, else what broke first."""
    qd, qdd, sd = samples["xd"][:, :6], samples["xdd"][:, :6], samples["xd"][:, 6]
    tol = 1.0 + LIMIT_TOLERANCE
    over = np.abs(qd) / limits.qd_max_rad_s
    if over.max() > tol:
        i, j = np.unravel_index(np.argmax(over), over.shape)
        return (
            f"joint {j + 1} speed reaches {over[i, j] * 100:.1f} % of its limit at "
            f"t={samples['t'][i]:.3f} s"
        )
    over = np.abs(qdd) / limits.qdd_max_rad_s2
    if over.max() > tol:
        i, j = np.unravel_index(np.argmax(over), over.shape)
        return (
            f"joint {j + 1} acceleration reaches {over[i, j] * 100:.1f} % of its limit at "
            f"t={samples['t'][i]:.3f} s"
        )
    if np.abs(sd).max() > limits.speed_m_s * tol:
        return f"the TCP speed reaches {np.abs(sd).max():.4f} m/s"
    return None


def _assemble(
    arm: URModel,
    samples: dict[str, FloatArray],
    limits: Limits,
    joints: JointPath,
    tool: ToolPath,
    T_flange_tcp: FloatArray | None,
    point_bound: PointSpeedBound | None = None,
) -> JointTrajectory:
    q = samples["x"][:, :6]
    flange = forward(arm, q)
    tcp = flange if T_flange_tcp is None else flange @ np.asarray(T_flange_tcp)
    tcp_pose = pose_from_transform(tcp)
    arc = samples["x"][:, 6]
    speed = samples["xd"][:, 6]
    return JointTrajectory(
        robot=arm.name,
        t_s=samples["t"],
        q_rad=q,
        qd_rad_s=samples["xd"][:, :6],
        qdd_rad_s2=samples["xdd"][:, :6],
        tcp_m=tcp_pose[:, :3],
        tcp_rotvec=tcp_pose[:, 3:],
        arc_length_m=arc,
        requested_speed_m_s=limits.speed_m_s,
        speed_drops=tuple(_speed_drops(arc, speed, joints, tool, limits, point_bound)),
        calibration=arm.calibration,
    )


def _speed_drops(
    arc: FloatArray,
    speed: FloatArray,
    joints: JointPath,
    tool: ToolPath,
    limits: Limits,
    point_bound: PointSpeedBound | None = None,
) -> list[SpeedDrop]:
    """Stretches where the TCP is slower than requested, with the limit that binds there.

    The ramps from rest to the first speed peak and from the last peak back to rest are not
    drops. Inside, the binding limit is read from the path's joint rates dq/ds at the slowest
    point: a joint whose speed limit allows no more than the achieved path speed is the cause;
    otherwise it is acceleration (a tight curve or a quick turn of the tool); near a singularity
    that is named instead, since it is what makes the joint rates large.
    """
    target = DROP_FRACTION * limits.speed_m_s
    rising = np.diff(speed) > 0
    first_peak = int(np.argmin(rising)) if not rising.all() else len(speed) - 1
    falling = np.diff(speed) < 0
    last_peak = len(speed) - 1 - int(np.argmin(falling[::-1])) if not falling.all() else 0
    slow = speed < target
    slow[: first_peak + 1] = False
    slow[last_peak:] = False
    if speed.max() < target and first_peak < last_peak:
        slow[first_peak : last_peak + 1] = True  # never reaches the request: all of it
    if not np.any(slow):
        return []
    drops = []
    edges = np.flatnonzero(np.diff(np.concatenate(([0], slow.astype(np.int8), [0]))))
    s_way = tool.arc_length_m
    rates = np.gradient(joints.q_rad, s_way, axis=0)  # dq/ds at the waypoints
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        i = start + int(np.argmin(speed[start:stop]))
        w = min(int(np.searchsorted(s_way, arc[i])), len(s_way) - 1)
        cap = limits.qd_max_rad_s / np.maximum(np.abs(rates[w]), 1e-12)
        joint = int(np.argmin(cap))
        bound, point = point_bound.at(float(arc[i])) if point_bound else (np.inf, -1)
        if point_bound is not None and bound <= 1.05 * speed[i]:
            cause = (
                f"the {SPEED_POINT_NAMES[point]} would pass the "
                f"{point_bound.cap_m_s * 1e3:.0f} mm/s speed cap (the tool turns about its tip)"
            )
        elif joints.wrist_singularity[w] < 0.15:
            cause = "near the wrist singularity (joints 4 and 6 nearly aligned)"
        elif joints.elbow_singularity[w] < 0.15:
            cause = "near the elbow singularity (arm nearly stretched)"
        elif cap[joint] <= 1.05 * speed[i]:
            cause = f"joint {joint + 1} speed limit"
        else:
            cause = "joint acceleration limits (a tight curve or a fast turn of the tool)"
        drops.append(
            SpeedDrop(
                start_m=float(arc[start]),
                end_m=float(arc[stop - 1]),
                min_speed_m_s=float(speed[i]),
                cause=cause,
            )
        )
    return drops
