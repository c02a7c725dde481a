"""The whole planned motion of the arm checked against the cell: capsules, planes, boxes, the scan.

A plan is a joint trajectory ``q_rad`` (M, 6) sampled at the controller rate with a phase label per
sample (:class:`Phase`). :func:`check_motion` checks the *continuous* motion through all samples,
vectorised over samples, against a :class:`Cell`: the mounting plane and other half-spaces,
keep-out boxes, and a scan of the workpiece (a point cloud, preprocessed once per cell).

Arm geometry
------------
Each arm is eight capsules (a segment with a radius), one per physical link, placed in the frames
of the DH chain (:func:`recon.kinematics.joint_frames`; frame ``k`` is the frame after joint ``k``,
its z-axis the axis of joint ``k + 1``):

============  =====  ========================================================================
capsule       frame  segment (in that frame's coordinates)
============  =====  ========================================================================
base          0      (0, 0, 0) to (0, 0, base_top): the base and the joint-1 housing (the
                     first part of the shoulder, which turns about its own axis)
shoulder      1      (0, 0, lo) to (0, 0, hi): the joint-2 housing, along the joint-2 axis
upper arm     2      (0, 0, off) to (-a2, 0, off): the tube between the joint-2 and joint-3 axes
elbow         2      (0, 0, lo) to (0, 0, hi): the joint-3 housing, along the joint-3 axis
forearm       3      (0, 0, off) to (-a3, 0, off): the tube between the joint-3 and joint-4 axes
wrist 1       3      (0, 0, lo) to (0, 0, hi): the joint-4 housing, along the joint-4 axis
wrist 2       4      (0, 0, lo) to (0, 0, hi): the joint-5 housing, along the joint-5 axis
wrist 3       5      (0, 0, lo) to (0, 0, d6): the joint-6 housing; it ends at the flange
============  =====  ========================================================================

The DH model folds the lateral offsets of the upper arm and the forearm (along the joint axes) into
``d4``; a tube along the DH origins would miss the real one by the shoulder offset (138 mm on a
UR5e, 258 mm on a UR20). The tubes here are at ``off``, the lateral position of the real tube.
A capsule along a joint axis is a solid of revolution about the joint it belongs to, so it covers
both links that meet at that joint whatever the joint angle.

Where the numbers come from. The lateral offsets of the upper arm and forearm are Universal Robots'
published ``shoulder_offset`` / ``elbow_offset`` (``config/<model>/physical_parameters.yaml`` of
UniversalRobots/Universal_Robots_ROS2_Description, 2.4.5), checked against the tubes' centres in
that repository's visual meshes (they agree within 0.5 mm, the UR20's and UR30's upper arms within
2.1 mm, except the CB3 UR10's upper arm: the file says 220.9 mm, the tube is at 176 mm; the
measured values are used). The extents and radii were fitted to the same visual
meshes (the real shape; the e-series collision meshes there are convex hulls of each link, which
would make the tubes as wide as the joint housings): with each link's mesh placed by the URDF chain
(which reproduces :func:`recon.kinematics.forward` to 1e-9), every mesh vertex and surface sample
(3 mm) lies inside the capsules of its link, for any joint angles; then lengths were rounded out
and radii up to the next millimetre. UR's own technical specifications give only the footprint
(base diameter: UR3e 128, UR5e 149, UR10e and UR16e 190, UR20 and UR30 245, UR3 118, UR5 149,
UR10 190 mm, as UR's spec sheets state them; not all of those sheets could be checked here) and
the reach (:data:`PUBLISHED_REACH_M`); the base capsules are at least as wide as those footprints
(the CB3 ones wider: their meshes include the cable connector) and the stretched-out arm's
capsules reach at least as far as the published reach (tested). Models without meshes of their
own in that repository: the UR16e uses the UR10e's base, shoulder and wrists, the UR30 the UR20's
(the same joints); their tubes have meshes of their own.
The numbers are in :data:`CAPSULES_MM`; :func:`capsule_model` gives them in metres.

The tool is a capsule from the flange to the TCP (:class:`CapsuleTool`) or a set of spheres in the
flange frame (:class:`SphereTool`).

Clearance and the conservative bound between samples
----------------------------------------------------
Clearance is the distance from a capsule's surface to the nearest obstacle (negative: penetration).
Every point ``p`` of the arm moves with speed ``|v| <= sum_i |dq_i/dt| * dist(p, axis_i)``; the
distance of any point of a link from the axis of joint ``i`` is bounded, whatever the
configuration, by ``B_i = |a_i| + sum_{k>i} |(a_k, d_k)| + (farthest capsule point from its frame
origin)``, the worst over the links that joint moves (the tool included). Between samples the
joints move linearly (the controller interpolates its setpoints), so the arm's motion is bounded by
the joint-space metric ``C = sum_i B_i |dq_i|``: no point of any link moves further than the change
of ``C``. The check configurations are chosen (by interpolation where one controller period moves
too far) so that consecutive ones are at most ``D = 2 f margin`` apart in ``C``; at any instant
between two checked configurations ``j`` and ``j + 1``, at ``C``-distances ``a`` and ``D_j - a``
from them, the clearance is at least ``max(c_j - a, c_{j+1} - D_j + a)``, and its minimum over a
sample period is what is reported. The reported clearance is therefore never larger than the true
clearance during the continuous motion, and a thin obstacle between two checked configurations is
still found; it is below the true minimum over the period by at most ``D`` plus the distance
errors below (:attr:`CollisionReport.tolerance_m`).

Scan distances are lower bounds from a k-d tree: the segment is covered with query points whose
spacing ``h`` bounds the error (``h / 2``), refined to ``margin * f / 2`` wherever the clearance is
near the margin; the voxel downsampling of the scan adds its measured resolution (the farthest
original point from the point that represents its voxel), which is subtracted. Plane distances are
exact; box distances are the exact minimum of the box's (convex) signed distance along the segment,
found by golden-section search to 1e-7 of the segment's length.

Contact exemption
-----------------
During the process phase the tool touches the workpiece on purpose. Given a :class:`ContactZone`
(the planned TCP positions of the process phase, the tool's axis at each, and a zone radius), the
scan points that are within the *contact radius* of the process path **and** no higher than the
*contact band* above the tip (measured along the tool's axis there) are ignored for the tool
during the process phase and during the last (approach) and first (retract) contact radius of
TCP travel. The contact radius is ``zone + tip radius + margin + tolerance``: the tool's tip (for
a capsule tool, the half sphere of its radius around the TCP) necessarily lies that close to the
surface it works on, and the check's own conservatism (:attr:`CollisionReport.tolerance_m`) must
not turn the intended contact into a reported one. The band is ``zone + margin + tolerance``
(about 21 mm with the defaults), whatever the tool's radius: the surface the tip works on lies
within it, a fixture that rises beside the path does not, and the tool's body is checked against
that fixture in full (a 45 mm tool passed a clamp 20 mm beside the path while the whole tube,
which grew with the tool, was exempt). What is lower than the band within the tube is taken for
the workpiece. With the defaults (20 mm tool radius, 5 mm zone, 10 mm margin) the tube is about
43 mm: an upright tool on the path is clear, while a tool body that leans more than about 25
degrees still meets the surface outside that tube, as a real 20 mm rod would (give a thin tip as
a :class:`SphereTool` for steep tools). Wrist 3 is exempted too when the tool is so short that
wrist 3's capsule reaches within the contact radius of the TCP; wrist 2 and the links above never
are. Everywhere else, and always for the other links, the scan counts in full (the exempt points
are found around points of the path a quarter of the contact radius apart, so the tube exempted
is never wider than stated).

The mounting plane gets the same treatment for the tool's tip only: where the tool is exempt, its
part within the contact radius of the TCP is left out of the test against the mounting plane (a
capsule's round end reaches its radius below the tip, and with a scan the plane is tested
``mounting_band_m`` up, so a sheet a few millimetres thick on the table could not be worked at
all with the default tool); the rest of the tool, and every other link, is tested in full, and a
tip deeper below the mounting surface than the contact zone's radius (a trace under the table)
has its whole tool tested (:func:`_tip_cut_mounting`).

The arm against itself
----------------------
The capsules three or more DH frames apart (:data:`SELF_PAIRS`: the tool and the wrists against
the base, the shoulder and the upper arm, the forearm against the base, ...) are checked against
each other at the same configurations, with exact segment distances
(:func:`segment_segment_closest`). Both capsules of a pair move, so each configuration's
clearance carries the spacing to its farther neighbour less, and the reported tolerance grows by
it. Closer pairs meet at their joint by construction and are not checked.

What is not checked: cables and dress packs, and the payload; the arm is assumed to follow its
samples (no overshoot).
"""

from __future__ import annotations

import enum
from dataclasses import InitVar, dataclass, field
from typing import Literal, overload

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from recon.arrays import FloatArray, piece_labels, piece_slices
from recon.kernels import nearest_to_voxel_centres
from recon.kinematics import URModel, joint_frames
from recon.kinematics import model as ur_model
from recon.paths import Phase
from recon.transforms import check_rigid, invert_transform


class ObstacleKind(enum.IntEnum):
    """What kind of obstacle a clearance was measured to."""

    SCAN = 0
    PLANE = 1
    BOX = 2
    NONE = 3  # no obstacle in the cell at all
    SELF = 4  # another part of the arm (or the tool)


#: The arm's capsules, in the order of :func:`link_capsules`.
LINK_NAMES: tuple[str, ...] = (
    "base",
    "shoulder",
    "upper arm",
    "elbow",
    "forearm",
    "wrist 1",
    "wrist 2",
    "wrist 3",
)
TOOL_NAME = "tool"

#: Pairs of capsules (indices into :data:`LINK_NAMES`, 8: the tool) checked against each other:
#: those three or more DH frames apart, whose distance the joints between them change (closer
#: pairs are held apart by the arm's own build: their capsules meet at the joint). The tool and
#: the wrists against the base, the shoulder and the upper arm are what folds into the arm.
SELF_PAIRS: tuple[tuple[int, int], ...] = (
    (0, 4), (0, 5), (0, 6), (0, 7), (0, 8),
    (1, 6), (1, 7), (1, 8),
    (2, 7), (2, 8), (3, 7), (3, 8),
    (4, 8), (5, 8),
)  # fmt: skip

#: Capsules of each arm, millimetres (parsed into :data:`CAPSULES_MM`). Per link: the base's top
#: and radius; for the housings along a joint axis (shoulder, elbow, wrists) "lo, hi", the capsule's
#: ends along the axis from the origin of its DH frame (see the module docstring for which frame;
#: the wrist-3 capsule ends at the flange, d6); for the tubes (upper arm, forearm) "off", the
#: tube's lateral offset along the joint axes, and the radius. Fitted to the visual meshes of
#: UniversalRobots/Universal_Robots_ROS2_Description 2.4.5 (see the module docstring); the tube
#: offsets are that repository's shoulder_offset / elbow_offset (config/<model>/
#: physical_parameters.yaml) as measured on the meshes (UR10: 176, not the file's 220.9). UR16e:
#: base, shoulder and wrists from the UR10e meshes; UR30: from the UR20 meshes.
_CAPSULE_TABLE_MM = """
#      base   |  shoulder   |up. arm  |   elbow     |forearm  |  wrist 1    |  wrist 2    |wrist 3
#     top   r |  lo  hi   r | off   r |  lo  hi   r | off   r |  lo  hi   r |  lo  hi   r |  lo   r
ur3e  162  66 |  65 162  49 | 120  46 |  50 155  43 |  27  36 |  -5 109  34 | -29  53  35 | -20  39
ur5e  182  78 |  71 186  63 | 138  59 |  39 184  66 |   7  53 | -35 106  40 | -36  57  43 | -30  46
ur10e 211  98 |  88 239  81 | 176  77 |  75 212  68 |  39  63 |  -1 141  48 | -40  75  50 | -33  53
ur16e 211  98 |  90 238  81 | 176  78 |  83 208  69 |  40  63 |  -1 144  48 | -41  75  50 | -33  53
ur20  237 125 | 122 191 103 | 258  97 | 103 170  83 |  43  82 | 128 158  57 |  -6 117  54 | -19  57
ur30  236 125 | 118 189 101 | 258  98 |  97 169  83 |  43  82 | 129 160  57 |  -6 117  54 | -18  57
ur3   122 101 |  65 160  48 | 120  47 |  52 153  44 |  27  36 |  -4  87  34 | -29  52  36 | -28  37
ur5    64 111 |  90 183  63 | 136  59 |  45 183  64 |  17  44 | -23  85  40 | -37  58  41 | -31  45
ur10  154  97 |  85 235  81 | 176  77 |  46 220 120 |  48  46 |  12 132  48 | -37  85  49 | -40  48
"""
CAPSULES_MM: dict[str, tuple[int, ...]] = {
    row.split()[0]: tuple(int(x) for x in row.replace("|", " ").split()[1:])
    for row in _CAPSULE_TABLE_MM.strip().splitlines()
    if not row.startswith("#")
}

#: The published reach of each arm (UR's technical specifications), metres: for reference in the
#: tests; the capsules of the stretched-out arm reach at least this far from the base axis.
PUBLISHED_REACH_M: dict[str, float] = {
    "ur3e": 0.500,
    "ur5e": 0.850,
    "ur10e": 1.300,
    "ur16e": 0.900,
    "ur20": 1.750,
    "ur30": 1.300,
    "ur3": 0.500,
    "ur5": 0.850,
    "ur10": 1.300,
}

# Golden-section iterations for the box distance: 0.618**34 ~ 1e-7 of the segment's length.
_GOLDEN_ITERATIONS = 34
# Scan clearances of stretches certainly deeper than this inside are not refined.
_DEEP_M = 0.02
# Scan clearances are refined (to the fine spacing) where the coarse bound is below
# margin + 4 * motion bound + this: close enough to the margin to decide, and to report exactly.
_REFINE_EXTRA_M = 0.01


# --------------------------------------------------------------------------------------------
# Geometry of the arm and the tool


@dataclass(frozen=True)
class CapsuleModel:
    """One arm's capsules in its DH frames (see the module docstring).

    Attributes
    ----------
    name : str
    frames : ndarray of shape (8,), int
        The DH frame each capsule is fixed in (0 base .. 5).
    local_m : ndarray of shape (8, 2, 3), metres
        Segment end points in that frame.
    radii_m : ndarray of shape (8,), metres
    """

    name: str
    frames: NDArray[np.int64]
    local_m: FloatArray
    radii_m: FloatArray


def capsule_model(arm: URModel | str) -> CapsuleModel:
    """The capsules of an arm, from :data:`CAPSULES_MM`.

    Raises
    ------
    ValueError
        An arm with no capsule table (the message lists those that have one).
    """
    arm = _arm(arm)
    try:
        v = np.array(CAPSULES_MM[arm.name], dtype=np.float64) / 1000.0
    except KeyError:
        raise ValueError(
            f"no capsule model for {arm.name!r}; known: {', '.join(sorted(CAPSULES_MM))}"
        ) from None
    (base_top, base_r, sh_lo, sh_hi, sh_r, ua_off, ua_r, el_lo, el_hi, el_r, fa_off, fa_r) = v[:12]
    (w1_lo, w1_hi, w1_r, w2_lo, w2_hi, w2_r, w3_lo, w3_r) = v[12:]

    def axial(lo: float, hi: float) -> list[list[float]]:
        return [[0.0, 0.0, lo], [0.0, 0.0, hi]]

    local = np.array(
        [
            axial(0.0, base_top),
            axial(sh_lo, sh_hi),
            [[0.0, 0.0, ua_off], [-arm.a2, 0.0, ua_off]],
            axial(el_lo, el_hi),
            [[0.0, 0.0, fa_off], [-arm.a3, 0.0, fa_off]],
            axial(w1_lo, w1_hi),
            axial(w2_lo, w2_hi),
            axial(w3_lo, arm.d6),
        ]
    )
    frames = np.array([0, 1, 2, 2, 3, 3, 4, 5])
    radii = np.array([base_r, sh_r, ua_r, el_r, fa_r, w1_r, w2_r, w3_r])
    for a in (local, radii, frames):
        a.setflags(write=False)
    return CapsuleModel(arm.name, frames, local, radii)


@dataclass(frozen=True)
class Capsules:
    """Capsules at many configurations, base frame.

    Attributes
    ----------
    ends_m : ndarray of shape (M, L, 2, 3), metres
        Segment end points of each capsule at each configuration.
    radii_m : ndarray of shape (L,), metres
    names : tuple of str, length L
    """

    ends_m: FloatArray
    radii_m: FloatArray
    names: tuple[str, ...]


@dataclass(frozen=True)
class CapsuleTool:
    """The tool as one capsule from the flange origin to the TCP.

    Attributes
    ----------
    radius_m : float
    """

    radius_m: float = 0.02

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius_m) and self.radius_m >= 0):
            raise ValueError(f"tool radius_m must be >= 0, got {self.radius_m}")


@dataclass(frozen=True)
class SphereTool:
    """The tool as spheres fixed to the flange (a gripper's fingers, a spindle and its burr).

    Attributes
    ----------
    centers_m : ndarray of shape (K, 3), metres
        Sphere centres in the flange frame.
    radii_m : ndarray of shape (K,), metres
    """

    centers_m: FloatArray
    radii_m: FloatArray

    def __post_init__(self) -> None:
        c = np.array(self.centers_m, dtype=np.float64)
        r = np.array(self.radii_m, dtype=np.float64).reshape(-1)
        if c.ndim != 2 or c.shape[1] != 3 or len(c) == 0:
            raise ValueError(f"tool centers_m must have shape (K, 3), K >= 1, got {c.shape}")
        if r.shape != (len(c),):
            raise ValueError(f"tool radii_m must have shape ({len(c)},), got {r.shape}")
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(r)) and np.all(r >= 0)):
            raise ValueError("tool centers_m and radii_m must be finite, radii >= 0")
        for name, a in (("centers_m", c), ("radii_m", r)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)


Tool = CapsuleTool | SphereTool


def _arm(arm: URModel | str) -> URModel:
    return ur_model(arm) if isinstance(arm, str) else arm


def _as_q(q_rad: FloatArray) -> FloatArray:
    q = np.asarray(q_rad, dtype=np.float64)
    if q.ndim == 1:
        q = q[None]
    if q.ndim != 2 or q.shape[1] != 6:
        raise ValueError(f"q_rad must have shape (M, 6), got {np.shape(q_rad)}")
    if not np.all(np.isfinite(q)):
        raise ValueError("q_rad has NaN or infinite values")
    return q


def _place(frames_T: FloatArray, frame_idx: NDArray[np.int64], local: FloatArray) -> FloatArray:
    """End points (M, L, 2, 3) of segments fixed in the given frames (M, 7, 4, 4)."""
    F = frames_T[:, frame_idx]  # (M, L, 4, 4)
    R, t = F[..., :3, :3], F[..., :3, 3]
    ends: FloatArray = np.einsum("mlij,lej->mlei", R, local) + t[:, :, None, :]
    return ends


def link_capsules(arm: URModel | str, q_rad: FloatArray, *, padding_m: float = 0.0) -> Capsules:
    """The arm's eight capsules at each configuration, base frame.

    Parameters
    ----------
    arm : URModel or str
    q_rad : ndarray of shape (M, 6) or (6,), radians
    padding_m : float
        Margin added to every radius (model and calibration error, cable guides).

    Returns
    -------
    Capsules
        ``ends_m`` of shape (M, 8, 2, 3), names :data:`LINK_NAMES`.
    """
    arm = _arm(arm)
    if not (np.isfinite(padding_m) and padding_m >= 0):
        raise ValueError(f"padding_m must be >= 0, got {padding_m}")
    cm = capsule_model(arm)
    ends = _place(joint_frames(arm, _as_q(q_rad)), cm.frames, cm.local_m)
    return Capsules(ends, cm.radii_m + padding_m, LINK_NAMES)


def _tool_local(T_flange_tcp: FloatArray, tool: Tool) -> tuple[FloatArray, FloatArray]:
    """Tool segments in the flange frame (K, 2, 3) and radii (K,)."""
    if isinstance(tool, CapsuleTool):
        local = np.stack([np.zeros(3), T_flange_tcp[:3, 3]])[None]
        return local, np.array([tool.radius_m])
    if isinstance(tool, SphereTool):
        return np.repeat(tool.centers_m[:, None, :], 2, axis=1), tool.radii_m
    raise ValueError(f"tool must be a CapsuleTool or a SphereTool, got {type(tool).__name__}")


def tool_capsules(T_base_flange: FloatArray, T_flange_tcp: FloatArray, tool: Tool) -> Capsules:
    """The tool's capsules at each flange pose, base frame.

    Parameters
    ----------
    T_base_flange : ndarray of shape (M, 4, 4)
    T_flange_tcp : ndarray of shape (4, 4)
    tool : CapsuleTool or SphereTool

    Returns
    -------
    Capsules
        One capsule ("tool") for a :class:`CapsuleTool`, ending at the TCP; one degenerate
        capsule (a sphere) per sphere of a :class:`SphereTool`.
    """
    T = np.asarray(T_base_flange, dtype=np.float64)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"T_base_flange must have shape (M, 4, 4), got {T.shape}")
    local, radii = _tool_local(check_rigid(T_flange_tcp, name="T_flange_tcp"), tool)
    ends = np.einsum("mij,lej->mlei", T[:, :3, :3], local) + T[:, None, None, :3, 3]
    return Capsules(ends, radii, (TOOL_NAME,) * len(radii))


# --------------------------------------------------------------------------------------------
# Exact distances of capsules to points, half-spaces and boxes


def segment_segment_closest(
    p0: FloatArray, p1: FloatArray, q0: FloatArray, q1: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The closest points of two segments, and their distance (exact; broadcasting).

    The clamped minimisation of Ericson's *Real-Time Collision Detection* (5.1.9), with its
    degenerate cases (a segment that is a point, parallel segments).

    Parameters
    ----------
    p0, p1 : ndarray of shape (..., 3)
        The first segment's ends.
    q0, q1 : ndarray of shape (..., 3)
        The second's.

    Returns
    -------
    distance : ndarray of shape (...)
    on_p, on_q : ndarray of shape (..., 3)
    """
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = np.einsum("...i,...i->...", d1, d1)
    e = np.einsum("...i,...i->...", d2, d2)
    f = np.einsum("...i,...i->...", d2, r)
    c = np.einsum("...i,...i->...", d1, r)
    b = np.einsum("...i,...i->...", d1, d2)
    tiny = 1e-18
    safe_a, safe_e = np.where(a > tiny, a, 1.0), np.where(e > tiny, e, 1.0)
    denom = a * e - b * b
    s = np.where(
        denom > tiny * np.maximum(a * e, tiny),
        np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0), 0.0, 1.0),
        0.0,
    )
    t = (b * s + f) / safe_e
    s = np.where(
        t < 0.0,
        np.clip(-c / safe_a, 0.0, 1.0),
        np.where(t > 1.0, np.clip((b - c) / safe_a, 0.0, 1.0), s),
    )
    t = np.clip(t, 0.0, 1.0)
    # A point for a segment: the other's closest point to it.
    s = np.where(a <= tiny, 0.0, s)
    t = np.where(a <= tiny, np.clip(f / safe_e, 0.0, 1.0), t)
    t = np.where(e <= tiny, 0.0, t)
    s = np.where((e <= tiny) & (a > tiny), np.clip(-c / safe_a, 0.0, 1.0), s)
    on_p = p0 + s[..., None] * d1
    on_q = q0 + t[..., None] * d2
    return np.linalg.norm(on_p - on_q, axis=-1), on_p, on_q


def segment_point_distance(a_m: FloatArray, b_m: FloatArray, p_m: FloatArray) -> FloatArray:
    """Distance from points to segments (broadcasting).

    Parameters
    ----------
    a_m, b_m : ndarray of shape (..., 3), metres
        Segment end points.
    p_m : ndarray of shape (..., 3), metres

    Returns
    -------
    ndarray of shape (...,), metres
    """
    a, b, p = (np.asarray(x, dtype=np.float64) for x in (a_m, b_m, p_m))
    ab = b - a
    denom = np.einsum("...i,...i->...", ab, ab)
    t = np.einsum("...i,...i->...", p - a, ab) / np.where(denom > 0, denom, 1.0)
    t = np.clip(np.where(denom > 0, t, 0.0), 0.0, 1.0)
    distance: FloatArray = np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)
    return distance


@dataclass(frozen=True)
class HalfSpace:
    """A plane the arm must stay on one side of: the allowed side is ``normal . x >= offset_m``.

    Attributes
    ----------
    normal : ndarray of shape (3,)
        Unit normal pointing into the allowed side, base frame (normalised on construction).
    offset_m : float
    name : str
    """

    normal: FloatArray
    offset_m: float = 0.0
    name: str = "plane"

    def __post_init__(self) -> None:
        n = np.array(self.normal, dtype=np.float64).reshape(-1)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9:
            raise ValueError(f"half-space normal must be a finite non-zero 3-vector, got {n}")
        if not np.isfinite(self.offset_m):
            raise ValueError("half-space offset_m must be finite")
        n = n / np.linalg.norm(n)
        n.setflags(write=False)
        object.__setattr__(self, "normal", n)

    @classmethod
    def mounting_surface(cls) -> HalfSpace:
        """The surface the base stands on: z = 0 of the base frame, for any mounting.

        UR's base frame sits on the base's mounting flange, so in base coordinates the mounting
        surface is z = 0 whether the arm stands on a table, hangs from a ceiling or sits on a
        wall; what differs between those is the rest of the cell (the floor below a wall-mounted
        arm has a horizontal normal in base coordinates: add it to ``Cell.planes``).
        """
        return cls(np.array([0.0, 0.0, 1.0]), 0.0, "mounting plane")

    def signed_distance_m(self, points_m: FloatArray) -> FloatArray:
        """Signed distance of points (..., 3) to the plane, positive on the allowed side."""
        return np.asarray(points_m) @ self.normal - self.offset_m


def capsule_halfspace_clearance(
    ends_m: FloatArray, radii_m: FloatArray, plane: HalfSpace
) -> tuple[FloatArray, FloatArray]:
    """Exact clearance of capsules to a half-space, and the nearest point of the plane.

    Parameters
    ----------
    ends_m : ndarray of shape (..., 2, 3), metres
    radii_m : ndarray broadcastable to (...,), metres
    plane : HalfSpace

    Returns
    -------
    clearance_m : ndarray of shape (...,)
        Distance of the capsule's surface from the plane on the allowed side (negative: it
        crosses the plane by that much).
    point_m : ndarray of shape (..., 3)
        The point of the plane nearest to the capsule's deepest point.
    """
    ends = np.asarray(ends_m, dtype=np.float64)
    s = plane.signed_distance_m(ends)
    k = np.argmin(s, axis=-1)
    s_min = np.take_along_axis(s, k[..., None], axis=-1)[..., 0]
    deepest = np.take_along_axis(ends, k[..., None, None].repeat(3, axis=-1), axis=-2)[..., 0, :]
    return s_min - radii_m, deepest - s_min[..., None] * plane.normal


@dataclass(frozen=True)
class Box:
    """A keep-out box: axis-aligned in its own frame, which is the base frame unless given.

    Attributes
    ----------
    min_m, max_m : ndarray of shape (3,), metres
        Opposite corners in the box's frame.
    T_base_box : ndarray of shape (4, 4), or None
        The box's pose; None: axis-aligned in the base frame.
    name : str
    """

    min_m: FloatArray
    max_m: FloatArray
    T_base_box: FloatArray | None = None
    name: str = "box"

    def __post_init__(self) -> None:
        lo = np.array(self.min_m, dtype=np.float64).reshape(-1)
        hi = np.array(self.max_m, dtype=np.float64).reshape(-1)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(np.r_[lo, hi])):
            raise ValueError("box min_m and max_m must be finite 3-vectors")
        if np.any(hi < lo):
            raise ValueError(f"box {self.name!r}: max_m {hi} must be >= min_m {lo} on every axis")
        for name, a in (("min_m", lo), ("max_m", hi)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        if self.T_base_box is not None:
            T = check_rigid(self.T_base_box, name=f"box {self.name!r} T_base_box").copy()
            T.setflags(write=False)
            object.__setattr__(self, "T_base_box", T)


def _box_sdf(p: FloatArray, centre: FloatArray, half: FloatArray) -> FloatArray:
    q = np.abs(p - centre) - half
    out = np.maximum(q, 0.0)
    outside: FloatArray = np.sqrt(np.einsum("...i,...i->...", out, out))
    inside: FloatArray = np.minimum(q.max(axis=-1), 0.0)
    return outside + inside


def _segment_box(
    a: FloatArray, ab: FloatArray, centre: FloatArray, half: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Minimum of the box's signed distance along segments a + t ab (N, 3): (t, distance)."""

    def f(t: FloatArray) -> FloatArray:
        return _box_sdf(a + t[:, None] * ab, centre, half)

    g = (np.sqrt(5.0) - 1.0) / 2.0
    lo, hi = np.zeros(len(a)), np.ones(len(a))
    x1, x2 = hi - g, lo + g
    f1, f2 = f(x1), f(x2)
    for _ in range(_GOLDEN_ITERATIONS):
        left = f1 <= f2  # the minimum is in [lo, x2]
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        x2_new = np.where(left, x1, lo + g * (hi - lo))
        x1_new = np.where(left, hi - g * (hi - lo), x2)
        f_new = f(np.where(left, x1_new, x2_new))
        f1, f2 = np.where(left, f_new, f2), np.where(left, f1, f_new)
        x1, x2 = x1_new, x2_new
    # The ends too, so a minimum at an end is exact rather than within the search tolerance.
    t_all = np.stack([np.zeros_like(lo), (lo + hi) / 2, np.ones_like(lo)], axis=1)
    d_all = _box_sdf(a[:, None, :] + t_all[..., None] * ab[:, None, :], centre, half)
    k = np.argmin(d_all, axis=1)
    rows = np.arange(len(a))
    return t_all[rows, k], d_all[rows, k]


def capsule_box_clearance(
    ends_m: FloatArray, radii_m: FloatArray, box: Box, *, far_m: float | None = None
) -> tuple[FloatArray, FloatArray]:
    """Clearance of capsules to a box, and the nearest point of the box's surface.

    The signed distance to a convex set is convex, so along a segment it has one minimum, found
    by golden-section search to 1e-7 of the segment's length (exact for practical purposes).

    Parameters
    ----------
    ends_m : ndarray of shape (..., 2, 3), metres, base frame
    radii_m : ndarray broadcastable to (...,), metres
    box : Box
    far_m : float, optional
        Capsules whose bounding sphere is at least this far from the box get that sphere's
        clearance (a lower bound) instead of the exact one: it saves the search.

    Returns
    -------
    clearance_m : ndarray of shape (...,)
        Negative: the capsule reaches that far into the box.
    point_m : ndarray of shape (..., 3)
        The point of the box's surface nearest to the capsule's axis, base frame.
    """
    ends = np.asarray(ends_m, dtype=np.float64)
    shape = ends.shape[:-2]
    r = np.broadcast_to(np.asarray(radii_m, dtype=np.float64), shape).reshape(-1)
    ends = ends.reshape(-1, 2, 3)
    if box.T_base_box is not None:
        T_box_base = invert_transform(box.T_base_box)
        ends = ends @ T_box_base[:3, :3].T + T_box_base[:3, 3]
    a, ab = ends[:, 0, :], ends[:, 1, :] - ends[:, 0, :]
    centre, half = (box.min_m + box.max_m) / 2, (box.max_m - box.min_m) / 2
    p = a + 0.5 * ab
    d = _box_sdf(p, centre, half) - 0.5 * np.linalg.norm(ab, axis=1)  # bounding sphere
    near = np.arange(len(a)) if far_m is None else np.flatnonzero(d - r < far_m)
    if len(near):
        t, d_near = _segment_box(a[near], ab[near], centre, half)
        d[near] = d_near
        p[near] = a[near] + t[:, None] * ab[near]
    # The nearest surface point: clamp into the box from outside; from inside, the nearest face.
    surface = np.clip(p, box.min_m, box.max_m)
    rel = p - centre
    axis = np.argmax(np.abs(rel) - half, axis=1)
    face = p.copy()
    rows = np.arange(len(p))
    face[rows, axis] = (centre + np.where(rel >= 0, half, -half))[rows, axis]
    surface = np.where((d < 0)[:, None], face, surface)
    if box.T_base_box is not None:
        surface = surface @ box.T_base_box[:3, :3].T + box.T_base_box[:3, 3]
    return (d - r).reshape(shape), surface.reshape(*shape, 3)


# --------------------------------------------------------------------------------------------
# The cell


@dataclass(frozen=True)
class Cell:
    """What the arm must not touch, base frame; the scan is preprocessed once, on construction.

    Attributes
    ----------
    mounting : HalfSpace or None
        The surface the base stands on (default: z = 0 of the base frame, see
        :meth:`HalfSpace.mounting_surface`). The base capsule (the base and the joint-1 housing,
        the first part of the shoulder) is exempt from it: it stands on it, and no joint can move
        it relative to it (joint 1 turns about the surface's normal), so testing it would only
        report the mounting itself. Every other link, the joint-2 housing ("shoulder") included,
        must stay ``margin_m`` above it; the shoulder is ``d1`` minus its radius above it in any
        configuration.
    planes : tuple of HalfSpace
        Other surfaces of the cell (walls, a floor below a wall-mounted arm): no link is exempt.
    boxes : tuple of Box
        Keep-out boxes.
    scan_points_m : ndarray of shape (N, 3), metres, base frame, or None
        The scanned workpiece (up to millions of points). Not kept: only its downsampled points.
    voxel_m : float
        Voxel size the scan is downsampled to (one real point per voxel, the one nearest the
        voxel's centre); 0 keeps every point. About a fifth of the margin you check with: the
        scan clearances are conservative by :attr:`scan_resolution_m` (at most sqrt(3) voxels).
    mounting_band_m : float
        Scan points within this distance of the mounting surface (or beyond it) are the mounting
        surface itself (a scan that sees the table): they are dropped, and the mounting plane is
        tested this much higher for every link but the base, which covers them.

    Derived attributes
    ------------------
    scan_m : ndarray of shape (N', 3)
        The points kept, base frame.
    scan_resolution_m : float
        Largest distance of an input point from the point kept for its voxel (0 without voxels).
    scan_dropped : int
        Input points dropped as the mounting surface.
    """

    mounting: HalfSpace | None = field(default_factory=HalfSpace.mounting_surface)
    planes: tuple[HalfSpace, ...] = ()
    boxes: tuple[Box, ...] = ()
    scan_points_m: InitVar[FloatArray | None] = None
    voxel_m: float = 0.002
    mounting_band_m: float = 0.005
    scan_m: FloatArray = field(init=False, repr=False, compare=False)
    scan_resolution_m: float = field(init=False, default=0.0)
    scan_dropped: int = field(init=False, default=0)
    _tree: cKDTree | None = field(init=False, repr=False, compare=False, default=None)

    def __post_init__(self, scan_points_m: FloatArray | None) -> None:
        object.__setattr__(self, "planes", tuple(self.planes))
        object.__setattr__(self, "boxes", tuple(self.boxes))
        for p in self.planes + ((self.mounting,) if self.mounting is not None else ()):
            if not isinstance(p, HalfSpace):
                raise ValueError(f"planes must be HalfSpace objects, got {type(p).__name__}")
        for b in self.boxes:
            if not isinstance(b, Box):
                raise ValueError(f"boxes must be Box objects, got {type(b).__name__}")
        if not (np.isfinite(self.voxel_m) and self.voxel_m >= 0):
            raise ValueError(f"voxel_m must be >= 0, got {self.voxel_m}")
        if not (np.isfinite(self.mounting_band_m) and self.mounting_band_m >= 0):
            raise ValueError(f"mounting_band_m must be >= 0, got {self.mounting_band_m}")
        points = np.zeros((0, 3))
        if scan_points_m is not None:
            points = np.asarray(scan_points_m, dtype=np.float64)
            if points.ndim != 2 or points.shape[1] != 3:
                raise ValueError(f"scan_points_m must have shape (N, 3), got {points.shape}")
            bad = ~np.isfinite(points).all(axis=1)
            if bad.any():
                raise ValueError(
                    f"scan_points_m has {int(bad.sum())} rows with NaN or infinite values; "
                    "remove them"
                )
        dropped = 0
        if self.mounting is not None and len(points):
            keep = self.mounting.signed_distance_m(points) > self.mounting_band_m
            dropped = int(len(points) - keep.sum())
            points = points[keep]
        kept, resolution = _voxel_downsample(points, self.voxel_m)
        kept.setflags(write=False)
        object.__setattr__(self, "scan_m", kept)
        object.__setattr__(self, "scan_resolution_m", resolution)
        object.__setattr__(self, "scan_dropped", dropped)
        tree = cKDTree(kept, balanced_tree=False, compact_nodes=False) if len(kept) else None
        object.__setattr__(self, "_tree", tree)

    @property
    def has_scan(self) -> bool:
        return self._tree is not None

    def obstacle_names(self) -> tuple[str, ...]:
        """What a motion is checked against, by the names collisions report."""
        names: tuple[str, ...] = ("mounting plane",) if self.mounting is not None else ()
        names += tuple(p.name for p in self.planes) + tuple(b.name for b in self.boxes)
        if self.has_scan:
            names += (f"scan ({len(self.scan_m)} points)",)
        return names


def _voxel_downsample(points: FloatArray, voxel_m: float) -> tuple[FloatArray, float]:
    """One real point per voxel (the nearest to the voxel's centre) and the largest distance of
    any input point from the point kept for its voxel."""
    if voxel_m == 0 or len(points) == 0:
        return points.copy(), 0.0
    # Column by column: numpy reduces an (N, 3) array along its rows several times slower.
    origin = np.array([points[:, k].min() for k in range(3)])
    top = np.array([points[:, k].max() for k in range(3)])
    scale = 1.0 / voxel_m
    # The largest voxel index along each axis is the farthest point's: (p - origin) * scale
    # never decreases as p grows, nor does its integer part (the kernel takes each point's).
    span = (top - origin) * scale
    with np.errstate(over="ignore"):  # an inf product is as refused as a finite one
        voxels = float(np.prod(np.floor(span) + 1.0))
    if voxels >= 2.0**62:  # before any cast to int64
        raise ValueError(
            f"the scan spans {np.floor(span) + 1} voxels of {voxel_m} m: too many; use a "
            "larger voxel_m or crop the scan (is it in millimetres?)"
        )
    dims = span.astype(np.int64) + 1
    kept, resolution = nearest_to_voxel_centres(points, origin, scale, dims)
    return points[kept], resolution


@dataclass(frozen=True)
class ContactZone:
    """Where the tool may touch the scanned workpiece: along the process path, on what lies no
    higher than a band above the tip.

    Attributes
    ----------
    path_m : ndarray of shape (N, 3), metres, base frame
        The planned TCP positions of the process phase.
    tool_axes : ndarray of shape (N, 3), base frame
        At each of them, the unit vector from the TCP along the tool towards the flange:
        heights above the tip are measured along it (a clamp that rises beside the path is not
        the surface the tip works on).
    radius_m : float
        Tolerance of the contact around the path (the tool's tip radius and the margin are added,
        see the module docstring).
    piece : ndarray of shape (N,), int, or None
        The path's pieces (0, 1, ... in order; see :func:`recon.arrays.piece_labels`): the zone
        follows each piece and never the untraced stretch between two. None: one piece.
    """

    path_m: FloatArray
    tool_axes: FloatArray
    radius_m: float = 0.005
    piece: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:

        p = np.array(self.path_m, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0 or not np.all(np.isfinite(p)):
            raise ValueError(f"contact path_m must be finite with shape (N, 3), got {p.shape}")
        axes = np.array(self.tool_axes, dtype=np.float64)
        if axes.shape != p.shape or not np.all(np.isfinite(axes)):
            raise ValueError(
                f"contact tool_axes must be finite with shape {p.shape}, got {axes.shape}"
            )
        norms = np.linalg.norm(axes, axis=1)
        if not np.all(norms > 0):
            raise ValueError("contact tool_axes must be non-zero vectors")
        axes = axes / norms[:, None]
        if not (np.isfinite(self.radius_m) and self.radius_m >= 0):
            raise ValueError(f"contact radius_m must be >= 0, got {self.radius_m}")
        for name, array in (("path_m", p), ("tool_axes", axes)):
            array.setflags(write=False)
            object.__setattr__(self, name, array)
        object.__setattr__(self, "piece", piece_labels(self.piece, len(p)))

    @classmethod
    def of_process(
        cls,
        arm: URModel | str,
        q_rad: FloatArray,
        T_flange_tcp: FloatArray,
        *,
        radius_m: float = 0.005,
        piece: NDArray[np.int64] | None = None,
    ) -> ContactZone:
        """The zone of a process path given as the arm's configurations along it.

        Parameters
        ----------
        arm : URModel or str
        q_rad : ndarray of shape (N, 6), radians
            The process phase's samples.
        T_flange_tcp : ndarray of shape (4, 4)
        radius_m : float
        piece : ndarray of shape (N,), int, optional

        Returns
        -------
        ContactZone
            The TCP's positions, and the tool's axis from the TCP to the flange (the capsule's;
            for a TCP at the flange, which has none, the flange's z backwards).
        """
        flange = joint_frames(_arm(arm), _as_q(q_rad))[:, 6]
        tcp = flange @ check_rigid(T_flange_tcp, name="T_flange_tcp")
        towards_flange = flange[:, :3, 3] - tcp[:, :3, 3]
        has_length = np.linalg.norm(towards_flange, axis=1)[:, None] > 1e-6
        return cls(
            path_m=tcp[:, :3, 3],
            tool_axes=np.where(has_length, towards_flange, -flange[:, :3, 2]),
            radius_m=radius_m,
            piece=piece,
        )

    def points(self, spacing_m: float) -> FloatArray:
        """Points along each piece at most ``spacing_m`` apart, shape (K, 3)."""
        return self.points_and_axes(spacing_m)[0]

    def points_and_axes(self, spacing_m: float) -> tuple[FloatArray, FloatArray]:
        """Points along each piece at most ``spacing_m`` apart (K, 3), and the tool's axis at
        each (K, 3, unit; interpolated between the path's points)."""

        assert self.piece is not None  # labelled by __post_init__
        points, axes = [], []
        for rows in piece_slices(self.piece):
            resampled, at = _resample_polyline(self.path_m[rows], spacing_m, with_position=True)
            points.append(resampled)
            local = self.tool_axes[rows]
            axis = np.column_stack(
                [np.interp(at, np.arange(len(local)), local[:, k]) for k in range(3)]
            )
            axes.append(axis / np.linalg.norm(axis, axis=1)[:, None])
        return np.concatenate(points), np.concatenate(axes)


# --------------------------------------------------------------------------------------------
# Scan clearances from a k-d tree


def _scan_clearance(
    tree: cKDTree,
    points: FloatArray,
    ends: FloatArray,
    radius: float,
    *,
    horizon_m: float,
    refine_below_m: float,
    fine_m: float,
    workers: int = -1,
) -> tuple[FloatArray, FloatArray]:
    """Lower bounds on the clearance of one capsule at many configurations to a point set.

    Coarse to fine. A stretch of the axis of half-length ``w`` around a query point at distance
    ``d`` from the nearest point has clearance between ``d - w - r`` and ``d - r``. The whole
    segment around its midpoint first; where that is inside the horizon, stretches of about the
    radius; then, branch and bound, the stretches that may hold the capsule's minimum (their
    lower bound more than ``fine_m / 2`` below the smallest upper bound) and are below
    ``refine_below_m`` are halved until ``w <= fine_m / 2``. Every value is a lower bound on the
    true clearance, below it by at most ``fine_m / 2`` where the truth is between ``-_DEEP_M``
    and ``refine_below_m``; stretches certainly deeper inside are not refined (their depth is of
    no use, and queries from inside a closed scanned surface are slow). Values at or beyond the
    horizon are ``horizon_m``.

    Parameters
    ----------
    ends : ndarray of shape (J, 2, 3)
    radius : float

    Returns
    -------
    clearance_m : ndarray of shape (J,)
    point_m : ndarray of shape (J, 3)
        The nearest point found (NaN where nothing is within the horizon).
    """
    J = len(ends)
    clear = np.full(J, horizon_m)
    point = np.full((J, 3), np.nan)
    if J == 0:
        return clear, point
    a, b = ends[:, 0], ends[:, 1]
    length = np.linalg.norm(b - a, axis=1)
    half_max = float(length.max()) / 2
    d0, _ = tree.query(
        (a + b) / 2, distance_upper_bound=horizon_m + radius + half_max, workers=workers
    )
    lb0 = d0 - length / 2 - radius
    rows = np.flatnonzero(lb0 < horizon_m)
    if len(rows) == 0:
        return clear, point
    # Stretches of the axis, spacing at most h1, one query point each.
    R = len(rows)
    h1 = float(np.clip(radius, 0.005, 0.05))
    n1 = max(2, int(np.ceil(float(length[rows].max()) / h1)) + 1)
    ar, abr, lr = a[rows], (b - a)[rows], length[rows]
    unit = abr / np.where(lr > 0, lr, 1.0)[:, None]
    leaf_row = np.repeat(np.arange(R), n1)
    leaf_t = (np.linspace(0.0, 1.0, n1)[None, :] * lr[:, None]).reshape(-1)
    leaf_w = np.repeat(lr / (n1 - 1) / 2, n1)
    d, idx = tree.query(
        ar[leaf_row] + leaf_t[:, None] * unit[leaf_row],
        distance_upper_bound=horizon_m + radius + h1,
        workers=workers,
    )
    best_ub = np.full(R, np.inf)
    np.minimum.at(best_ub, leaf_row, d - radius)
    while True:
        lb = d - leaf_w - radius
        # Branch and bound: a stretch whose lower bound is within fine/2 of the best upper bound
        # cannot improve the answer by more than that; nor one above refine_below_m.
        split = (
            (leaf_w > fine_m / 2)
            & (lb < refine_below_m)
            & (lb < best_ub[leaf_row] - fine_m / 2)
            & (d - radius > -_DEEP_M)
        )
        if not split.any():
            break
        # Halve each such stretch (clipped to the segment) and query the halves' centres.
        r_s, t_s, w_s = leaf_row[split], leaf_t[split], leaf_w[split]
        lo = np.maximum(t_s - w_s, 0.0)
        hi = np.minimum(t_s + w_s, lr[r_s])
        mid = (lo + hi) / 2
        c_row = np.r_[r_s, r_s]
        c_t = np.r_[(lo + mid) / 2, (mid + hi) / 2]
        c_w = np.r_[(hi - lo) / 4, (hi - lo) / 4]
        c_d, c_idx = tree.query(
            ar[c_row] + c_t[:, None] * unit[c_row],
            distance_upper_bound=refine_below_m + radius + h1,
            workers=workers,
        )
        np.minimum.at(best_ub, c_row, c_d - radius)
        keep = ~split
        leaf_row = np.r_[leaf_row[keep], c_row]
        leaf_t = np.r_[leaf_t[keep], c_t]
        leaf_w = np.r_[leaf_w[keep], c_w]
        d = np.r_[d[keep], c_d]
        idx = np.r_[idx[keep], c_idx]
    lb = d - leaf_w - radius
    # The smallest lower bound of each row, and its point.
    order = np.lexsort((lb, leaf_row))
    first = order[np.r_[True, leaf_row[order][1:] != leaf_row[order][:-1]]]
    best = lb[first]
    clear[rows] = np.minimum(np.maximum(best, lb0[rows]), horizon_m)
    found = np.isfinite(d[first])
    point[rows[found]] = points[idx[first][found]]
    return clear, point


# --------------------------------------------------------------------------------------------
# The report


@dataclass(frozen=True)
class Collision:
    """The first sample period in which the arm or the tool may come closer than the margin.

    Attributes
    ----------
    sample : int
        Index of the sample the period starts at (the motion from it to the next sample).
    t_s : float or None
        Its time, when the trajectory's times were given.
    phase : Phase
    link : str
        One of :data:`LINK_NAMES`, or "tool".
    obstacle : str
        "scan", or the name of the plane or box.
    kind : ObstacleKind
    point_m : ndarray of shape (3,), metres, base frame
        The obstacle's nearest point found: a scan point, the foot on the plane, the box surface.
    clearance_m : float
        The conservative clearance over the period (negative: penetration).
    margin_m : float
    """

    sample: int
    t_s: float | None
    phase: Phase
    link: str
    obstacle: str
    kind: ObstacleKind
    point_m: FloatArray
    clearance_m: float
    margin_m: float

    def describe(self) -> str:
        """One line in words, for a terminal."""
        x, y, z = np.asarray(self.point_m) * 1000.0
        what = {
            ObstacleKind.SCAN: "the scan",
            ObstacleKind.PLANE: f"the {self.obstacle}",
            ObstacleKind.BOX: f"box {self.obstacle!r}",
            ObstacleKind.NONE: "nothing",
            ObstacleKind.SELF: f"the arm's own {self.obstacle}",
        }[self.kind]
        when = f"at {self.t_s:.2f} s" if self.t_s is not None else f"at sample {self.sample}"
        c = self.clearance_m * 1000.0
        depth = (
            f"{-c:.1f} mm inside"
            if c < 0
            else f"{c:.1f} mm away, within the {self.margin_m * 1000:.1f} mm margin"
        )
        verb = "touches" if c < 0 else "comes too close to"
        return (
            f"{self.link} {verb} {what} at ({x:.1f}, {y:.1f}, {z:.1f}) mm during "
            f"{self.phase.name.lower()} {when} (sample {self.sample}), {depth}"
        )


@dataclass(frozen=True)
class CollisionReport:
    """Clearances of a whole motion, per sample period and per link.

    Attributes
    ----------
    names : tuple of str, length L
        The capsules: :data:`LINK_NAMES` then the tool's ("tool").
    clearance_m : ndarray of shape (M,), metres
        Smallest clearance of any capsule during the motion from sample m to sample m + 1 (the
        last: at the last sample); a lower bound on the true clearance, below it by at most
        :attr:`tolerance_m` where it is below :attr:`exact_below_m`. Scan clearances beyond
        ``horizon_m`` are reported as ``horizon_m``; ``inf`` when the cell is empty.
    link_clearance_m : ndarray of shape (M, L), metres
        The same per capsule.
    nearest_link : ndarray of shape (M,), int
        Index into ``names`` of the capsule with the smallest clearance.
    nearest_kind : ndarray of shape (M,), int8
        :class:`ObstacleKind` of the obstacle it is nearest to.
    first_collision : Collision or None
        The first period whose clearance is below the margin; None when the motion is clear.
    margin_m : float
    motion_bound_m : float
        The most any point of the arm or tool can move between a checked configuration and the
        nearest one (half the largest metric step between checks), at most ``f * margin``.
    tolerance_m : float
        How far below the true clearance at a sample a reported value can be (where below
        ``exact_below_m``): twice the motion bound, plus the scan's resolution and query spacing.
    exact_below_m : float
    scan_resolution_m : float
    contact_radius_m : float or None
        Radius of the tube around the process path whose scan points the tool ignores while
        in contact (None without a contact zone).
    exempt_links : tuple of str
        The capsules the contact exemption applies to.
    checked_samples : ndarray of shape (K,)
        The (fractional) sample indices whose configurations were checked.
    phase : ndarray of shape (M,), int8
    t_s : ndarray of shape (M,), or None
    obstacles : tuple of str
        What the motion was checked against (:meth:`Cell.obstacle_names`).
    """

    names: tuple[str, ...]
    clearance_m: FloatArray
    link_clearance_m: FloatArray
    nearest_link: NDArray[np.int64]
    nearest_kind: NDArray[np.int8]
    first_collision: Collision | None
    margin_m: float
    motion_bound_m: float
    tolerance_m: float
    exact_below_m: float
    scan_resolution_m: float
    contact_radius_m: float | None
    exempt_links: tuple[str, ...]
    checked_samples: FloatArray
    phase: NDArray[np.int8]
    t_s: FloatArray | None = None
    obstacles: tuple[str, ...] = ()

    @property
    def clear(self) -> bool:
        """True when no sample period comes closer than the margin."""
        return self.first_collision is None

    def link_min_clearance_m(self) -> dict[str, float]:
        """Smallest clearance of each capsule over the whole motion (the tool's spheres merged)."""
        out: dict[str, float] = {}
        for j, name in enumerate(self.names):
            v = float(self.link_clearance_m[:, j].min()) if len(self.clearance_m) else np.inf
            out[name] = min(out.get(name, np.inf), v)
        return out

    def lines(self) -> list[str]:
        """A short report for a terminal."""
        m = len(self.clearance_m)
        out = []
        if self.first_collision is not None:
            out.append("COLLISION: " + self.first_collision.describe())
        else:
            out.append(f"clear: no part comes within the {self.margin_m * 1000:.1f} mm margin")
        if m:
            i = int(np.argmin(self.clearance_m))
            when = f"{self.t_s[i]:.2f} s" if self.t_s is not None else f"sample {i}"
            kind = ObstacleKind(int(self.nearest_kind[i])).name.lower()
            out.append(
                f"smallest clearance {self.clearance_m[i] * 1000:.1f} mm "
                f"({self.names[int(self.nearest_link[i])]} to {kind}, "
                f"{Phase(int(self.phase[i])).name.lower()} at {when})"
            )
        if self.obstacles:
            out.append("against: " + ", ".join(self.obstacles))
        out.append(
            f"checked {len(self.checked_samples)} configurations for {m} samples; motion "
            f"between checks <= {self.motion_bound_m * 1000:.2f} mm, clearances conservative "
            f"by <= {self.tolerance_m * 1000:.2f} mm"
        )
        if self.contact_radius_m is not None:
            out.append(
                f"contact: {', '.join(self.exempt_links)} may touch the scan within "
                f"{self.contact_radius_m * 1000:.1f} mm of the process path"
            )
        return out


# --------------------------------------------------------------------------------------------
# The motion check

_BIG = 1e6  # stands for "no obstacle" inside the arithmetic; reported as inf


def _tip_cut_mounting(
    tool_ends_m: FloatArray,
    tool_radii_m: FloatArray,
    tcp_m: FloatArray,
    reach_m: FloatArray,
    T_ft: FloatArray,
    tool: Tool,
    raised: HalfSpace,
    band_m: float,
    mounting: HalfSpace,
    contact_radius_m: float,
    zone_radius_m: float,
    whole: tuple[FloatArray, FloatArray],
) -> tuple[FloatArray, FloatArray]:
    """The tool's clearance to the mounting plane without the tip's own region, for contact.

    A tip working on a plate that lies on the mounting surface is within millimetres of it: a
    capsule's round end reaches its radius below the TCP, and the mounting plane is tested
    ``band_m`` higher when there is a scan. So the tool's part within the contact radius of the
    TCP (the tip, as for the scan's contact exemption) is left out: for a capsule, the lowest
    point of the capsule outside the ball of radius ``R`` around the TCP, exactly (it leaves
    the ball at ``sqrt(R^2 - r^2)`` along the axis; the flange's half sphere is always
    counted); for spheres, those lying wholly within ``R`` of the TCP are left out. The rest of
    the tool is tested against the (raised) plane in full. What is left out is fixed in the
    flange frame, so the clearance moves no faster than the tool does.

    The tip is left out only where the TCP is no deeper than the contact zone's radius below
    the real mounting plane, by a slack of the distance to the neighbouring checked
    configurations (``reach_m``), so that the whole sample period around a configuration is on
    the same side of that rule and the bound between configurations still holds; a path below
    the table has its whole tool tested.

    Parameters
    ----------
    tool_ends_m : ndarray of shape (J, T, 2, 3)
        The tool's segments at the checked configurations (a capsule: flange to TCP).
    tool_radii_m : ndarray of shape (T,)
    tcp_m : ndarray of shape (J, 3)
    reach_m : ndarray of shape (J,)
    T_ft : ndarray of shape (4, 4)
    tool : CapsuleTool or SphereTool
    raised, mounting : HalfSpace
        The plane tested (``band_m`` above the mounting surface) and the mounting surface.
    band_m, contact_radius_m, zone_radius_m : float
    whole : tuple of ndarray (J, T) and (J, T, 3)
        The whole tool's clearances and nearest points, kept where the tip is not left out.

    Returns
    -------
    clearance_m : ndarray of shape (J, T)
    point_m : ndarray of shape (J, T, 3)
    """
    c, p = whole[0].copy(), whole[1].copy()
    depth_m = -mounting.signed_distance_m(tcp_m)
    rows = np.flatnonzero(depth_m + reach_m <= zone_radius_m)
    if len(rows) == 0:
        return c, p
    if isinstance(tool, CapsuleTool):
        length_m = float(np.linalg.norm(T_ft[:3, 3]))
        cut_m = np.sqrt(max(contact_radius_m**2 - tool.radius_m**2, 0.0))
        if cut_m >= length_m:
            c[rows] = _BIG
            return c, p
        tip_m, flange_m = tool_ends_m[rows, 0, 1], tool_ends_m[rows, 0, 0]  # (n, 3) each
        axis = (flange_m - tip_m) / length_m
        cos = axis @ raised.normal
        sin = np.sqrt(np.clip(1.0 - cos**2, 0.0, None))
        r = tool.radius_m
        # Lowest point of the capsule outside the ball: on the flange's half sphere, or on the
        # cylinder where it leaves the ball (axial cut_m, radial r, on the plane's side).
        lowest = raised.signed_distance_m(flange_m) - r
        at = flange_m
        ring = raised.signed_distance_m(tip_m) + cut_m * cos - r * sin
        lower = ring < lowest
        lowest = np.where(lower, ring, lowest)
        at = np.where(lower[:, None], tip_m + cut_m * axis, at)
        c[rows, 0] = lowest
        p[rows, 0] = at - (raised.signed_distance_m(at) + band_m)[:, None] * raised.normal
        return c, p
    reach_from_tcp = np.linalg.norm(tool.centers_m - T_ft[:3, 3], axis=1) + tool.radii_m
    tip = np.flatnonzero(reach_from_tcp <= contact_radius_m)
    c[np.ix_(rows, tip)] = _BIG
    return c, p


def _joint_weights(
    arm: URModel, frame_idx: NDArray[np.int64], local: FloatArray, radii: FloatArray
) -> FloatArray:
    """B_i: a bound on the distance of any capsule point moved by joint i from that joint's axis,
    for any configuration (see the module docstring)."""
    a, d = arm.a, arm.d
    link_len = np.hypot(a, d)  # |o_k - o_(k-1)|, k = 1..6
    rho = np.linalg.norm(local, axis=2).max(axis=1) + radii
    w = np.zeros(6)
    for i in range(1, 7):
        moved = frame_idx >= i
        if not moved.any():
            continue
        chain = np.array([link_len[i:f].sum() for f in frame_idx[moved]])
        w[i - 1] = float((abs(a[i - 1]) + chain + rho[moved]).max())
    return w


def _check_points(C: FloatArray, step_m: float) -> FloatArray:
    """Fractional sample indices to check so that consecutive ones are at most ``step_m`` apart
    in the motion metric ``C`` (cumulative, one value per sample)."""
    M = len(C)
    if M == 1:
        return np.zeros(1)
    # Periods longer than half a step are "fast": their ends are checked. Between those, picks
    # from a grid of spacing g = step - (longest slow period) are at most g + that apart.
    step = np.diff(C)
    fast = np.flatnonzero(step > step_m / 2)
    slow_max = float(np.max(step, initial=0.0, where=step <= step_m / 2))
    g = step_m - slow_max
    grid = np.arange(0.0, C[-1] + g, g)
    picks = np.searchsorted(C, grid, side="right") - 1
    parts = [picks.astype(np.float64), fast, fast + 1.0, np.array([0.0, M - 1.0])]
    long_ = np.flatnonzero(step > step_m)
    if len(long_):
        n = np.ceil(step[long_] / step_m).astype(np.int64)
        owner = np.repeat(long_, n - 1)
        k = np.arange(int((n - 1).sum())) - np.repeat(np.cumsum(n - 1) - (n - 1), n - 1) + 1
        parts.append(owner + k / np.repeat(n, n - 1))
    return np.unique(np.concatenate(parts))


def _interpolate(q: FloatArray, u: FloatArray) -> FloatArray:
    if len(q) == 1:
        return np.repeat(q, len(u), axis=0)
    i0 = np.clip(np.floor(u).astype(np.int64), 0, len(q) - 2)
    frac = (u - i0)[:, None]
    return q[i0] + frac * (q[i0 + 1] - q[i0])


@overload
def _resample_polyline(
    path: FloatArray, spacing_m: float, *, with_position: Literal[False] = False
) -> FloatArray: ...
@overload
def _resample_polyline(
    path: FloatArray, spacing_m: float, *, with_position: Literal[True]
) -> tuple[FloatArray, FloatArray]: ...
def _resample_polyline(
    path: FloatArray, spacing_m: float, *, with_position: bool = False
) -> FloatArray | tuple[FloatArray, FloatArray]:
    """Points on a polyline (N, 3), at most ``spacing_m`` apart along it, both ends included;
    with ``with_position``, also each one's fractional index into ``path`` (K,)."""
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
    if s[-1] == 0:
        return (path[:1], np.zeros(1)) if with_position else path[:1]
    n = int(np.ceil(s[-1] / spacing_m)) + 1
    targets = np.linspace(0.0, s[-1], n)
    points = np.column_stack([np.interp(targets, s, path[:, k]) for k in range(3)])
    if not with_position:
        return points
    # Repeated points (zero-length steps) would make s non-increasing for the inverse lookup.
    keep = np.r_[True, np.diff(s) > 0]
    return points, np.interp(targets, s[keep], np.flatnonzero(keep).astype(np.float64))


def _travel_windows(
    arm: URModel, q: FloatArray, phase: NDArray[np.int8], T_ft: FloatArray, radius_m: float
) -> NDArray[np.bool_]:
    """Samples in the last ``radius_m`` of TCP travel of each approach run and the first of each
    retract run."""
    out = np.zeros(len(q), dtype=bool)
    idx = np.flatnonzero((phase == Phase.APPROACH) | (phase == Phase.RETRACT))
    if len(idx) == 0:
        return out
    run = np.cumsum(np.r_[True, phase[1:] != phase[:-1]])[idx]
    tcp = (joint_frames(arm, q[idx])[:, 6] @ T_ft)[:, :3, 3]
    same = (run[1:] == run[:-1]) & (np.diff(idx) == 1)
    cum = np.r_[0.0, np.cumsum(np.where(same, np.linalg.norm(np.diff(tcp, axis=0), axis=1), 0))]
    first = np.r_[True, ~same]
    last = np.r_[~same, True]
    start_of = np.maximum.accumulate(np.where(first, np.arange(len(idx)), 0))
    end_of = np.minimum.accumulate(np.where(last, np.arange(len(idx)), len(idx))[::-1])[::-1]
    from_start = cum - cum[start_of]
    to_end = cum[end_of] - cum
    approach = phase[idx] == Phase.APPROACH
    out[idx] = np.where(approach, to_end <= radius_m, from_start <= radius_m)
    return out


def check_motion(
    arm: URModel | str,
    q_rad: FloatArray,
    phase: NDArray[np.int8],
    cell: Cell,
    *,
    T_flange_tcp: FloatArray,
    tool: Tool | None = None,
    margin_m: float = 0.01,
    contact_zone: ContactZone | None = None,
    t_s: FloatArray | None = None,
    motion_bound_fraction: float = 0.25,
    horizon_m: float = 0.1,
    workers: int = -1,
    self_check: bool = True,
) -> CollisionReport:
    """Check the continuous motion through a joint trajectory against a cell, and the arm
    against itself.

    Parameters
    ----------
    arm : URModel or str
    q_rad : ndarray of shape (M, 6), radians
        Samples at the controller rate; the motion between samples is taken as linear in joints.
    phase : ndarray of shape (M,), int
        :class:`Phase` of each sample.
    cell : Cell
    T_flange_tcp : ndarray of shape (4, 4)
        The TCP in the flange frame.
    tool : CapsuleTool or SphereTool, optional
        Default: ``CapsuleTool(radius_m=0.02)``, from the flange to the TCP.
    margin_m : float
        Required clearance; closer is reported as a collision.
    contact_zone : ContactZone, optional
        Where the tool may touch the scan (the process path); None: nowhere.
    t_s : ndarray of shape (M,), seconds, optional
        Sample times, for the report.
    motion_bound_fraction : float in (0, 1]
        ``f``: configurations are checked often enough that no point moves more than
        ``f * margin_m`` from the nearest checked one (see the module docstring).
    horizon_m : float
        Scan and box clearances beyond this are reported as this (a lower bound): it bounds the
        work. At least ``margin_m * (1 + 8 f) + 10 mm`` is used, so that clearances near the
        margin are always resolved.
    workers : int
        Threads for the k-d tree queries (-1: all cores).
    self_check : bool
        Check the pairs of :data:`SELF_PAIRS` (the tool and the wrists against the base, the
        shoulder and the upper arm, ...) too, reported as the arm's own obstacles.

    Returns
    -------
    CollisionReport

    Raises
    ------
    ValueError
        Shapes, non-finite values, unknown phases, a non-rigid ``T_flange_tcp``, a margin that
        is not positive, ``motion_bound_fraction`` outside (0, 1], ``horizon_m < margin_m``.
    """
    arm = _arm(arm)
    q = _as_q(q_rad)
    phase, t_s = _checked_phase_and_times(phase, t_s, len(q))
    if not (np.isfinite(margin_m) and margin_m > 0):
        raise ValueError(f"margin_m must be > 0, got {margin_m}")
    if not (0 < motion_bound_fraction <= 1):
        raise ValueError(f"motion_bound_fraction must be in (0, 1], got {motion_bound_fraction}")
    if not (np.isfinite(horizon_m) and horizon_m >= margin_m):
        raise ValueError(f"horizon_m must be >= margin_m ({margin_m}), got {horizon_m}")
    if not isinstance(cell, Cell):
        raise ValueError(f"cell must be a Cell, got {type(cell).__name__}")
    T_ft = check_rigid(T_flange_tcp, name="T_flange_tcp")
    tool = CapsuleTool() if tool is None else tool

    # Configurations to check: at most step_m apart in the motion metric.
    step_m = 2.0 * motion_bound_fraction * margin_m
    sweep = _sweep(arm, q, T_ft, tool, step_m)
    fine_m = motion_bound_fraction * margin_m / 2  # spacing of the fine scan queries
    refine_below = margin_m + 2 * step_m + _REFINE_EXTRA_M
    horizon_m = max(horizon_m, refine_below)  # exact up to exact_below_m, whatever the horizon
    worst_tolerance = 2 * motion_bound_fraction * margin_m + fine_m / 2 + cell.scan_resolution_m
    exemption = _contact_exemption(
        arm, q, phase, T_ft, tool, cell, contact_zone, sweep, margin_m, worst_tolerance
    )

    # Clearances at the checked configurations: the mounting plane, planes and boxes, the arm
    # against itself; then the scan, in full and (for the exempt columns) without the contact.
    obstacles = _Obstacles()
    full = _Nearest.empty(len(sweep.u), len(sweep.names))
    mounting_tool = _mounting_clearances(
        full, obstacles, sweep, cell, T_ft, tool, contact_zone, exemption.contact_radius_m
    )
    for plane in cell.planes:
        c, p = capsule_halfspace_clearance(sweep.ends, sweep.radii, plane)
        full.take(c, p, obstacles.add(plane.name, ObstacleKind.PLANE))
    for box in cell.boxes:
        c, p = capsule_box_clearance(sweep.ends, sweep.radii, box, far_m=horizon_m)
        full.take(c, p, obstacles.add(box.name, ObstacleKind.BOX))
    self_tol = _self_clearances(full, obstacles, sweep) if self_check else 0.0
    exempt = full.copy()
    if mounting_tool is not None:
        # The whole tool against the mounting plane everywhere; where the tip is exempt, the
        # tool without its tip (see _tip_cut_mounting).
        c, p, (c_cut, p_cut), k_mounting, tool_cols = mounting_tool
        full.take(c, p, k_mounting, tool_cols)
        exempt.take(c_cut, p_cut, k_mounting, tool_cols)
    scan_tol = 0.0
    if cell.has_scan:
        scan_tol = cell.scan_resolution_m + fine_m / 2
        exempt = _scan_clearances(
            full, exempt, obstacles, sweep, cell, exemption, horizon_m, refine_below, fine_m,
            workers,
        )  # fmt: skip

    bound, gov, use_ex = _period_bounds(sweep, exemption, full, exempt)
    M, L = bound.shape
    every_col = np.arange(L)[None, :]
    obst = np.where(use_ex, exempt.obstacle[gov, every_col], full.obstacle[gov, every_col])
    nearest = np.argmin(bound, axis=1)
    clearance = bound[np.arange(M), nearest]
    kinds = np.array([int(k) for k in obstacles.kinds] + [int(ObstacleKind.NONE)], dtype=np.int8)
    nearest_kind = kinds[obst[np.arange(M), nearest]]
    first = None
    bad = clearance < margin_m
    if bad.any():
        s = int(np.argmax(bad))
        j, g = int(nearest[s]), int(gov[s, nearest[s]])
        k = int(obst[s, j])
        pt = (exempt if use_ex[s, j] else full).point_m[g, j]
        first = Collision(
            sample=s,
            t_s=float(t_s[s]) if t_s is not None else None,
            phase=Phase(int(phase[s])),
            link=sweep.names[j],
            obstacle=obstacles.names[k] if k >= 0 else "",
            kind=obstacles.kinds[k] if k >= 0 else ObstacleKind.NONE,
            point_m=np.array(pt),
            clearance_m=float(clearance[s]),
            margin_m=margin_m,
        )
    empty = bound >= _BIG / 2
    bound[empty] = np.inf
    clearance = np.where(clearance >= _BIG / 2, np.inf, clearance)
    J = len(sweep.u)
    motion_bound = float(np.diff(sweep.v).max()) / 2 if J > 1 else 0.0
    u = sweep.u
    for a in (bound, clearance, nearest, nearest_kind, u, phase):
        a.setflags(write=False)
    return CollisionReport(
        names=sweep.names,
        clearance_m=clearance,
        link_clearance_m=bound,
        nearest_link=nearest,
        nearest_kind=nearest_kind,
        first_collision=first,
        margin_m=margin_m,
        motion_bound_m=motion_bound,
        tolerance_m=2 * motion_bound + max(scan_tol, self_tol),
        exact_below_m=refine_below - step_m,
        scan_resolution_m=cell.scan_resolution_m,
        contact_radius_m=exemption.contact_radius_m,
        exempt_links=tuple(n for n, e in zip(sweep.names, exemption.columns, strict=True) if e),
        checked_samples=u,
        phase=phase,
        t_s=t_s,
        obstacles=cell.obstacle_names(),
    )


# --- the steps of check_motion -----------------------------------------------------------------


def _checked_phase_and_times(
    phase: NDArray[np.int8], t_s: FloatArray | None, M: int
) -> tuple[NDArray[np.int8], FloatArray | None]:
    """``phase`` (M,) as known :class:`Phase` values in int8 and ``t_s`` (M,) as finite floats,
    or a ValueError naming what is wrong."""
    phase = np.asarray(phase)
    if phase.shape != (M,) or not np.issubdtype(phase.dtype, np.integer):
        raise ValueError(f"phase must be an integer array of shape ({M},), got {phase.shape}")
    known = [int(p) for p in Phase]
    if not np.isin(phase, known).all():
        bad = sorted(set(np.unique(phase).tolist()) - set(known))
        raise ValueError(f"phase has unknown values {bad}; known: {known} (see Phase)")
    if t_s is not None:
        t_s = np.asarray(t_s, dtype=np.float64)
        if t_s.shape != (M,) or not np.all(np.isfinite(t_s)):
            raise ValueError(f"t_s must be finite with shape ({M},), got {t_s.shape}")
    return phase.astype(np.int8), t_s


@dataclass(frozen=True)
class _Sweep:
    """The motion as the check sees it: L capsules (the arm's links, then the tool's) placed at
    J checked configurations between M samples.

    Attributes
    ----------
    names : tuple of L str
    frame_idx : ndarray of shape (L,), int
        The DH frame each capsule is fixed in (6: the flange).
    local : ndarray of shape (L, 2, 3), metres
        Each capsule's segment in its frame.
    radii : ndarray of shape (L,), metres
    C : ndarray of shape (M,), metres
        The motion metric at the samples (how far a point of the arm can have moved).
    u : ndarray of shape (J,)
        The checked configurations, in sample-index units (fractional between samples).
    v : ndarray of shape (J,), metres
        The motion metric at them.
    frames : ndarray of shape (J, 7, 4, 4)
        The DH frames at them.
    ends : ndarray of shape (J, L, 2, 3), metres
        The capsules' segments at them.
    j0, j1 : ndarray of shape (M - 1,), int
        Each sample period [m, m + 1] is covered by the check intervals j0[m] .. j1[m].
    """

    names: tuple[str, ...]
    frame_idx: NDArray[np.int64]
    local: FloatArray
    radii: FloatArray
    C: FloatArray
    u: FloatArray
    v: FloatArray
    frames: FloatArray
    ends: FloatArray
    j0: NDArray[np.intp]
    j1: NDArray[np.intp]


def _sweep(arm: URModel, q: FloatArray, T_ft: FloatArray, tool: Tool, step_m: float) -> _Sweep:
    """The capsules at configurations at most ``step_m`` apart in the motion metric."""
    # Geometry: the arm's capsules and the tool's, each fixed in one DH frame (6: the flange).
    cm = capsule_model(arm)
    tool_local, tool_r = _tool_local(T_ft, tool)
    frame_idx = np.r_[cm.frames, np.full(len(tool_r), 6)]
    local = np.concatenate([cm.local_m, tool_local])
    radii = np.r_[cm.radii_m, tool_r]
    names = LINK_NAMES + (TOOL_NAME,) * len(tool_r)
    M = len(q)
    w = _joint_weights(arm, frame_idx, local, radii)
    C = np.r_[0.0, np.cumsum(np.abs(np.diff(q, axis=0)) @ w)]
    u = _check_points(C, step_m)
    v = np.interp(u, np.arange(M), C)
    frames = joint_frames(arm, _interpolate(q, u))
    ends = _place(frames, frame_idx, local)
    m_all = np.arange(M - 1)
    j0 = np.searchsorted(u, m_all, side="right") - 1
    j1 = np.searchsorted(u, m_all + 1, side="left") - 1
    return _Sweep(names, frame_idx, local, radii, C, u, v, frames, ends, j0, j1)


@dataclass(frozen=True)
class _Exemption:
    """Where the tool may touch the scan (see :class:`ContactZone` and the module docstring).

    Attributes
    ----------
    columns : ndarray of shape (L,), bool
        The capsules exempt (the tool's, and wrist 3 when it lies within the contact radius).
    samples : ndarray of shape (M,), bool
        The samples exempt (the process, and the travel windows near it).
    contact_radius_m : float or None
        None without a contact zone.
    reduced : (tree, points (P, 3), rows (R,)) or None
        The scan without what the contact touches, as a tree (None if nothing is left), and the
        checked configurations that bound an exempt sample period.
    full_rows : ndarray of shape (F,), int, or None
        The checked configurations whose clearance to the full scan the exempt capsules need:
        those that bound a sample period not exempt (the others' bounds read the exempt table,
        so their full-scan clearance is never used). None: every configuration.
    """

    columns: NDArray[np.bool_]
    samples: NDArray[np.bool_]
    contact_radius_m: float | None = None
    reduced: tuple[cKDTree | None, FloatArray, NDArray[np.intp]] | None = None
    full_rows: NDArray[np.intp] | None = None


def _contact_exemption(
    arm: URModel,
    q: FloatArray,
    phase: NDArray[np.int8],
    T_ft: FloatArray,
    tool: Tool,
    cell: Cell,
    contact_zone: ContactZone | None,
    sweep: _Sweep,
    margin_m: float,
    worst_tolerance: float,
) -> _Exemption:
    """What is exempt from the scan check, and the scan it sees instead."""
    L, M = len(sweep.names), len(q)
    exempt_cols = np.zeros(L, dtype=bool)
    exempt = np.zeros(M, dtype=bool)
    if contact_zone is None:
        return _Exemption(exempt_cols, exempt)
    cm = capsule_model(arm)
    p_tcp = T_ft[:3, 3]
    if isinstance(tool, CapsuleTool):
        tip_r = tool.radius_m
    else:
        near = np.linalg.norm(tool.centers_m - p_tcp, axis=1) <= (
            tool.radii_m + contact_zone.radius_m
        )
        tip_r = float(tool.radii_m[near].max()) if near.any() else 0.0
    # The tip lies this close to the surface it works on, plus what the check may
    # underestimate: the contact itself must not read as a collision (module docstring).
    contact_radius = contact_zone.radius_m + tip_r + margin_m + worst_tolerance
    exempt_cols[len(LINK_NAMES) :] = True
    w3_lo = cm.local_m[7, 0, 2] - arm.d6  # wrist 3 in the flange frame: z from w3_lo to 0
    w3 = segment_point_distance(np.array([0.0, 0.0, w3_lo]), np.zeros(3), p_tcp)
    if w3 - cm.radii_m[7] <= contact_radius:
        exempt_cols[7] = True
    exempt = (phase == Phase.PROCESS) | _travel_windows(arm, q, phase, T_ft, contact_radius)
    if cell._tree is None or not exempt.any():
        return _Exemption(exempt_cols, exempt, contact_radius)
    # Points on the path a quarter of the radius apart: what is within the radius of them is
    # within the radius of the path (the tube exempted is never wider). Of those, only what lies
    # no higher than the band above the tip, along the tool's axis there: the surface the tip
    # works on, never a fixture rising beside it.
    on_path, axes = contact_zone.points_and_axes(contact_radius / 4)
    band = contact_zone.radius_m + margin_m + worst_tolerance
    pts = cell.scan_m
    touched = _touched_by_contact(cell._tree, pts, on_path, axes, contact_radius, band)
    rest = pts[~touched]
    tree = cKDTree(rest, balanced_tree=False, compact_nodes=False) if len(rest) else None
    # Only the configurations that bound an exempt sample period need the exempt scan; only
    # those that bound one not exempt need the full scan for the exempt capsules.
    exempt_period = exempt[:-1] & exempt[1:]
    need_exempt = _bounding_configurations(sweep, exempt_period)
    need_exempt[-1] |= bool(exempt[-1])
    need_full = _bounding_configurations(sweep, ~exempt_period)
    need_full[-1] |= not exempt[-1]
    return _Exemption(
        exempt_cols,
        exempt,
        contact_radius,
        (tree, rest, np.flatnonzero(need_exempt)),
        np.flatnonzero(need_full),
    )


_PAIR_CHUNK = 65_536  # (path point, scan point) pairs per step: a few MB, in cache


def _touched_by_contact(
    tree: cKDTree,
    points_m: FloatArray,
    on_path_m: FloatArray,
    axes: FloatArray,
    radius_m: float,
    band_m: float,
) -> NDArray[np.bool_]:
    """The scan points the contact touches: within ``radius_m`` of a point on the path and no
    higher than ``band_m`` above it along the tool's axis there.

    Parameters
    ----------
    tree : cKDTree
        Of ``points_m``.
    points_m : ndarray of shape (P, 3)
    on_path_m, axes : ndarray of shape (K, 3)
        Points along the path and the tool's unit axis at each.

    Returns
    -------
    ndarray of shape (P,), bool
    """
    # The pairs as two index arrays in one call (a ball query per path point returns Python
    # lists: millions of ints to convert), then their heights a cache-sized chunk at a time.
    pairs = cKDTree(on_path_m).sparse_distance_matrix(tree, radius_m, output_type="ndarray")
    at, hit = pairs["i"], pairs["j"]
    touched = np.zeros(len(points_m), dtype=bool)
    for start in range(0, len(hit), _PAIR_CHUNK):
        h, a = hit[start : start + _PAIR_CHUNK], at[start : start + _PAIR_CHUNK]
        height = np.einsum("ij,ij->i", points_m[h] - on_path_m[a], axes[a])
        touched[h[height <= band_m]] = True
    return touched


def _bounding_configurations(sweep: _Sweep, periods: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Which checked configurations bound at least one of the given sample periods.

    Parameters
    ----------
    periods : ndarray of shape (M - 1,), bool
        The sample periods (from sample m to m + 1) in question.

    Returns
    -------
    ndarray of shape (J,), bool
        Configuration j bounds period m when ``j0[m] <= j <= j1[m] + 1`` (see :class:`_Sweep`).
    """
    J = len(sweep.u)
    rows = np.flatnonzero(periods)
    count = np.zeros(J + 1, dtype=np.int64)
    np.add.at(count, sweep.j0[rows], 1)
    np.add.at(count, sweep.j1[rows] + 2, -1)
    return np.cumsum(count)[:J] > 0


class _Obstacles:
    """The obstacles met so far, in the order their indices were given."""

    def __init__(self) -> None:
        self.names: list[str] = []
        self.kinds: list[ObstacleKind] = []

    def add(self, name: str, kind: ObstacleKind) -> int:
        self.names.append(name)
        self.kinds.append(kind)
        return len(self.names) - 1


@dataclass
class _Nearest:
    """Per checked configuration and capsule, the least clearance found so far, its obstacle
    (-1: none yet) and its nearest point there: arrays of shape (J, L), (J, L), (J, L, 3)."""

    clearance_m: FloatArray
    obstacle: NDArray[np.int64]
    point_m: FloatArray

    @classmethod
    def empty(cls, J: int, L: int) -> _Nearest:
        return cls(
            np.full((J, L), _BIG), np.full((J, L), -1, dtype=np.int64), np.full((J, L, 3), np.nan)
        )

    def copy(self) -> _Nearest:
        return _Nearest(self.clearance_m.copy(), self.obstacle.copy(), self.point_m.copy())

    def take(self, c: FloatArray, p: FloatArray, k: int, cols: slice = slice(None)) -> None:
        """Keep clearances ``c`` (J, l) and points ``p`` (J, l, 3) of obstacle ``k`` where they
        are smaller, in columns ``cols``."""
        better = c < self.clearance_m[:, cols]
        self.clearance_m[:, cols] = np.where(better, c, self.clearance_m[:, cols])
        self.obstacle[:, cols] = np.where(better, k, self.obstacle[:, cols])
        self.point_m[:, cols] = np.where(better[..., None], p, self.point_m[:, cols])


_MountingTool = tuple[FloatArray, FloatArray, tuple[FloatArray, FloatArray], int, slice]


def _mounting_clearances(
    full: _Nearest,
    obstacles: _Obstacles,
    sweep: _Sweep,
    cell: Cell,
    T_ft: FloatArray,
    tool: Tool,
    contact_zone: ContactZone | None,
    contact_radius: float | None,
) -> _MountingTool | None:
    """The arm's links against the mounting plane (taken into ``full``); the tool's clearances
    to it, whole and cut at the tip, are returned for the caller to take after the exempt copy
    is made: (c, p, (c_cut, p_cut), obstacle index, tool columns). None without a mounting."""
    if cell.mounting is None:
        return None
    L = len(sweep.names)
    band = cell.mounting_band_m if (cell.has_scan or cell.scan_dropped) else 0.0
    raised = HalfSpace(cell.mounting.normal, cell.mounting.offset_m + band, cell.mounting.name)
    # Tested ``band`` higher: that covers the scan points dropped as the mounting surface.
    c, p = capsule_halfspace_clearance(sweep.ends, sweep.radii, raised)
    p = p - band * raised.normal
    c[:, 0] = _BIG  # the base stands on it
    k_mounting = obstacles.add(cell.mounting.name, ObstacleKind.PLANE)
    arm_cols = slice(0, len(LINK_NAMES))
    full.take(c[:, arm_cols], p[:, arm_cols], k_mounting, arm_cols)
    tool_cols = slice(len(LINK_NAMES), L)
    cut = (c[:, tool_cols], p[:, tool_cols])
    if contact_zone is not None and contact_radius is not None:  # set together
        v = sweep.v
        reach = np.maximum(np.r_[np.diff(v), 0.0], np.r_[0.0, np.diff(v)])  # (J,)
        tcp = (sweep.frames[:, 6] @ T_ft)[:, :3, 3]
        cut = _tip_cut_mounting(
            sweep.ends[:, tool_cols], sweep.radii[tool_cols], tcp, reach, T_ft, tool, raised,
            band, cell.mounting, contact_radius, contact_zone.radius_m, cut,
        )  # fmt: skip
    return (c[:, tool_cols], p[:, tool_cols], cut, k_mounting, tool_cols)


def _self_clearances(full: _Nearest, obstacles: _Obstacles, sweep: _Sweep) -> float:
    """The arm against itself (the pairs of :data:`SELF_PAIRS`), taken into ``full``; returns
    the tolerance this adds (m).

    Both capsules of a pair move: between two checked configurations their distance changes by
    up to twice what one point moves, so each configuration's clearance carries the spacing to
    its farther neighbour less, and the static bound still holds.
    """
    J, L = len(sweep.u), len(sweep.names)
    ends, radii = sweep.ends, sweep.radii
    spacing = np.diff(sweep.v) if J > 1 else np.zeros(0)
    reach = np.maximum(np.r_[spacing, 0.0], np.r_[0.0, spacing])  # (J,)
    self_index: dict[int, int] = {}
    for i, j in SELF_PAIRS:
        # The tool is column 8, or columns 8.. (one per sphere of a SphereTool).
        for jj in [j] if j < len(LINK_NAMES) else range(len(LINK_NAMES), L):
            distance, on_i, on_j = segment_segment_closest(
                ends[:, i, 0], ends[:, i, 1], ends[:, jj, 0], ends[:, jj, 1]
            )
            c = distance - radii[i] - radii[jj] - reach
            for mine, other, point in ((i, jj, on_j), (jj, i, on_i)):
                if other not in self_index:
                    self_index[other] = obstacles.add(sweep.names[other], ObstacleKind.SELF)
                full.take(c[:, None], point[:, None], self_index[other], slice(mine, mine + 1))
    return float(reach.max()) if J > 1 else 0.0


def _scan_clearances(
    full: _Nearest,
    exempt: _Nearest,
    obstacles: _Obstacles,
    sweep: _Sweep,
    cell: Cell,
    exemption: _Exemption,
    horizon_m: float,
    refine_below_m: float,
    fine_m: float,
    workers: int,
) -> _Nearest:
    """The scan, taken into ``full`` for every capsule and configuration and into ``exempt``
    (without what the contact touches) for the exempt capsules where they need it; returns the
    exempt table to use from here (``full`` itself when nothing is exempt)."""
    k_scan = obstacles.add("scan", ObstacleKind.SCAN)
    every_row = np.arange(len(sweep.u))
    columns = exemption.columns
    full_rows = every_row if exemption.full_rows is None else exemption.full_rows
    # (tree, its points, the configurations, the table, its columns)
    sources = [
        (cell._tree, cell.scan_m, every_row, full, np.flatnonzero(~columns)),
        (cell._tree, cell.scan_m, full_rows, full, np.flatnonzero(columns)),
    ]
    if exemption.reduced is not None:
        tree_ex, pts_ex, rows_ex = exemption.reduced
        sources.append((tree_ex, pts_ex, rows_ex, exempt, np.flatnonzero(columns)))
    for tree, pts, rows, table, source_cols in sources:
        if tree is None or len(rows) == 0:
            continue
        for col in source_cols:
            c, p = _scan_clearance(
                tree,
                pts,
                sweep.ends[rows, col],
                float(sweep.radii[col]),
                horizon_m=horizon_m,
                refine_below_m=refine_below_m,
                fine_m=fine_m,
                workers=workers,
            )
            c = c - cell.scan_resolution_m
            better = c < table.clearance_m[rows, col]
            table.clearance_m[rows[better], col] = c[better]
            table.obstacle[rows[better], col] = k_scan
            table.point_m[rows[better], col] = p[better]
    if exemption.reduced is None:  # no exemption: the same as the full scan
        return full
    # Columns not exempt see the full scan in every period.
    not_exempt = ~exemption.columns
    exempt.clearance_m[:, not_exempt] = full.clearance_m[:, not_exempt]
    exempt.obstacle[:, not_exempt] = full.obstacle[:, not_exempt]
    exempt.point_m[:, not_exempt] = full.point_m[:, not_exempt]
    return exempt


def _period_bounds(
    sweep: _Sweep, exemption: _Exemption, full: _Nearest, exempt: _Nearest
) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.bool_]]:
    """Per sample period, the conservative clearance of each capsule from the checked
    configurations around it (the last row: the last sample's own).

    Returns
    -------
    bound : ndarray of shape (M, L), metres
    gov : ndarray of shape (M, L), int
        The checked configuration that governs each bound.
    use_ex : ndarray of shape (M, L), bool
        Whether the bound comes from the exempt table.
    """
    C, v, j0, j1 = sweep.C, sweep.v, sweep.j0, sweep.j1
    M, L, J = len(C), len(sweep.names), len(sweep.u)
    samples, columns = exemption.samples, exemption.columns
    c_full, c_ex = full.clearance_m, exempt.clearance_m
    use_ex_period = (samples[:-1] & samples[1:])[:, None] & columns[None, :]  # (M-1, L)
    bound = np.empty((M, L))
    gov = np.empty((M, L), dtype=np.int64)
    use_ex = np.zeros((M, L), dtype=bool)
    if M > 1:
        m = np.arange(M - 1)
        n = j1 - j0 + 1
        starts = np.cumsum(n) - n
        pm = np.repeat(m, n)
        pj = np.arange(int(n.sum())) - np.repeat(starts, n) + j0[pm]
        alpha = (np.maximum(C[pm], v[pj]) - v[pj])[:, None]
        beta = (np.minimum(C[pm + 1], v[pj + 1]) - v[pj])[:, None]
        D = (v[pj + 1] - v[pj])[:, None]
        ex = use_ex_period[pm]
        cj = np.where(ex, c_ex[pj], c_full[pj])
        cj1 = np.where(ex, c_ex[pj + 1], c_full[pj + 1])
        a_c = np.clip((cj - cj1 + D) / 2, alpha, beta)
        left, right = cj - a_c, cj1 - D + a_c
        piece = np.maximum(left, right)
        piece_gov = np.where(left >= right, pj[:, None], pj[:, None] + 1)
        res, res_gov = piece[starts].copy(), piece_gov[starts].copy()
        for r in range(1, int(n.max())):
            sel = np.flatnonzero(n > r)
            idx = starts[sel] + r
            better = piece[idx] < res[sel]
            res[sel] = np.where(better, piece[idx], res[sel])
            res_gov[sel] = np.where(better, piece_gov[idx], res_gov[sel])
        bound[:-1], gov[:-1], use_ex[:-1] = res, res_gov, use_ex_period
    last_ex = samples[-1] & columns
    bound[-1] = np.where(last_ex, c_ex[-1], c_full[-1])
    gov[-1] = J - 1
    use_ex[-1] = last_ex
    return bound, gov, use_ex
