"""Frozen dataclasses shared by every layer: inputs, parameters and results of the core.

Conventions (see docs/architecture.md): SI units (m, rad, s); a transform ``T_a_b`` is a 4x4
homogeneous matrix mapping points of frame ``b`` into frame ``a``; quaternions are scalar-last
``(x, y, z, w)`` where a field says ``xyzw``. Arrays held by these classes are made read-only so a
result cannot be changed behind the back of whoever stored it.
"""

from __future__ import annotations

import enum
import functools
import itertools
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

from recon.params import check_bounds, param
from recon.transforms import rotation_angle_deg, translation_m

if TYPE_CHECKING:
    # Annotations only: each of these modules imports this one.
    from recon.classify import SegmentKind
    from recon.collision import Tool
    from recon.kinematics import Configuration, DHCalibration, URModel
    from recon.scan_model import ScanModel

FloatArray = NDArray[np.float64]


def frozen_array(
    values: ArrayLike, *, dtype: DTypeLike = np.float64, shape_tail: tuple[int, ...] = (), name: str
) -> NDArray[Any]:
    """Copy ``values`` into a read-only array, checking its trailing shape and finiteness.

    Parameters
    ----------
    values : array_like
        The data.
    dtype : numpy dtype
        Target dtype.
    shape_tail : tuple of int
        Required trailing dimensions, e.g. ``(3,)`` for an ``(N, 3)`` array.
    name : str
        Field name used in error messages.

    Raises
    ------
    ValueError
        Wrong shape or non-finite floating-point values.
    """
    arr = np.array(values, dtype=dtype, copy=True)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        want = "(N, " + ", ".join(map(str, shape_tail)) + ")" if shape_tail else "(N,)"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr).reshape(len(arr), -1).all(axis=1)))
        raise ValueError(f"{name} has {bad} rows with NaN or infinite values; remove or fill them")
    arr.setflags(write=False)
    return arr


def piece_labels(values: ArrayLike | None, n: int, *, name: str = "piece") -> NDArray[np.int64]:
    """Check per-point piece labels: 0, 1, ... in order, each piece at least two points long.

    Parameters
    ----------
    values : array_like of shape (n,), or None
        None: one piece (all zeros).
    n : int
        Number of points.

    Raises
    ------
    ValueError
        Wrong length, labels that do not start at 0 and step by 0 or 1, a piece of one point.
    """
    if values is None:
        arr = np.zeros(n, dtype=np.int64)
        arr.setflags(write=False)
        return arr
    arr = frozen_array(values, dtype=np.int64, name=name)
    if len(arr) != n:
        raise ValueError(f"{name} has {len(arr)} values for {n} points")
    if n and (arr[0] != 0 or np.any((np.diff(arr) != 0) & (np.diff(arr) != 1))):
        raise ValueError(f"{name} must count pieces in order: 0, 0, ..., 1, 1, ...")
    if n and np.min(np.bincount(arr)) < 2:
        raise ValueError(f"every {name} needs at least two points")
    return arr


def piece_slices(piece: NDArray[np.int64]) -> list[slice]:
    """The index range of each piece, in order (``piece`` as checked by :func:`piece_labels`)."""
    starts = np.r_[0, np.flatnonzero(np.diff(piece)) + 1, len(piece)]
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(starts)]


@dataclass(frozen=True)
class Recording:
    """A traced path as the tracker delivered it, in the tracker frame.

    Attributes
    ----------
    points_m : ndarray of shape (N, 3), metres
        Pen-tip positions in traversal order.
    t_s : ndarray of shape (N,), seconds, or None
        Sample times, strictly increasing when given.
    orientations_xyzw : ndarray of shape (N, 4), or None
        Pen orientations as unit quaternions, scalar last.
    piece : ndarray of shape (N,), int
        Which continuous piece each sample belongs to (0, 1, ... in order): a trace split by
        long dropouts or lift-offs, kept whole. All zeros (one piece) when not given.
    """

    points_m: FloatArray
    t_s: FloatArray | None = None
    orientations_xyzw: FloatArray | None = None
    piece: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        pts = frozen_array(self.points_m, shape_tail=(3,), name="points_m")
        object.__setattr__(self, "points_m", pts)
        object.__setattr__(self, "piece", piece_labels(self.piece, len(pts)))
        if self.t_s is not None:
            t = frozen_array(self.t_s, name="t_s")
            if len(t) != len(pts):
                raise ValueError(f"t_s has {len(t)} values for {len(pts)} points")
            if len(t) > 1 and np.any(np.diff(t) <= 0):
                raise ValueError("t_s must be strictly increasing; sort the samples by time")
            object.__setattr__(self, "t_s", t)
        if self.orientations_xyzw is not None:
            q = frozen_array(self.orientations_xyzw, shape_tail=(4,), name="orientations_xyzw")
            if len(q) != len(pts):
                raise ValueError(f"orientations_xyzw has {len(q)} rows for {len(pts)} points")
            norms = np.linalg.norm(q, axis=1)
            if np.any(np.abs(norms - 1.0) > 1e-3):
                raise ValueError("orientations_xyzw must be unit quaternions (x, y, z, w)")
            object.__setattr__(self, "orientations_xyzw", q)

    def __len__(self) -> int:
        return len(self.points_m)

    def _labels(self) -> NDArray[np.int64]:
        """``piece`` as ``__post_init__`` left it (labels, never None after it)."""
        assert self.piece is not None  # set by __post_init__
        return self.piece

    @property
    def n_pieces(self) -> int:
        piece = self._labels()
        return int(piece[-1]) + 1 if len(piece) else 0

    @classmethod
    def joined(cls, pieces: list[Recording]) -> Recording:
        """Pieces (in time order) as one recording that keeps them apart (``piece``)."""
        if not pieces:
            raise ValueError("no piece to join")

        def stacked(name: str) -> NDArray[Any] | None:
            values = [getattr(p, name) for p in pieces]
            return None if any(v is None for v in values) else np.concatenate(values)

        return cls(
            points_m=np.concatenate([p.points_m for p in pieces]),
            t_s=stacked("t_s"),
            orientations_xyzw=stacked("orientations_xyzw"),
            piece=np.repeat(np.arange(len(pieces)), [len(p) for p in pieces]),
        )

    def pieces(self) -> list[Recording]:
        """Each piece as a recording of its own."""
        return [
            Recording(
                points_m=self.points_m[rows],
                t_s=None if self.t_s is None else self.t_s[rows],
                orientations_xyzw=None
                if self.orientations_xyzw is None
                else self.orientations_xyzw[rows],
            )
            for rows in piece_slices(self._labels())
        ]


@dataclass(frozen=True)
class Scan:
    """A point cloud of the workpiece, in the scan frame.

    Attributes
    ----------
    points_m : ndarray of shape (M, 3), metres
    normals : ndarray of shape (M, 3), or None
        Unit normals if the scanner or reader supplied them (orientation not relied upon).
    """

    points_m: FloatArray
    normals: FloatArray | None = None

    def __post_init__(self) -> None:
        pts = frozen_array(self.points_m, shape_tail=(3,), name="scan points_m")
        object.__setattr__(self, "points_m", pts)
        if self.normals is not None:
            n = frozen_array(self.normals, shape_tail=(3,), name="scan normals")
            if len(n) != len(pts):
                raise ValueError(f"scan has {len(n)} normals for {len(pts)} points")
            object.__setattr__(self, "normals", n)

    def __len__(self) -> int:
        return len(self.points_m)


Method = Literal["paper", "anchored"]
METHODS: tuple[str, ...] = ("paper", "anchored")


@dataclass(frozen=True)
class ReconParams:
    """Parameters of one reconstruction; stored with every result so it can be replayed.

    Attributes
    ----------
    spacing_m : float
        Distance between resampled path points.
    radius_m : float
        Reconstruction radius r: path points within r of a point (along the path) form N_P.
    degree : int
        Degree d of the fitted polynomials.
    alpha : float in [0, 1] or "auto"
        Weight of the path against the scan (1: path only, 0: scan only). ``"auto"`` picks it per
        point from the estimated noise of both (see ``recon.reconstruct``).
    beta : float in [0, 1]
        Total amount of reconstruction (0 leaves the path as it is for ``anchored``; see paper).
    method : {"paper", "anchored"}
        ``paper``: Eq. (4) of the paper, using only the shape of the scan near the path.
        ``anchored``: uses the registered scan's absolute position and keeps all three components.
    corner_angle_deg : float
        Turning angle above which the path is split into separately reconstructed segments.
    corner_scale_m : float
        Chord length over which the turning angle is measured (larger than hand tremor).
    register : bool
        Register the path to the scan's features with ICP before reconstructing.
    icp_max_distance_m : float
        Largest path-to-scan distance ICP pairs points over (a bound on the misalignment).
    crop_margin_m : float
        Only scan points within this distance of the path are processed.
    voxel_m : float
        Voxel size the cropped scan is averaged down to (0: keep every point). Curvature needs a
        scale: on a dense cloud, small neighbourhoods see only noise.
    curvature_radius_m : float
        Neighbourhood radius for normals and curvature (surface variation).
    edge_curvature : float or None
        Surface variation above which a scan point is an edge point; None derives it from the
        cloud (see ``recon.features.edge_threshold``).
    edge_fraction : float
        A segment follows an edge of the scan when the edge runs along at least this share of it
        (and close to it); its points without the edge then take the height of the face under
        them (see ``recon.classify``).
    surface_k : int
        k nearest scan points of every point of N_P that form N_S on a surface.
    uncertainty_tolerance_m : float
        The summary warns of every stretch whose points' 1-sigma uncertainty exceeds this.
    evidence_sigmas : float
        The scan may move a point at most this many of the trace's standard deviations (the
        hand's error model); a feature farther away is not the one traced there, and the point
        keeps the smoothed trace (said per point in ``reason``).
    """

    spacing_m: float = param(0.001, ge=1e-4, le=0.01, unit="m", help="resampling step")
    radius_m: float = param(0.008, ge=5e-4, le=0.2, unit="m", help="reconstruction radius r")
    degree: int = param(2, ge=1, le=5, help="polynomial degree")
    alpha: float | Literal["auto"] = param(
        "auto", ge=0, le=1, help="weight of the path against the scan (1: path only), or auto"
    )
    beta: float = param(1.0, ge=0, le=1, help="amount of reconstruction")
    method: Method = param(
        "anchored", help="paper: the paper's Eq. (4); anchored: ours, using the scan's position"
    )
    corner_angle_deg: float = param(
        50.0, ge=1, le=180, unit="deg", help="turning angle that splits the path at a corner"
    )
    corner_scale_m: float = param(
        0.004, ge=5e-4, le=0.05, unit="m", help="chord over which the turning angle is measured"
    )
    register: bool = True
    icp_max_distance_m: float = param(
        0.010, ge=1e-4, le=0.1, unit="m", help="largest path-to-scan distance ICP pairs over"
    )
    crop_margin_m: float = param(
        0.020, ge=1e-3, le=0.2, unit="m", help="scan points farther from the path are left out"
    )
    voxel_m: float = param(
        0.002, ge=0, le=0.05, unit="m", help="voxel the cropped scan is averaged to (0: none)"
    )
    curvature_radius_m: float = param(
        0.008, ge=5e-4, le=0.1, unit="m", help="ball of the scan's normals and curvature"
    )
    edge_curvature: float | None = param(
        None, gt=0, lt=1 / 3, help="surface variation above which a scan point is an edge"
    )
    edge_fraction: float = param(
        0.25, ge=0.01, le=1, help="share of a segment an edge must run along for it to follow it"
    )
    surface_k: int = param(
        10, ge=3, le=1000, help="nearest scan points per path point on a surface"
    )
    uncertainty_tolerance_m: float = param(
        0.0005,
        ge=1e-5,
        le=0.01,
        unit="m",
        help="the summary names the stretches whose 1-sigma uncertainty exceeds this",
    )
    evidence_sigmas: float = param(
        3.0,
        ge=0.5,
        le=20,
        help="the scan moves a point at most this many of the trace's standard deviations",
    )

    def __post_init__(self) -> None:
        check_bounds(self)
        if 0 < self.voxel_m < MIN_VOXEL_M:
            raise ValueError(
                f"voxel_m must be 0 (no averaging) or at least {MIN_VOXEL_M} m, got {self.voxel_m}"
            )
        if self.radius_m < 2 * self.spacing_m:
            raise ValueError(
                f"radius_m ({self.radius_m}) must be at least twice spacing_m ({self.spacing_m}) "
                "so that N_P holds enough points for a fit"
            )

    @property
    def uses_scan(self) -> bool:
        """Whether the scan can influence the result at all (alpha = 1 means path only)."""
        return self.alpha == "auto" or self.alpha < 1.0


#: The finest voxel the scan is averaged to (finer than a depth camera resolves is no averaging,
#: and a vanishing one overflows the voxel grid's indices).
MIN_VOXEL_M = 1e-4

Orientation = Literal["auto", "scan", "pen", "fixed"]
#: The TCP a plan assumes unless told: a straight tool 10 cm along the flange's z axis.
DEFAULT_TCP_POSE = (0.0, 0.0, 0.1, 0.0, 0.0, 0.0)
#: Most spheres a tool may be given as (``PlanParams.tool_spheres_m``): every sphere is checked
#: against every scan point near the motion.
MAX_TOOL_SPHERES = 32


def check_tool_spheres(numbers: tuple[float, ...]) -> None:
    """Check ``PlanParams.tool_spheres_m``'s shape: four numbers per sphere, radii >= 0 (the
    bounds of each number are the parameter's own).

    Raises
    ------
    ValueError
        Saying what a sphere takes.
    """
    if len(numbers) % 4 or len(numbers) > 4 * MAX_TOOL_SPHERES:
        raise ValueError(
            "tool_spheres_m takes four numbers per sphere (X,Y,Z,R, flange frame, metres), "
            f"at most {MAX_TOOL_SPHERES} spheres; got {len(numbers)} numbers"
        )
    if any(r < 0 for r in numbers[3::4]):
        raise ValueError("tool_spheres_m: every sphere's radius (its 4th number) must be >= 0")


@dataclass(frozen=True)
class PlanParams:
    """How to turn a path into the whole motion of the arm.

    Attributes
    ----------
    robot : str
        UR model.
    speed_m_s : float
        Requested TCP speed along the path.
    orientation : {"auto", "scan", "pen", "fixed"}
        Source of the tool axis; "auto" takes the scan if given, else the pen, else fixed.
    lead_deg, tilt_deg : float
        Lean of the tool (see ``recon.orient``).
    heading : {"travel", "free"}
        The tool's x axis along the travel, or free about the tool axis (a round tool: wrist 3
        kept as still as the axis allows; see :func:`recon.orient.tool_path`).
    smooth_m : float
        Smoothing of the tool axis along the path (0 turns it off).
    approach : tuple of 3 floats or None
        Where the tool comes from, base frame: surface normals are turned to face it, and the
        fixed tool axis is minus it. None (the default): from above the work, ``mount_up``.
    mount_up : tuple of 3 floats
        Away from the earth's centre, in the base frame, as UR's installation gives it
        (``set_gravity``'s direction): (0, 0, 1) for an arm on a floor or table, (0, 0, -1)
        hanging from a ceiling, horizontal on a wall. The default approach comes from it: the
        tool comes at the work from above, whatever the mount (the mounting plane is the base's
        own z = 0 plane for every mount: the surface it is bolted to).
    tcp_offset_m : tuple of 3 floats
        The TCP in the flange frame, position only (a tool of length L along the flange's z:
        (0, 0, L)); when set it replaces ``tcp_pose``.
    tcp_pose : tuple of 6 floats
        The TCP in the flange frame as UR's pendant sets it: x, y, z (m), rx, ry, rz (rotation
        vector, rad). Default :data:`DEFAULT_TCP_POSE`, a straight tool 10 cm long: a plan for
        the bare flange (all zero) puts the flange itself on the workpiece, which the collision
        check refuses; set your tool's.
    velocity_scale, acceleration_scale : float
        Fractions of the arm's joint limits to plan the path within.
    start_q_rad : tuple of 6 floats or None
        The joints the motion starts from (the arm's, read at planning time); None: home.
    shoulder, elbow, wrist : str
        The IK configuration (see :class:`recon.kinematics.Configuration`); "any" for either.
    approach_m : float
        How far above the path's first and last points (along the tool axis) the approach
        starts and the retract ends.
    approach_speed_m_s : float
        TCP speed of the approach and retract lines.
    transit_speed_scale, transit_acceleration_scale : float
        Fractions of the joint limits for the joint moves (transit and return).
    transit_tcp_speed_m_s : float
        The joint moves' largest TCP speed (a real arm's server caps every phase's TCP speed;
        the transit would otherwise reach 0.3-0.7 m/s at the joint scales alone).
    return_to_start : bool
        Move back to the start joints after the retract.
    payload_kg : float or None
        The payload's mass to set before motion; None: not set, the controller's installation
        keeps its own (read from it and shown when a real arm runs). Never a silent zero: a
        zero set over an installed gripper misjudges its weight and trips protective stops.
    payload_cog_m : tuple of 3 floats
        The payload's centre of gravity in the flange frame (with ``payload_kg`` only).
    tool_radius_m : float
        Radius of the tool's body from the flange to the TCP, for the collision check.
    tool_spheres_m : tuple of float
        The tool as spheres instead, four numbers each (X, Y, Z, R; flange frame, metres;
        at most :data:`MAX_TOOL_SPHERES`): a spindle with a flat end, whose capsule's round end
        would reach ``tool_radius_m`` past the tip into the table beside a thin plate; a
        gripper's fingers. Their union must hold the whole tool: the check sees nothing else.
    clearance_m : float
        Smallest distance the arm and tool keep from the scan, the mounting plane and the
        keep-out boxes (the tool's tip may touch the workpiece along the path only).
    joint_margin_deg : float
        Smallest distance every joint keeps from its limits at every sample (a plan 0.4 deg
        from a wrist's limit was accepted: the controller's own limit check stops it there).
    """

    robot: str = param(
        "ur5e", help="UR model (ur3e, ur5e, ur10e, ur16e, ur20, ur30, ur3, ur5, ur10)"
    )
    speed_m_s: float = param(0.05, ge=0.001, le=2.0, unit="m/s", help="requested TCP speed")
    orientation: Orientation = param(
        "auto", help="tool axis from the scan's normals, the pen, or fixed; auto picks in order"
    )
    lead_deg: float = param(0.0, ge=-60, le=60, unit="deg", help="lean along the travel")
    tilt_deg: float = param(0.0, ge=-60, le=60, unit="deg", help="lean across the travel")
    heading: Literal["travel", "free"] = param(
        "free",
        help="the tool's x axis: along the travel, or free about the tool axis (a round tool: "
        "wrist 3 kept still)",
    )
    smooth_m: float = param(
        0.01, ge=0, le=0.1, unit="m", help="smoothing of the tool axis along the path (0: off)"
    )
    approach: tuple[float, float, float] | None = param(
        None,
        ge=-1,
        le=1,
        help="where the tool comes from, base frame (default: from above, mount_up)",
    )
    mount_up: tuple[float, float, float] = param(
        (0.0, 0.0, 1.0),
        ge=-1,
        le=1,
        help="up (away from the earth's centre) in the base frame: 0,0,1 floor, 0,0,-1 ceiling, "
        "horizontal on a wall",
    )
    tcp_offset_m: tuple[float, float, float] = param(
        (0.0, 0.0, 0.0), ge=-1, le=1, unit="m", help="the TCP in the flange frame"
    )
    tcp_pose: tuple[float, float, float, float, float, float] = param(
        DEFAULT_TCP_POSE,
        ge=-2 * math.pi,
        le=2 * math.pi,
        help="the TCP in the flange frame as on UR's pendant: x,y,z (m), rx,ry,rz (rad)",
    )
    velocity_scale: float = param(
        1.0, ge=0.01, le=1, help="fraction of the arm's joint speed limits to plan within"
    )
    acceleration_scale: float = param(
        1.0, ge=0.01, le=1, help="fraction of the arm's joint acceleration limits to plan within"
    )
    start_q_rad: tuple[float, float, float, float, float, float] | None = param(
        None,
        ge=-2 * math.pi,
        le=2 * math.pi,
        unit="rad",
        help="the joints the motion starts from (the service: the arm's now; else home)",
    )
    shoulder: Literal["any", "left", "right"] = param("any", help="IK configuration: shoulder")
    elbow: Literal["up", "down", "any"] = param("up", help="IK configuration: elbow")
    wrist: Literal["any", "flip", "noflip"] = param("any", help="IK configuration: wrist")
    approach_m: float = param(
        0.05, ge=0.005, le=0.5, unit="m", help="approach and retract height along the tool axis"
    )
    approach_speed_m_s: float = param(
        0.05, ge=0.001, le=0.25, unit="m/s", help="TCP speed of the approach and retract"
    )
    transit_speed_scale: float = param(
        0.3, ge=0.01, le=1, help="fraction of the joint speed limits for the transit and return"
    )
    transit_acceleration_scale: float = param(
        0.3, ge=0.01, le=1, help="fraction of the joint accelerations for the transit and return"
    )
    transit_tcp_speed_m_s: float = param(
        0.25, ge=0.005, le=1.0, unit="m/s", help="largest TCP speed of the transit and return"
    )
    return_to_start: bool = param(False, help="move back to the start joints at the end")
    payload_kg: float | None = param(
        None,
        ge=0,
        le=35,
        unit="kg",
        help="the payload's mass to set before motion (default: not set, the controller's "
        "installation keeps its own)",
    )
    payload_cog_m: tuple[float, float, float] = param(
        (0.0, 0.0, 0.0), ge=-0.5, le=0.5, unit="m", help="the payload's centre of gravity"
    )
    tool_radius_m: float = param(
        0.01, ge=5e-4, le=0.2, unit="m", help="radius of the tool's body (collision check)"
    )
    tool_spheres_m: tuple[float, ...] = param(
        (),
        ge=-1,
        le=1,
        unit="m",
        help="the tool as spheres instead of a capsule: X,Y,Z,R per sphere in the flange frame "
        "(a spindle with a flat end, a gripper's fingers); their union must hold the whole tool",
    )
    clearance_m: float = param(
        0.01, ge=0, le=0.1, unit="m", help="distance the arm and tool keep from obstacles"
    )
    joint_margin_deg: float = param(
        5.0, ge=0, le=45, unit="deg", help="distance every joint keeps from its limits"
    )

    def __post_init__(self) -> None:
        from recon import kinematics  # here: kinematics imports this module

        arm = kinematics.model(self.robot)  # raises on an unknown arm
        check_bounds(self)
        if self.approach is not None and np.linalg.norm(self.approach) < 1e-9:
            raise ValueError("approach must be a non-zero direction")
        if np.linalg.norm(self.mount_up) < 0.5:
            raise ValueError(
                f"mount_up must be a direction (a unit vector, as 0,0,1 for a floor mount), got "
                f"{self.mount_up}"
            )
        if tuple(self.tcp_pose) != DEFAULT_TCP_POSE and any(self.tcp_offset_m):
            raise ValueError("give the TCP as tcp_pose or as tcp_offset_m, not both")
        if any(abs(v) > 1.0 for v in self.tcp_pose[:3]):
            raise ValueError(f"the TCP must be within 1 m of the flange, got {self.tcp_pose[:3]}")
        check_tool_spheres(self.tool_spheres_m)
        if self.payload_kg is not None and self.payload_kg > arm.payload_kg:
            raise ValueError(
                f"payload_kg {self.payload_kg} is above the {arm.name}'s {arm.payload_kg} kg"
            )
        if self.start_q_rad is not None:
            q = np.asarray(self.start_q_rad)
            if np.any(q < arm.q_min_rad) or np.any(q > arm.q_max_rad):
                raise ValueError("start_q_rad is outside the arm's joint limits")

    @property
    def tcp(self) -> tuple[float, float, float, float, float, float]:
        """The TCP pose in the flange frame (x, y, z, rx, ry, rz), whichever way it was given
        (``tcp_offset_m``, when set, moves the TCP without turning it)."""
        if any(self.tcp_offset_m):
            return (*self.tcp_offset_m, 0.0, 0.0, 0.0)
        x, y, z, rx, ry, rz = self.tcp_pose
        return (x, y, z, rx, ry, rz)

    @property
    def approach_direction(self) -> FloatArray:
        """Where the tool comes from (unit, base frame): ``approach``, or from above."""
        direction = np.asarray(
            self.mount_up if self.approach is None else self.approach, dtype=np.float64
        )
        return direction / np.linalg.norm(direction)

    @property
    def point_speed_max_m_s(self) -> float:
        """The largest speed of the elbow, the wrists and the flange on the straight moves and
        the path: the fastest TCP speed any phase asks for (a real arm's cap applies to every
        point, and the service keeps each of these speeds under it)."""
        return max(self.speed_m_s, self.approach_speed_m_s, self.transit_tcp_speed_m_s)

    @property
    def tool(self) -> Tool:
        """The tool's collision shape: :class:`recon.collision.SphereTool` of
        ``tool_spheres_m`` when given, else a :class:`recon.collision.CapsuleTool` of
        ``tool_radius_m`` from the flange to the TCP."""
        from recon.collision import CapsuleTool, SphereTool

        if self.tool_spheres_m:
            spheres = np.reshape(np.asarray(self.tool_spheres_m, dtype=np.float64), (-1, 4))
            return SphereTool(centers_m=spheres[:, :3], radii_m=spheres[:, 3])
        return CapsuleTool(radius_m=self.tool_radius_m)

    @property
    def T_flange_tcp(self) -> FloatArray:
        from recon.transforms import transform_from_pose

        return transform_from_pose(np.asarray(self.tcp, dtype=np.float64))

    @property
    def configuration(self) -> Configuration:
        """The wanted :class:`recon.kinematics.Configuration` ("any" as None)."""
        from recon.kinematics import Configuration

        def named(value: str) -> str | None:
            return None if value == "any" else value

        return Configuration(
            shoulder=named(self.shoulder), elbow=named(self.elbow), wrist=named(self.wrist)
        )


class PointMode(enum.IntEnum):
    """What a reconstructed point followed."""

    PATH = 0  #: the path alone (no scan, alpha = 1, or no scan support near this point)
    SURFACE = 1  #: a surface of the scan
    EDGE = 2  #: an edge of the scan
    UNCHANGED = 3  #: too few points around it for a fit; passed through as resampled

    @property
    def label(self) -> str:
        return self.name.lower()


class PointReason(enum.IntEnum):
    """Why a point was not reconstructed as its segment claims (the scan's evidence failed
    there), or how it was, where that needs saying. ``NONE`` for every point that followed its
    segment's feature, and for every point of a reconstruction without a scan."""

    NONE = 0  #: as its segment claims
    NO_FEATURE = 1  #: the scan shows no such feature here (nothing fitted, too few points)
    FAR_FROM_TRACE = 2  #: the feature is farther from the trace than the hand's error explains
    OFF_EVIDENCE = 3  #: the fitted feature is not where the scan's points are (too far from them)
    #: the whole segment ran far from the scan (no longer produced: judged point by point as
    #: FAR_FROM_TRACE; kept so records that hold it still read)
    SEGMENT_DISAGREES = 4
    ONE_FACE = 5  #: the edge was not found here; the height comes from the one face under it
    CONTINUED = 6  #: past the end of the scan's feature, continued along its line
    PAST_END = 7  #: farther past the end of the scan's feature than it is continued

    @property
    def label(self) -> str:
        return "" if self is PointReason.NONE else self.name.lower()

    @property
    def fallen_back(self) -> bool:
        """The scan was not used at this point although the segment claimed it."""
        return self in (
            PointReason.NO_FEATURE,
            PointReason.FAR_FROM_TRACE,
            PointReason.OFF_EVIDENCE,
            PointReason.SEGMENT_DISAGREES,
            PointReason.PAST_END,
        )


#: A segment where more than this share of the points fell back to the trace is one where the
#: scan is not trusted (said in the summary).
DISTRUST_SHARE = 0.05


@dataclass(frozen=True)
class Segment:
    """A run of path points between corners, reconstructed on its own.

    ``start`` and ``stop`` index the resampled path (``stop`` exclusive); neighbouring segments
    share their corner point, which belongs to the later one in ``Reconstruction.segment``.
    ``kind`` is a :class:`recon.classify.SegmentKind`, a string enum: ``dataclasses.asdict`` of a
    segment serialises to JSON as ``"edge"``, ``"surface"`` or ``"path"``.

    The evidence for an edge segment's choice: ``edge_fraction`` (the share of the segment the
    chosen edge runs along), ``edge_distance_m`` (how far the trace ran from it, median) and
    ``next_edge_m`` (how far the next candidate edge lay from it, median; None when there was
    none). ``fallen_back`` is the share of its points where the scan's evidence failed and the
    trace was kept; a segment with more than :data:`DISTRUST_SHARE` of them is one where the
    scan is not trusted.
    """

    start: int
    stop: int
    kind: SegmentKind
    edge_fraction: float
    edge_distance_m: float | None = None
    next_edge_m: float | None = None
    fallen_back: float = 0.0

    @property
    def scan_trusted(self) -> bool:
        """Whether the scan's evidence held along the segment (see :data:`DISTRUST_SHARE`)."""
        return self.fallen_back <= DISTRUST_SHARE

    def __post_init__(self) -> None:
        # Imported here: recon.classify imports this module. A plain string is accepted (a
        # segment read back from JSON) and refused if it names no kind.
        from recon.classify import SegmentKind

        object.__setattr__(self, "kind", SegmentKind(self.kind))


@dataclass(frozen=True)
class DemonstrationReport:
    """How one of several demonstrations of a path entered their fusion.

    Attributes
    ----------
    used : bool
    reversed : bool
        It was traced the other way round and turned.
    mean_offset_m : float
        Its mean distance from the others' median.
    roughness_m : float
        RMS departure from its own smoothing (hand tremor and tracker noise).
    reason : str
        Why it was left out (empty when used).
    """

    used: bool
    reversed: bool
    mean_offset_m: float
    roughness_m: float
    reason: str = ""


@dataclass(frozen=True)
class CornerReport:
    """Where the trace turned sharply, and whether the path was split there.

    Attributes
    ----------
    index : int
        The resampled point of the turn.
    angle_deg : float
        How much the trace turned there.
    split : bool
    reason : str
        Why (or why not), in words.
    point_m : tuple of 3 floats or None
        Where the scan's edges meet, tracker frame, when they placed the corner: both segments
        end there (with ``beta`` < 1, that share of the way there from the trace).
    """

    index: int
    angle_deg: float
    split: bool
    reason: str
    point_m: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Registration:
    """Result of registering the path to the scan.

    Attributes
    ----------
    T_scan_tracker : ndarray of shape (4, 4)
        Maps path (tracker-frame) points into the scan frame.
    rmse_m : float
        Root mean square distance of the paired points after registration.
    fitness : float
        Fraction of path points that were paired (with non-zero robust weight) at the end.
    n_pairs : int
        Number of such pairs.
    target : str
        What the path was registered to: "edge" or "surface".
    constrained_dof : int
        How many of the six rigid degrees of freedom the scan's feature fixed (6 for a corner,
        5 for a circle, 4 for a straight edge, 3 for a plane); the others kept the initial guess.
    path_moved_mean_m, path_moved_max_m : float
        How far the path's points moved from where the initial guess put them (mean, max; NaN
        if unknown). What a user means by "registration moved the path": the transform's own
        translation also holds the scanner's placement, metres away for a scanner whose origin
        is far from the tracker's.
    path_moved_off_feature_median_m : float
        The part of a point's move toward or away from the feature it was registered to
        (along the surface's normal, across the edge), median over the path (NaN if unknown).
        A path moved by millimetres but off its feature by a fraction of one slid along it:
        where the feature hardly fixes that sliding (a nearly flat patch), the move says little
        about the scanner.
    reason : str
        Why this target was chosen (empty when there was no choice).
    alternative : dict or None
        The other target's figures when it was tried too: ``target``, ``rmse_m``, ``fitness``,
        ``constrained_dof``, ``following_edge`` (the fraction of the path that would follow the
        edge), ``path_moved_mean_m``.
    covariance : ndarray of shape (6, 6) or None
        Of the transform's error as a twist ``(L omega, t)`` about ``motion_centre_m`` with
        ``L = motion_length_m`` (see :class:`recon.icp.RigidMotion`), scan frame; zero along the
        motions the target leaves free. None when unknown.
    motion_centre_m : ndarray of shape (3,) or None
    motion_length_m : float or None
    """

    T_scan_tracker: FloatArray
    rmse_m: float
    fitness: float
    n_pairs: int
    target: str
    constrained_dof: int = 6
    path_moved_mean_m: float = float("nan")
    path_moved_max_m: float = float("nan")
    path_moved_off_feature_median_m: float = float("nan")
    reason: str = ""
    alternative: dict[str, Any] | None = field(default=None, compare=False)
    covariance: FloatArray | None = field(default=None, compare=False, repr=False)
    motion_centre_m: FloatArray | None = field(default=None, compare=False, repr=False)
    motion_length_m: float | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        T = np.array(self.T_scan_tracker, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"T_scan_tracker must be 4x4, got {T.shape}")
        T.setflags(write=False)
        object.__setattr__(self, "T_scan_tracker", T)

    @property
    def translation_m(self) -> FloatArray:
        return translation_m(self.T_scan_tracker)

    @property
    def rotation_deg(self) -> float:
        """Angle of the rotation part, degrees."""
        return rotation_angle_deg(self.T_scan_tracker)


#: The fields of a :class:`Reconstruction` that hold one row per point, in the order of the
#: reconstruction CSV's columns.
PER_POINT_FIELDS = (
    "points_m",
    "input_points_m",
    "t_s",
    "orientations_xyzw",
    "displacement_m",
    "mode",
    "segment",
    "n_path",
    "n_surface",
    "residual_path_m",
    "residual_surface_m",
    "alpha",
    "piece",
    "uncertainty_m",
    "reason",
)


@dataclass(frozen=True)
class Reconstruction:
    """A reconstructed path with per-point diagnostics, in the tracker frame.

    Attributes
    ----------
    points_m : ndarray of shape (N, 3), metres
        The reconstructed path.
    input_points_m : ndarray of shape (N, 3), metres
        The equidistantly resampled input that ``points_m`` corresponds to point by point.
    t_s : ndarray of shape (N,), seconds, or None
        Sample times interpolated at the resampled points, when the input had times.
    orientations_xyzw : ndarray of shape (N, 4), or None
        The pen's orientations interpolated at the resampled points, when the input had them.
    displacement_m : ndarray of shape (N,), metres
        How far each point moved: ``|points_m - input_points_m|``.
    mode : ndarray of shape (N,), int8
        :class:`PointMode` of each point.
    segment : ndarray of shape (N,), int
        Index into ``segments``.
    n_path, n_surface : ndarray of shape (N,), int
        Sizes of N_P and N_S (0 where no scan was used).
    residual_path_m, residual_surface_m : ndarray of shape (N,), metres
        RMS residual of the path and scan fits (NaN where there was no such fit).
    alpha : ndarray of shape (N,)
        The path weight used at each point (1 where only the path was used).
    piece : ndarray of shape (N,), int
        The trace's piece each point belongs to (see :class:`Recording`); no segment spans two.
    segments : tuple of Segment
    registration : Registration or None
        None when no scan was used or registration was switched off.
    params : ReconParams
    notes : tuple of str
    orientations_xyzw : see above
    T_scan_tracker : ndarray of shape (4, 4), or None
        The transform the scan was used with: the registration's, else the initial (calibrated)
        one given, else identity when a scan was used without either; None when no scan was used.
    scan_model : ScanModel or None
        The scan's structure near the path, scan frame, as the reconstruction used it (None
        without a scan). Planning reuses it with ``T_scan_tracker`` instead of recomputing it.
        Left out of equality and repr: it is large and derived from the inputs.
    corners : tuple of CornerReport
        Every place the trace turned sharply, split or not, and why.
    uncertainty_m : ndarray of shape (N,), metres, or None
        1-sigma uncertainty of each point across the path, tracker frame: from the fits, the
        trace's estimated noise and the registration (the transform's uncertainty moves the
        scan's features, and the path with them). None for results made before it was kept.
    demonstrations : tuple of DemonstrationReport
        When several demonstrations were fused into the trace: how each one entered.
    reason : ndarray of shape (N,), int8, or None
        :class:`PointReason` of each point: why the scan's evidence was not used where the
        segment claimed it, or how it was used past a feature's end. None for results made
        before it was kept.
    """

    points_m: FloatArray
    input_points_m: FloatArray
    t_s: FloatArray | None
    displacement_m: FloatArray
    mode: NDArray[np.int8]
    segment: NDArray[np.int64]
    n_path: NDArray[np.int64]
    n_surface: NDArray[np.int64]
    residual_path_m: FloatArray
    residual_surface_m: FloatArray
    alpha: FloatArray
    segments: tuple[Segment, ...]
    registration: Registration | None
    params: ReconParams
    notes: tuple[str, ...] = field(default=())
    orientations_xyzw: FloatArray | None = None
    T_scan_tracker: FloatArray | None = None
    scan_model: ScanModel | None = field(default=None, compare=False, repr=False)
    piece: NDArray[np.int64] | None = None
    corners: tuple[CornerReport, ...] = ()
    uncertainty_m: FloatArray | None = None
    demonstrations: tuple[DemonstrationReport, ...] = ()
    reason: NDArray[np.int8] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "piece", piece_labels(self.piece, len(self.points_m)))
        if self.T_scan_tracker is not None:
            T = np.array(self.T_scan_tracker, dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"T_scan_tracker must be 4x4, got {T.shape}")
            T.setflags(write=False)
            object.__setattr__(self, "T_scan_tracker", T)
        n = len(self.points_m)
        for name in PER_POINT_FIELDS:
            value = getattr(self, name)
            if value is None:
                continue
            arr = np.array(value, copy=True)
            if len(arr) != n:
                raise ValueError(f"{name} has {len(arr)} rows for {n} points")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def point_pieces(self) -> NDArray[np.int64]:
        """``piece`` as ``__post_init__`` left it (one label per point; never None)."""
        assert self.piece is not None  # labelled by __post_init__
        return self.piece

    def __len__(self) -> int:
        return len(self.points_m)

    def count(self, mode: PointMode) -> int:
        """Number of points reconstructed in ``mode``."""
        return int(np.count_nonzero(self.mode == int(mode)))


@dataclass(frozen=True)
class ReconstructedPath:
    """What planning needs of a reconstruction, however it was stored (an artifact, a CSV).

    Attributes
    ----------
    points_m : ndarray of shape (N, 3), metres
        The reconstructed path, tracker frame.
    mode : ndarray of shape (N,), int8
        :class:`PointMode` per point.
    orientations_xyzw : ndarray of shape (N, 4), or None
        The pen's orientations, tracker frame, scalar last.
    T_scan_tracker : ndarray of shape (4, 4), or None
        The transform the reconstruction used between tracker and scan (None: no scan, or not
        recorded).
    piece : ndarray of shape (N,), int
        The trace's piece of each point (all zeros: one piece); the arm lifts between pieces.
    """

    points_m: FloatArray
    mode: NDArray[np.int8]
    orientations_xyzw: FloatArray | None = None
    T_scan_tracker: FloatArray | None = None
    piece: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "piece", piece_labels(self.piece, len(self.points_m)))


@dataclass(frozen=True)
class ToolPath:
    """TCP poses along a path.

    Attributes
    ----------
    points_m : ndarray of shape (N, 3), metres
        TCP positions.
    orientations_xyzw : ndarray of shape (N, 4)
        TCP orientations as unit quaternions, scalar last; the tool's z-axis points from the
        flange towards the workpiece, its x-axis along the direction of travel.
    arc_length_m : ndarray of shape (N,), metres
    source : {"scan", "pen", "fixed"}
        Where the tool axis came from.
    """

    points_m: FloatArray
    orientations_xyzw: FloatArray
    arc_length_m: FloatArray
    source: str

    def __post_init__(self) -> None:
        pts = frozen_array(self.points_m, shape_tail=(3,), name="points_m")
        q = frozen_array(self.orientations_xyzw, shape_tail=(4,), name="orientations_xyzw")
        arc = frozen_array(self.arc_length_m, name="arc_length_m")
        if not len(pts) == len(q) == len(arc):
            raise ValueError("points, orientations and arc lengths differ in length")
        for name, value in (("points_m", pts), ("orientations_xyzw", q), ("arc_length_m", arc)):
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.points_m)

    def poses(self) -> FloatArray:
        """The poses as 4x4 transforms, shape (N, 4, 4)."""
        from scipy.spatial.transform import Rotation

        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, :3] = Rotation.from_quat(self.orientations_xyzw).as_matrix()
        T[:, :3, 3] = self.points_m
        return T


@dataclass(frozen=True)
class JointPath:
    """Inverse kinematics along a tool path, one branch kept throughout.

    Attributes
    ----------
    q_rad : ndarray of shape (N, 6)
        Joint angles, unwrapped along the path and shifted into the joint limits.
    branch : int
        Which of the eight analytic solutions (see ``recon.kinematics.IKSolutions``).
    limit_margin_rad : ndarray of shape (N,)
        Smallest distance of any joint to its position limit.
    wrist_singularity, elbow_singularity : ndarray of shape (N,)
        |sin q5| and |sin q3| (0 at the singularity).
    shoulder_margin_m : ndarray of shape (N,)
        Distance of the wrist centre outside the shoulder-singular cylinder.
    """

    q_rad: FloatArray
    branch: int
    limit_margin_rad: FloatArray
    wrist_singularity: FloatArray
    elbow_singularity: FloatArray
    shoulder_margin_m: FloatArray


@dataclass(frozen=True)
class SpeedDrop:
    """A stretch of the path where the TCP moves slower than requested, and why."""

    start_m: float
    end_m: float
    min_speed_m_s: float
    cause: str


#: A summary lists at most this many speed drops, the slowest, and counts the rest.
LISTED_SPEED_DROPS = 5


def speed_drop_lines(drops: tuple[SpeedDrop, ...] | list[SpeedDrop]) -> list[str]:
    """Summary lines for the stretches slower than requested: the slowest
    :data:`LISTED_SPEED_DROPS` in path order, then one line counting the others.

    A 10 m serpentine has over a hundred small drops at its turns; a line for each buried the
    rest of the summary. Every drop stays in the plan (``speed_drops``) for the pendant and the
    files.
    """
    drops = list(drops)
    slowest = sorted(drops, key=lambda d: d.min_speed_m_s)[:LISTED_SPEED_DROPS]
    lines = [
        f"slower than requested from {d.start_m * 1e3:.0f} to {d.end_m * 1e3:.0f} mm of path "
        f"(down to {d.min_speed_m_s * 1e3:.1f} mm/s): {d.cause}"
        for d in sorted(slowest, key=lambda d: d.start_m)
    ]
    rest = len(drops) - len(slowest)
    if rest:
        length_mm = sum(d.end_m - d.start_m for d in drops) * 1e3
        floor = max(d.min_speed_m_s for d in slowest) * 1e3
        lines.append(
            f"... and {rest} more stretches slower than requested, none below {floor:.1f} mm/s "
            f"({len(drops)} in all over {length_mm:.0f} mm of path; every one is in the plan's "
            "speed_drops)"
        )
    return lines


class Phase(enum.IntEnum):
    """What a sample of a planned motion is part of."""

    TRANSIT = 0  #: a joint move from where the arm is to above the path
    APPROACH = 1  #: a straight line down the tool axis onto the path's first point
    PROCESS = 2  #: the path itself
    RETRACT = 3  #: a straight line up the tool axis from the path's last point
    RETURN = 4  #: a joint move back to where the arm started

    @property
    def label(self) -> str:
        return self.name.lower()


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
        for name in (
            "t_s",
            "q_rad",
            "qd_rad_s",
            "qdd_rad_s2",
            "tcp_m",
            "tcp_rotvec",
            "arc_length_m",
        ):
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
        from recon import kinematics  # here: kinematics imports this module

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
        from recon.sample_check import tcp_speeds_m_s  # here: sample_check imports this module

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
