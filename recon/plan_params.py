"""The motion planner's parameters (:class:`PlanParams`): the arm, the tool, speeds, margins,
orientation and where the motion starts.

Units, frames and quaternion order as docs/architecture.md's conventions say; the arrays held
here are read-only (:func:`recon.arrays.frozen_array`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from recon import kinematics
from recon.arrays import FloatArray
from recon.collision import CapsuleTool, SphereTool, Tool
from recon.kinematics import Configuration
from recon.params import check_bounds, param
from recon.transforms import transform_from_pose

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

        if self.tool_spheres_m:
            spheres = np.reshape(np.asarray(self.tool_spheres_m, dtype=np.float64), (-1, 4))
            return SphereTool(centers_m=spheres[:, :3], radii_m=spheres[:, 3])
        return CapsuleTool(radius_m=self.tool_radius_m)

    @property
    def T_flange_tcp(self) -> FloatArray:

        return transform_from_pose(np.asarray(self.tcp, dtype=np.float64))

    @property
    def configuration(self) -> Configuration:
        """The wanted :class:`recon.kinematics.Configuration` ("any" as None)."""

        def named(value: str) -> str | None:
            return None if value == "any" else value

        return Configuration(
            shoulder=named(self.shoulder), elbow=named(self.elbow), wrist=named(self.wrist)
        )
