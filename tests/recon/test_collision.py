"""Collision checking of whole motions: exact primitives, the arms' capsules, the cell, the
contact exemption, the bound between samples, and agreement with an independent brute force."""

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from recon.collision import (
    CAPSULES_MM,
    LINK_NAMES,
    PUBLISHED_REACH_M,
    Box,
    CapsuleTool,
    Cell,
    ContactZone,
    HalfSpace,
    ObstacleKind,
    Phase,
    SphereTool,
    capsule_box_clearance,
    capsule_halfspace_clearance,
    check_motion,
    link_capsules,
    segment_point_distance,
    tool_capsules,
)
from recon.kinematics import (
    HOME_Q_RAD,
    UR_MODELS,
    follow_path,
    forward,
    inverse,
    joint_frames,
    model,
)
from recon.plan_params import PlanParams

MODELS = sorted(UR_MODELS)


def _tcp_transform(length_m: float) -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = length_m
    return T


# --- exact primitives ----------------------------------------------------------------------


def test_segment_point_distance_is_exact():
    a, b = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    points = np.array([[0.5, 0.3, 0.4], [-0.3, 0.4, 0.0], [1.6, 0.0, 0.8], [0.2, 0.0, 0.0]])
    np.testing.assert_allclose(segment_point_distance(a, b, points), [0.5, 0.5, 1.0, 0.0])
    # A degenerate segment is a point.
    np.testing.assert_allclose(segment_point_distance(a, a, points[:1]), [np.sqrt(0.5)])


def test_capsule_halfspace_clearance_is_exact():
    ends = np.array([[[0.0, 0.0, 0.3], [0.2, 0.0, 0.1]], [[0.0, 0.0, -0.02], [0.0, 0.0, 0.5]]])
    c, p = capsule_halfspace_clearance(ends, np.array([0.05, 0.01]), HalfSpace([0, 0, 1]))
    np.testing.assert_allclose(c, [0.05, -0.03])
    np.testing.assert_allclose(p, [[0.2, 0.0, 0.0], [0.0, 0.0, 0.0]], atol=1e-15)
    # A wall x >= -0.3 with its normal not normalised by the caller.
    wall = HalfSpace([2.0, 0.0, 0.0], -0.3, "wall")
    c, _ = capsule_halfspace_clearance(ends[:1], 0.05, wall)
    np.testing.assert_allclose(c, [0.25])


BOX = Box([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], name="unit")


@pytest.mark.parametrize(
    ("a", "b", "r", "expected"),
    [
        ((2.0, 0.5, 0.5), (2.0, 0.5, 0.7), 0.1, 0.9),  # parallel to a face
        ((2.0, 2.0, 2.0), (3.0, 3.0, 3.0), 0.1, np.sqrt(3.0) - 0.1),  # pointing at a corner
        ((2.0, -1.0, 0.5), (2.0, 2.0, 0.5), 0.0, 1.0),  # passing a face, closest mid-segment
        ((1.5, 1.5, -1.0), (1.5, 1.5, 2.0), 0.2, np.sqrt(0.5) - 0.2),  # along an edge
        ((0.5, 0.5, 0.5), (0.5, 0.5, 0.6), 0.05, -0.5 - 0.05),  # inside, at the centre
        ((-1.0, 0.5, 0.3), (2.0, 0.5, 0.3), 0.0, -0.3),  # through it, nearest face z = 0
    ],
)
def test_capsule_box_clearance_analytic(a, b, r, expected):
    ends = np.array([[a, b]], dtype=float)
    c, p = capsule_box_clearance(ends, r, BOX)
    assert c[0] == pytest.approx(expected, abs=1e-7)
    # The reported point is on the box's surface.
    assert abs(_point_box_signed(p, BOX.min_m, BOX.max_m)[0]) < 1e-7


def _point_box_signed(p, lo, hi):
    """Signed distance of points to an axis-aligned box, written independently of the module."""
    outside = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=-1)
    inside = np.minimum(p - lo, hi - p).min(axis=-1)
    return np.where(np.all((p >= lo) & (p <= hi), axis=-1), -inside, outside)


def test_capsule_box_clearance_matches_dense_sampling_for_a_posed_box():
    rng = np.random.default_rng(4)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -0.5, 0.9]).as_matrix()
    T[:3, 3] = [0.2, -0.1, 0.3]
    box = Box([-0.1, -0.2, -0.05], [0.1, 0.2, 0.05], T_base_box=T)
    ends = rng.uniform(-0.4, 0.8, (300, 2, 3))
    c, p = capsule_box_clearance(ends, 0.02, box)
    s = np.linspace(0.0, 1.0, 4001)
    pts = ends[:, :1] + s[None, :, None] * (ends[:, 1:] - ends[:, :1])
    local = (pts - T[:3, 3]) @ T[:3, :3]
    dense = _point_box_signed(local, box.min_m, box.max_m).min(axis=1) - 0.02
    seg_len = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    # Dense sampling overestimates the minimum by at most half a sampling step.
    assert np.all(c <= dense + 1e-9)
    assert np.all(dense - c <= seg_len / 4000 / 2 + 1e-9)
    # The nearest points are on the box's surface.
    q = np.abs((p - T[:3, 3]) @ T[:3, :3]) - box.max_m
    assert np.abs(q.max(axis=1)).max() < 1e-9


# --- the arms' capsules ------------------------------------------------------------------


@pytest.mark.parametrize("name", MODELS)
def test_wrist_3_capsule_ends_at_the_flange_and_the_tool_at_the_tcp(name):
    arm = model(name)
    q = np.random.default_rng(1).uniform(-np.pi, np.pi, (50, 6))
    caps = link_capsules(arm, q)
    assert caps.ends_m.shape == (50, 8, 2, 3) and caps.names == LINK_NAMES
    flange = forward(arm, q)
    np.testing.assert_allclose(caps.ends_m[:, 7, 1], flange[:, :3, 3], atol=1e-12)
    # Wrist 3 lies along the flange's z-axis.
    axis = caps.ends_m[:, 7, 1] - caps.ends_m[:, 7, 0]
    np.testing.assert_allclose(np.cross(axis, flange[:, :3, 2]), 0.0, atol=1e-12)
    T_ft = np.eye(4)
    T_ft[:3, :3] = Rotation.from_euler("x", 30, degrees=True).as_matrix()
    T_ft[:3, 3] = [0.0, 0.05, 0.18]
    tool = tool_capsules(flange, T_ft, CapsuleTool(0.015))
    np.testing.assert_allclose(tool.ends_m[:, 0, 0], flange[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(tool.ends_m[:, 0, 1], (flange @ T_ft)[:, :3, 3], atol=1e-12)
    spheres = tool_capsules(flange, T_ft, SphereTool([[0, 0, 0.1], [0, 0.05, 0.18]], [0.03, 0.0]))
    np.testing.assert_allclose(spheres.ends_m[:, 1, 0], (flange @ T_ft)[:, :3, 3], atol=1e-12)
    # The base column stands on the mounting plane, on the base axis, at least as wide as the
    # footprint UR's specifications give.
    np.testing.assert_allclose(caps.ends_m[:, 0, 0], 0.0, atol=1e-15)
    assert 2 * caps.radii_m[0] >= PUBLISHED_FOOTPRINT_M[name]


#: Base diameter ("footprint") in UR's technical specifications, metres.
PUBLISHED_FOOTPRINT_M = {
    "ur3e": 0.128,
    "ur5e": 0.149,
    "ur10e": 0.190,
    "ur16e": 0.190,
    "ur20": 0.245,
    "ur30": 0.245,
    "ur3": 0.118,
    "ur5": 0.149,
    "ur10": 0.190,
}


#: shoulder_offset of config/<model>/physical_parameters.yaml (Universal_Robots_ROS2_Description),
#: millimetres: the tube's lateral offset that the DH model folds into d4.
PUBLISHED_SHOULDER_OFFSET_MM = {
    "ur3e": 120.0,
    "ur5e": 138.0,
    "ur10e": 176.2,
    "ur16e": 176.0,
    "ur20": 260.0,
    "ur30": 260.0,
    "ur3": 119.8,
    "ur5": 135.85,
    "ur10": 220.941,  # the CB3 UR10's mesh origin; its tube is at 176 mm (see CAPSULES_MM)
}


@pytest.mark.parametrize("name", MODELS)
def test_the_upper_arm_tube_is_where_the_real_one_is_not_on_the_dh_origins(name):
    arm = model(name)
    q = np.random.default_rng(2).uniform(-np.pi, np.pi, (20, 6))
    caps = link_capsules(arm, q)
    F = joint_frames(arm, q)
    shoulder, elbow = F[:, 1, :3, 3], F[:, 2, :3, 3]
    # The capsule's ends are the DH joint points moved along the joint axis by the offset.
    offset = np.linalg.norm(caps.ends_m[:, 2, 0] - elbow, axis=1)
    np.testing.assert_allclose(offset, CAPSULES_MM[name][5] / 1000.0, atol=1e-12)
    np.testing.assert_allclose(
        np.linalg.norm(caps.ends_m[:, 2, 1] - shoulder, axis=1), offset, atol=1e-12
    )
    if name != "ur10":
        assert abs(CAPSULES_MM[name][5] - PUBLISHED_SHOULDER_OFFSET_MM[name]) <= 2.5
    # A tube along the DH origins would lie outside the real one.
    assert offset[0] > caps.radii_m[2]


@pytest.mark.parametrize("name", MODELS)
def test_stretched_out_capsules_reach_the_published_reach(name):
    arm = model(name)
    q = np.zeros((4, 6))
    q[:, 3] = [-np.pi / 2, 0.0, np.pi / 2, np.pi]  # the wrist pointing out, up, in, down
    caps = link_capsules(arm, q)
    radial = np.hypot(caps.ends_m[..., 0], caps.ends_m[..., 1]) + caps.radii_m[None, :, None]
    extent = radial.max()
    flange = np.hypot(*forward(arm, q)[:, :2, 3].T).max()
    # The capsules cover the arm as far as UR says it reaches, and add no more beyond the
    # flange than the wrist's own radius (plus a centimetre).
    assert extent >= PUBLISHED_REACH_M[name]
    assert extent <= flange + caps.radii_m[5:].max() + 0.01
    # Stretched along -x of the base, as UR's zero position is.
    assert caps.ends_m[..., 0].min() < -(abs(arm.a2) + abs(arm.a3)) + 1e-9


# --- the cell ----------------------------------------------------------------------------


def test_scan_preprocessing_keeps_every_point_within_the_stated_resolution():
    rng = np.random.default_rng(5)
    # A dense scan of a gently curved surface, half of it the table the arm stands on.
    xy = rng.uniform([0.2, -0.3], [0.6, 0.3], (200_000, 2))
    z = np.where(xy[:, 0] < 0.3, 0.0, 0.05 + 0.1 * np.sin(4 * xy[:, 1]) ** 2)
    pts = np.c_[xy, z + rng.normal(scale=0.001, size=len(z))]
    cell = Cell(scan_points_m=pts, voxel_m=0.004, mounting_band_m=0.005)
    kept = cell.scan_m
    above = pts[pts[:, 2] > 0.005]
    assert cell.scan_dropped == len(pts) - len(above)
    assert len(kept) < len(above) / 5
    d, _ = cKDTree(kept).query(above)
    assert d.max() <= cell.scan_resolution_m + 1e-12
    assert cell.scan_resolution_m <= np.sqrt(3) * 0.004
    # Kept points are real scan points.
    d_real, _ = cKDTree(above).query(kept)
    assert d_real.max() == 0.0


def test_bad_cells_and_arguments_raise():
    with pytest.raises(ValueError, match="NaN"):
        Cell(scan_points_m=np.array([[0.0, 0.0, np.nan]]))
    with pytest.raises(ValueError, match="max_m"):
        Box([0, 0, 1], [1, 1, 0])
    with pytest.raises(ValueError, match="normal"):
        HalfSpace([0, 0, 0])
    q = np.zeros((3, 6))
    with pytest.raises(ValueError, match="phase"):
        check_motion("ur5e", q, np.array([0, 1, 7]), Cell(), T_flange_tcp=np.eye(4))
    with pytest.raises(ValueError, match="margin"):
        check_motion("ur5e", q, np.zeros(3, int), Cell(), T_flange_tcp=np.eye(4), margin_m=0)
    with pytest.raises(ValueError, match="T_flange_tcp"):
        check_motion("ur5e", q, np.zeros(3, int), Cell(), T_flange_tcp=np.ones((4, 4)))
    with pytest.raises(ValueError, match="unknown robot"):
        link_capsules("ur99", q)


# --- whole motions -----------------------------------------------------------------------


def _down_poses(positions: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(positions), 1, 1))
    T[:, :3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:, :3, 3] = positions
    return T


def test_elbow_down_dips_below_the_table_elbow_up_does_not():
    arm = model("ur5e")
    n = 600
    s = 0.5 - 0.5 * np.cos(np.pi * np.linspace(0.0, 1.0, n))
    flange = _down_poses(np.c_[0.45 - 0.1 * s, np.full(n, -0.15), 0.45 - 0.35 * s])
    sol = inverse(arm, flange)
    # Branches 0 and 1 differ in the elbow only; tell them apart by where the elbow is.
    assert sol.valid[:, :2].all()
    qs = [np.unwrap(sol.q_rad[:, b], axis=0) for b in (0, 1)]
    elbow_z = [joint_frames(arm, q)[:, 2, 2, 3].mean() for q in qs]
    q_up, q_down = (qs[0], qs[1]) if elbow_z[0] > elbow_z[1] else (qs[1], qs[0])
    phase = np.full(n, Phase.TRANSIT)
    t = np.arange(n) / arm.control_rate_hz
    kw = {
        "T_flange_tcp": _tcp_transform(0.05),
        "tool": CapsuleTool(0.01),
        "margin_m": 0.01,
        "t_s": t,
    }
    up = check_motion(arm, q_up, phase, Cell(), **kw)
    assert up.clear, up.lines()
    down = check_motion(arm, q_down, phase, Cell(), **kw)
    hit = down.first_collision
    assert hit is not None and hit.kind == ObstacleKind.PLANE
    assert hit.obstacle == "mounting plane" and hit.link in ("upper arm", "elbow")
    # Ground truth: the exact plane clearance of the arm's links at every sample.
    caps = link_capsules(arm, q_down)
    c, _ = capsule_halfspace_clearance(caps.ends_m[:, 1:], caps.radii_m[1:], HalfSpace([0, 0, 1]))
    first_true = int(np.argmax(c.min(axis=1) < 0.01))
    assert LINK_NAMES[1 + int(np.argmin(c[first_true]))] in ("upper arm", "elbow")
    # Reported no later than the truth, and only as early as the stated conservatism allows.
    assert hit.sample <= first_true
    assert c[hit.sample : hit.sample + 2].min() < 0.01 + down.tolerance_m
    assert hit.t_s == pytest.approx(t[hit.sample])
    assert "mounting plane" in down.lines()[0] and "during transit" in down.lines()[0]


def _box_scan(lo, hi, spacing):
    """Points on the top and the four sides of a box (a scanned workpiece on the table)."""
    xs, ys, zs = (np.arange(lo[i], hi[i] + 1e-9, spacing) for i in range(3))
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    faces = [np.c_[X.ravel(), Y.ravel(), np.full(X.size, hi[2])]]
    for x in (lo[0], hi[0]):
        Yy, Z = np.meshgrid(ys, zs, indexing="ij")
        faces.append(np.c_[np.full(Yy.size, x), Yy.ravel(), Z.ravel()])
    for y in (lo[1], hi[1]):
        Xx, Z = np.meshgrid(xs, zs, indexing="ij")
        faces.append(np.c_[Xx.ravel(), np.full(Xx.size, y), Z.ravel()])
    return np.vstack(faces)


WORKPIECE_LO, WORKPIECE_HI = (0.30, -0.35, 0.0), (0.60, 0.05, 0.10)


@pytest.fixture(scope="module")
def workpiece_cell():
    return Cell(scan_points_m=_box_scan(WORKPIECE_LO, WORKPIECE_HI, 0.002), voxel_m=0.002)


def _contact_plan(arm, tilt_deg, *, branch=None, rate_hz=500.0, speed_m_s=0.05, top_m=None):
    """Approach 50 mm straight down onto the workpiece's top (``top_m``, default its box's),
    a 200 mm process line on it, retract straight up; the tool points down, tilted about the
    line by ``tilt_deg``."""
    top = WORKPIECE_HI[2] if top_m is None else top_m
    start, end = np.array([0.45, -0.25, top]), np.array([0.45, -0.05, top])

    def line(a, b):
        n = max(2, int(round(np.linalg.norm(b - a) / speed_m_s * rate_hz)))
        s = 0.5 - 0.5 * np.cos(np.pi * np.linspace(0.0, 1.0, n))
        return a + s[:, None] * (b - a)

    up = np.array([0.0, 0.0, 0.05])
    approach, process, retract = line(start + up, start)[:-1], line(start, end), line(end, end + up)
    retract = retract[1:]
    tcp = np.vstack([approach, process, retract])
    phase = np.r_[
        np.full(len(approach), Phase.APPROACH),
        np.full(len(process), Phase.PROCESS),
        np.full(len(retract), Phase.RETRACT),
    ]
    R = Rotation.from_euler("y", tilt_deg, degrees=True) * Rotation.from_matrix(
        np.diag([1.0, -1.0, -1.0])
    )
    T_base_tcp = np.tile(np.eye(4), (len(tcp), 1, 1))
    T_base_tcp[:, :3, :3] = R.as_matrix()
    T_base_tcp[:, :3, 3] = tcp
    T_ft = _tcp_transform(0.15)
    joints = follow_path(
        arm,
        T_base_tcp @ np.linalg.inv(T_ft),
        allowed_branches=None if branch is None else (branch,),
    )
    return joints, phase, T_ft, process, np.arange(len(tcp)) / rate_hz


def test_the_tool_may_touch_the_process_path_only_in_the_process_phases(workpiece_cell):
    arm = model("ur5e")
    joints, phase, T_ft, process, t = _contact_plan(arm, 0.0)
    zone = ContactZone.of_process(arm, joints.q_rad[phase == Phase.PROCESS], T_ft)
    assert np.allclose(zone.path_m, process)
    kw = {"T_flange_tcp": T_ft, "tool": CapsuleTool(0.02), "margin_m": 0.01, "t_s": t}
    ok = check_motion(arm, joints.q_rad, phase, workpiece_cell, contact_zone=zone, **kw)
    assert ok.clear, ok.lines()
    assert ok.exempt_links == ("tool",)
    # Without the exemption the tool's tip touches the scan in the process phase.
    no_zone = check_motion(arm, joints.q_rad, phase, workpiece_cell, **kw)
    assert no_zone.first_collision.link == "tool"
    assert no_zone.link_clearance_m[phase == Phase.PROCESS, -1].max() < 0
    # The same motion labelled as a transit: the contact is a collision.
    transit = np.full_like(phase, Phase.TRANSIT)
    moved = check_motion(arm, joints.q_rad, transit, workpiece_cell, contact_zone=zone, **kw)
    hit = moved.first_collision
    assert hit is not None and hit.link == "tool" and hit.kind == ObstacleKind.SCAN
    assert hit.phase == Phase.TRANSIT
    # The arm's links never get the exemption: a keep-out box around the forearm's path is
    # reported for the forearm even in the process phase.
    F = joint_frames(arm, joints.q_rad[phase == Phase.PROCESS])
    wrist = F[len(F) // 2, 3, :3, 3]
    guard = Box(wrist - 0.01, wrist + 0.01, name="guard")
    cell = Cell(boxes=(guard,), scan_points_m=workpiece_cell.scan_m, voxel_m=0.0)
    boxed = check_motion(arm, joints.q_rad, phase, cell, contact_zone=zone, **kw)
    assert boxed.first_collision.obstacle == "guard" and boxed.first_collision.link != "tool"
    in_process = boxed.link_clearance_m[boxed.phase == Phase.PROCESS]
    hit_links = {boxed.names[j] for j in np.flatnonzero(in_process.min(axis=0) < boxed.margin_m)}
    assert hit_links and "tool" not in hit_links, hit_links


def _tilted_contact(arm, tilt_deg):
    """The contact plan tilted by ``tilt_deg`` on the upright plan's IK branch, and the
    check_motion arguments of its process as a contact zone (a 20 mm capsule tool, 10 mm
    margin)."""
    upright, *_ = _contact_plan(arm, 0.0)
    joints, phase, T_ft, process, t = _contact_plan(arm, tilt_deg, branch=upright.branch)
    kw = {
        "T_flange_tcp": T_ft,
        "tool": CapsuleTool(0.02),
        "margin_m": 0.01,
        "contact_zone": ContactZone.of_process(arm, joints.q_rad[phase == Phase.PROCESS], T_ft),
        "t_s": t,
    }
    return joints, phase, process, kw


def test_a_tool_tilted_into_the_workpiece_is_reported_as_the_tool(workpiece_cell):
    arm = model("ur5e")
    joints, phase, process, kw = _tilted_contact(arm, 60.0)
    # Tilted 60 deg, the 150 mm tool also passes 5 mm from the forearm's housing from the
    # first sample on: the arm against itself is found first.
    both = check_motion(arm, joints.q_rad, phase, workpiece_cell, **kw)
    first = both.first_collision
    assert first.kind == ObstacleKind.SELF and {first.link, first.obstacle} == {"tool", "forearm"}
    assert first.sample == 0 and "the arm's own" in first.describe()
    # Against the workpiece alone:
    report = check_motion(arm, joints.q_rad, phase, workpiece_cell, self_check=False, **kw)
    hit = report.first_collision
    assert hit is not None and hit.link == "tool" and hit.kind == ObstacleKind.SCAN
    # The body goes into the workpiece's top, outside the contact tube, in the process phase.
    tool_process = report.link_clearance_m[phase == Phase.PROCESS, -1]
    assert tool_process.min() < 0
    assert hit.point_m[2] == pytest.approx(WORKPIECE_HI[2], abs=1e-9)
    assert np.linalg.norm(hit.point_m[:2] - process[:, :2].mean(axis=0)) < 0.2


def test_a_thin_obstacle_between_two_samples_is_found():
    """Samples 50 mm apart straddle a 1 mm plate; each sample alone is clear of it."""
    arm = model("ur10")  # CB3: 125 Hz
    n = 41
    q = np.tile([0.0, -1.2, 1.0, -1.4, -np.pi / 2, 0.0], (n, 1))
    q[:, 0] = np.linspace(0.0, 2.0, n)  # 0.05 rad per sample
    T_ft = _tcp_transform(0.10)
    tcp = (forward(arm, q) @ T_ft)[:, :3, 3]
    m = 20
    radius = np.hypot(*tcp[m, :2])
    # A radial plate at the azimuth halfway between the TCP's at samples m and m + 1.
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", np.arctan2(tcp[m, 1], tcp[m, 0]) + 0.025).as_matrix()
    plate = Box(
        [radius - 0.03, -0.0005, tcp[m, 2] - 0.03],
        [radius + 0.03, 0.0005, tcp[m, 2] + 0.03],
        T_base_box=T,
        name="plate",
    )
    tool = CapsuleTool(0.005)
    ends = np.concatenate(
        [link_capsules(arm, q).ends_m, tool_capsules(forward(arm, q), T_ft, tool).ends_m], axis=1
    )
    radii = np.r_[link_capsules(arm, q[:1]).radii_m, 0.005]
    per_sample, _ = capsule_box_clearance(ends, radii, plate)
    assert per_sample.min() > 0.015  # a check of the samples alone sees nothing
    report = check_motion(
        arm, q, np.zeros(n, int), Cell(boxes=(plate,)), T_flange_tcp=T_ft, tool=tool
    )
    hit = report.first_collision
    assert hit is not None and hit.obstacle == "plate" and hit.link == "tool"
    assert hit.sample == m
    assert np.any((report.checked_samples > m) & (report.checked_samples < m + 1))


def test_the_stride_skips_samples_but_not_what_lies_between_them():
    """At 500 Hz a slow move is checked every few samples; a small obstacle touched between
    two checked samples is still reported, from the sample period that touches it."""
    arm = model("ur5e")
    n = 2000
    q0 = np.array([0.3, -1.7, 1.9, -1.8, -1.57, 0.0])
    q = q0 + np.linspace(0.0, 1.0, n)[:, None] * np.array([0.25, 0.1, -0.1, 0.05, 0.0, 0.0])
    T_ft = _tcp_transform(0.12)
    clear = check_motion(arm, q, np.zeros(n, int), Cell(), T_flange_tcp=T_ft)
    u = clear.checked_samples
    assert np.diff(u).max() >= 5  # the stride skips samples
    # A small sphere of scan points next to the tool at a sample that is not checked.
    gaps = np.flatnonzero(np.diff(u) >= 5)
    j = gaps[len(gaps) // 2]
    s = int(u[j]) + int((u[j + 1] - u[j]) // 2)
    assert s not in u
    flange = forward(arm, q[s])
    tcp, x_axis = (flange @ T_ft)[:3, 3], flange[:3, 0]
    ball = tcp + (0.02 + 0.005) * x_axis + 0.002 * np.random.default_rng(6).normal(size=(50, 3))
    report = check_motion(
        arm, q, np.zeros(n, int), Cell(scan_points_m=ball, voxel_m=0.0), T_flange_tcp=T_ft
    )
    hit = report.first_collision
    assert hit is not None and hit.link == "tool" and hit.kind == ObstacleKind.SCAN
    tool = tool_capsules(forward(arm, q), T_ft, CapsuleTool()).ends_m[:, 0]
    d = segment_point_distance(tool[:, None, 0], tool[:, None, 1], ball[None]).min(axis=1) - 0.02
    first_true = int(np.argmax(d < 0.01))
    assert hit.sample <= first_true <= hit.sample + 1 + np.diff(u).max()


def _brute_force(arm, q, T_ft, tool, points, planes, boxes):
    """Clearance of every capsule at every sample: exact point distances to every point, exact
    plane distances, boxes by sampling each segment every 0.5 mm."""
    caps = link_capsules(arm, q)
    tcaps = tool_capsules(forward(arm, q), T_ft, tool)
    ends = np.concatenate([caps.ends_m, tcaps.ends_m], axis=1)
    radii = np.r_[caps.radii_m, tcaps.radii_m]
    a, b = ends[..., 0, :], ends[..., 1, :]
    best = np.full(ends.shape[:2], np.inf)
    for chunk in np.array_split(points, max(1, len(points) // 200)):
        d = segment_point_distance(a[..., None, :], b[..., None, :], chunk[None, None])
        best = np.minimum(best, d.min(axis=-1) - radii)
    for plane, exempt_base in planes:
        s = np.minimum(a @ plane.normal, b @ plane.normal) - plane.offset_m - radii
        if exempt_base:
            s[:, 0] = np.inf
        best = np.minimum(best, s)
    length = np.linalg.norm(b - a, axis=-1).max()
    t = np.linspace(0.0, 1.0, int(np.ceil(length / 0.0005)) + 1)
    for box in boxes:
        pts = a[..., None, :] + t[:, None] * (b - a)[..., None, :]
        if box.T_base_box is not None:
            pts = (pts - box.T_base_box[:3, 3]) @ box.T_base_box[:3, :3]
        sd = _point_box_signed(pts, box.min_m, box.max_m).min(axis=-1) - radii
        best = np.minimum(best, sd)
    return best, 0.25e-3  # the sampled boxes overestimate by at most this


@pytest.mark.slow
@pytest.mark.parametrize("voxel_m", [0.0, 0.003])
def test_agrees_with_an_independent_brute_force_within_the_stated_bound(voxel_m):
    arm = model("ur5e")
    rng = np.random.default_rng(11)
    n = 200
    t = np.arange(n) / 125.0
    q0 = np.array([0.2, -1.6, 1.7, -1.7, -1.57, 0.3])
    amp, freq, phs = rng.uniform(0.1, 0.5, 6), rng.uniform(0.2, 0.8, 6), rng.uniform(0, 6, 6)
    q = q0 + amp * np.sin(2 * np.pi * freq * t[:, None] + phs)
    T_ft = _tcp_transform(0.12)
    tool = CapsuleTool(0.02)
    # Scan points scattered around the arm's own path, from 2 cm inside to 8 cm outside.
    caps = link_capsules(arm, q[::8])
    e = caps.ends_m
    axis_pts = e[:, :, 0] + rng.uniform(0, 1, e.shape[:2])[..., None] * (e[:, :, 1] - e[:, :, 0])
    direction = rng.normal(size=axis_pts.shape)
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    offset = caps.radii_m[None, :, None] + rng.uniform(-0.02, 0.08, e.shape[:2] + (1,))
    pts = (axis_pts + direction * offset).reshape(-1, 3)
    pts = pts[pts[:, 2] > 0.01][:1500]
    scan = np.repeat(pts, 4, axis=0) + rng.normal(scale=0.002, size=(4 * len(pts), 3))
    boxes = (
        Box([0.35, 0.1, 0.0], [0.55, 0.3, 0.25], name="b1"),
        Box([-0.1, -0.1, -0.1], [0.1, 0.1, 0.1], T_base_box=_posed(), name="b2"),
    )
    cell = Cell(boxes=boxes, scan_points_m=scan, voxel_m=voxel_m, mounting_band_m=0.0)
    report = check_motion(
        arm,
        q,
        np.zeros(n, int),
        cell,
        T_flange_tcp=T_ft,
        tool=tool,
        margin_m=0.01,
        t_s=t,
        horizon_m=0.2,
    )
    # The truth between samples too: every period cut in four (the joints move linearly).
    k = 4
    s = np.arange((n - 1) * k + 1) / k
    i0 = np.minimum(s.astype(int), n - 2)
    q_fine = q[i0] + (s - i0)[:, None] * (q[i0 + 1] - q[i0])
    mounting = [(HalfSpace([0, 0, 1]), True)]
    truth, sampling = _brute_force(arm, q_fine, T_ft, tool, scan, mounting, boxes)
    period = np.minimum.reduceat(truth[:-1], np.arange(0, len(truth) - 1, k), axis=0)
    period = np.minimum(period, truth[k::k])  # each period includes its end
    fast = report.link_clearance_m[:-1]
    # Never optimistic, between samples included.
    assert np.all(fast <= period + 1e-9)
    # And within the stated tolerance where the clearance matters (the brute force's own
    # sampling of boxes and of time, 1/4 period, adds a fraction of a millimetre).
    near = (period < report.exact_below_m) & (period > -0.015)
    assert near.sum() > 100
    assert (period - fast)[near].max() <= report.tolerance_m + sampling + 0.3e-3
    # The first collision: no later than the brute force's, earlier only within the tolerance.
    at_samples = truth[::k]
    true_first = int(np.argmax(at_samples.min(axis=1) < 0.01))
    hit = report.first_collision
    assert hit.sample <= true_first
    assert period[hit.sample].min() < 0.01 + report.tolerance_m + sampling + 0.3e-3


def _posed() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.2, 0.4, 0.7]).as_matrix()
    T[:3, 3] = [0.3, -0.4, 0.4]
    return T


def test_the_report_reads_in_words():
    arm = model("ur5e")
    q = np.tile([0.0, -1.2, 1.6, -2.0, -1.57, 0.0], (10, 1))
    flange = forward(arm, q[:1])[0]
    tcp = (flange @ _tcp_transform(0.1))[:3, 3]
    scan = tcp + np.array([[0.0, 0.0, 0.005]])  # 5 mm up the tool's axis: inside the tool
    report = check_motion(
        arm,
        q,
        np.full(10, Phase.TRANSIT),
        Cell(scan_points_m=scan, voxel_m=0.0),
        T_flange_tcp=_tcp_transform(0.1),
        t_s=np.arange(10) * 0.002 + 2.0,
    )
    line = report.lines()[0]
    assert line.startswith("COLLISION: tool touches the scan at (")
    assert "during transit at 2.00 s" in line and "mm inside" in line
    x, y, z = scan[0] * 1000
    assert f"({x:.1f}, {y:.1f}, {z:.1f}) mm" in line
    assert any(line.startswith("checked ") for line in report.lines())


def test_walls_and_the_floor_below_a_ceiling_mounted_arm_are_half_spaces():
    """In the base frame the mounting surface is always z = 0; a ceiling-mounted arm's base z
    points down, so the floor 0.9 m below the ceiling is z <= 0.9 (normal -z)."""
    arm = model("ur5e")
    n = 200
    q = np.tile([0.0, -1.57, 0.0, -1.57, 0.0, 0.0], (n, 1))
    q[:, 1] = np.linspace(-1.57, 0.3, n)  # the stretched arm swings down from straight up
    floor = HalfSpace([0.0, 0.0, -1.0], -0.9, "floor")
    wall = HalfSpace([1.0, 0.0, 0.0], -0.95, "wall")  # x >= -0.95
    report = check_motion(
        arm, q, np.zeros(n, int), Cell(planes=(floor, wall)), T_flange_tcp=_tcp_transform(0.1)
    )
    hit = report.first_collision
    assert hit is not None and hit.kind == ObstacleKind.PLANE and hit.obstacle in ("floor", "wall")
    caps = link_capsules(arm, q)
    tool = tool_capsules(forward(arm, q), _tcp_transform(0.1), CapsuleTool())
    ends = np.concatenate([caps.ends_m, tool.ends_m], axis=1)
    radii = np.r_[caps.radii_m, tool.radii_m]
    worst = np.minimum(
        capsule_halfspace_clearance(ends, radii, floor)[0],
        capsule_halfspace_clearance(ends, radii, wall)[0],
    )
    first_true = int(np.argmax(worst.min(axis=1) < 0.01))
    assert hit.sample <= first_true
    # Without a mounting plane and those surfaces the same swing is clear.
    assert check_motion(
        arm, q, np.zeros(n, int), Cell(mounting=None), T_flange_tcp=_tcp_transform(0.1)
    ).clear


def test_a_short_tool_exempts_wrist_3_and_a_single_sample_is_checked():
    arm = model("ur5e")
    q = np.array([[0.0, -1.2, 1.6, -2.0, -1.57, 0.0]])
    flange = forward(arm, q)[0]
    zone = ContactZone.of_process(arm, q, _tcp_transform(0.01))
    assert np.allclose(zone.path_m[0], (flange @ _tcp_transform(0.01))[:3, 3])
    short = check_motion(
        arm,
        q,
        [Phase.PROCESS],
        Cell(),
        T_flange_tcp=_tcp_transform(0.01),
        tool=SphereTool([[0.0, 0.0, 0.01]], [0.004]),
        contact_zone=zone,
    )
    assert short.exempt_links == ("wrist 3", "tool")
    assert short.clearance_m.shape == (1,) and short.link_clearance_m.shape == (1, 9)
    assert len(short.checked_samples) == 1 and short.clear
    long_tool = check_motion(
        arm, q, [Phase.PROCESS], Cell(), T_flange_tcp=_tcp_transform(0.25), contact_zone=zone
    )
    assert long_tool.exempt_links == ("tool",)


# --- the contact exemption covers the tip's surface, never a fixture beside the path ----------

CLAMP_HEIGHT_M = 0.03


def _clamped_cell(gap_m: float) -> tuple[Cell, tuple]:
    """The workpiece and a 30 mm clamp on its top whose face is ``gap_m`` beside the process
    line (x = 0.45), both scanned; the clamp's box."""
    top = WORKPIECE_HI[2]
    lo = (0.45 + gap_m, -0.20, top)
    hi = (0.45 + gap_m + 0.04, -0.10, top + CLAMP_HEIGHT_M)
    scan = np.vstack([_box_scan(WORKPIECE_LO, WORKPIECE_HI, 0.002), _box_scan(lo, hi, 0.002)])
    return Cell(scan_points_m=scan, voxel_m=0.002), (np.array(lo), np.array(hi))


def _independent_clearance(arm, q, T_ft, radius_m, box) -> float:
    """The tool's least clearance to the clamp, computed apart from recon.collision: the tool's
    axis (flange to TCP) sampled every 0.5 mm at every sample, exact distances to the box."""
    lo, hi = box
    flange = forward(arm, q)
    tcp = (flange @ T_ft)[:, :3, 3]
    s = np.linspace(0.0, 1.0, int(np.ceil(np.linalg.norm(T_ft[:3, 3]) / 0.0005)) + 1)
    axis = flange[:, None, :3, 3] + s[None, :, None] * (tcp - flange[:, :3, 3])[:, None, :]
    outside = np.maximum(np.maximum(lo - axis, axis - hi), 0.0)
    return float(np.linalg.norm(outside, axis=-1).min()) - radius_m


@pytest.mark.parametrize("radius_mm", [20, 30, 45])
@pytest.mark.parametrize("gap_mm", [20, 35, 50, 70])
def test_a_thick_tool_beside_a_clamp_is_refused_exactly_where_it_touches(radius_mm, gap_mm):
    """A 45 mm tool passed through a clamp 20 mm beside the path: every scan point within the
    contact tube (which grows with the tool) was exempt for the whole tool. Now only what lies
    no higher than the band above the tip is; the clamp's upper part counts in full. Each case
    is judged against an independent distance computation: refused where the tool comes within
    the margin of the clamp, clear where it stays farther than the margin plus the check's
    stated tolerance (between the two, either answer is right)."""
    arm = model("ur5e")
    joints, phase, T_ft, _, t = _contact_plan(arm, 0.0)
    cell, box = _clamped_cell(gap_mm / 1000)
    radius_m, margin_m = radius_mm / 1000, 0.01
    report = check_motion(
        arm,
        joints.q_rad,
        phase,
        cell,
        T_flange_tcp=T_ft,
        tool=CapsuleTool(radius_m),
        margin_m=margin_m,
        contact_zone=ContactZone.of_process(arm, joints.q_rad[phase == Phase.PROCESS], T_ft),
        t_s=t,
    )
    truth = _independent_clearance(arm, joints.q_rad, T_ft, radius_m, box)
    print(
        f"\ntool r {radius_mm} mm, clamp {gap_mm} mm beside the path: independent clearance "
        f"{truth * 1e3:.1f} mm; check: {'clear' if report.clear else 'refused'}"
        f" (smallest {report.clearance_m.min() * 1e3:.1f} mm, tolerance "
        f"{report.tolerance_m * 1e3:.1f} mm)"
    )
    if truth < margin_m:
        assert not report.clear
        hit = report.first_collision
        assert hit.link == "tool" and hit.kind == ObstacleKind.SCAN
        assert hit.point_m[2] > WORKPIECE_HI[2] + 0.01  # the clamp, above the band
    elif truth > margin_m + report.tolerance_m:
        assert report.clear, report.lines()


# --- a spindle with a flat end, as spheres, beside a plate on the table -------------------------

PLATE_TOP_M = 0.03
#: A 20 mm spindle whose flat end is the TCP (0.15 m from the flange), as spheres: a small one
#: for the burr at the tip, 20 mm ones for the body from 25 mm above the tip up.
SPINDLE_SPHERES_M = (0, 0, 0.147, 0.003, 0, 0, 0.125, 0.02, 0, 0, 0.09, 0.02, 0, 0, 0.055, 0.02)


def test_a_flat_ended_spindle_given_as_spheres_works_a_plate():
    """A 30 mm plate on the table, a 20 mm spindle along its top. As spheres
    (``PlanParams.tool_spheres_m``, as the CLI and the API give them) the lowest
    point of the tool is the burr at the tip: clear, and the report's smallest clearance
    matches the spheres' lowest point over the table computed apart from the check."""
    arm = model("ur5e")
    plate_hi = (WORKPIECE_HI[0], WORKPIECE_HI[1], PLATE_TOP_M)
    cell = Cell(scan_points_m=_box_scan(WORKPIECE_LO, plate_hi, 0.002), voxel_m=0.002)
    joints, phase, T_ft, _, t = _contact_plan(arm, 0.0, top_m=PLATE_TOP_M)
    zone = ContactZone.of_process(arm, joints.q_rad[phase == Phase.PROCESS], T_ft)
    margin_m = 0.01

    def check(params):
        return check_motion(
            arm, joints.q_rad, phase, cell, T_flange_tcp=T_ft, tool=params.tool,
            margin_m=margin_m, contact_zone=zone, t_s=t,
        )  # fmt: skip

    # The capsule was refused here: its round end reaches 20 mm below the tip. That end is
    # within the contact radius of the tip, the tip's own region, now left out against the
    # table during contact (the thin-plate tests below).
    capsule = check(PlanParams(speed_m_s=0.05, tool_radius_m=0.02))
    assert capsule.clear, capsule.lines()
    spindle = PlanParams(speed_m_s=0.05, tool_spheres_m=SPINDLE_SPHERES_M)
    assert isinstance(spindle.tool, SphereTool) and len(spindle.tool.radii_m) == 4
    report = check(spindle)
    assert report.clear, report.lines()
    # Apart from the check: every sphere's lowest point over the table (the mounting plane is
    # tested 5 mm up, where a scan's table points are dropped), and to the plate's top only
    # for the spheres above the contact band.
    centres = tool_capsules(forward(arm, joints.q_rad), T_ft, spindle.tool).ends_m[:, :, 0]
    lowest_m = (centres[..., 2] - spindle.tool.radii_m).min()
    assert lowest_m - cell.mounting_band_m > margin_m
    # The burr's sphere lies within the contact radius of the tip: the tip's own region, left
    # out against the table during contact. The body's spheres are tested in full.
    tcp = T_ft[:3, 3]
    body = (
        np.linalg.norm(spindle.tool.centers_m - tcp, axis=1) + spindle.tool.radii_m
        > report.contact_radius_m
    )
    assert not body[0] and body[1:].all()
    body_lowest_m = (centres[..., body, 2] - spindle.tool.radii_m[body]).min()
    assert report.clearance_m.min() <= body_lowest_m - cell.mounting_band_m + 1e-9


# --- a thin plate on the table: the tip works it, the tool's body keeps off the table -----------


def _body_over_table_m(arm, q, T_ft, radius_m, contact_radius_m, band_m) -> float:
    """The least height over the mounting plane (tested ``band_m`` up) of the tool capsule's
    points farther than ``contact_radius_m`` from the TCP, computed apart from recon.collision:
    the capsule's surface sampled (rings of 36 points every 0.5 mm along the axis, the flange's
    half sphere every 2.5 degrees)."""
    flange = forward(arm, q)
    tip, top = (flange @ T_ft)[:, :3, 3], flange[:, :3, 3]
    length = np.linalg.norm(T_ft[:3, 3])
    axis = (top - tip) / length
    ref = np.where(np.abs(axis[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(axis, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(axis, e1)
    phi = np.linspace(0.0, 2 * np.pi, 36, endpoint=False)
    ring = np.cos(phi)[None, :, None] * e1[:, None] + np.sin(phi)[None, :, None] * e2[:, None]
    points = []
    for t in np.arange(0.0, length + 1e-9, 0.0005):
        points.append(tip[:, None] + t * axis[:, None] + radius_m * ring)
    for theta in np.radians(np.arange(0.0, 90.1, 2.5)):  # the flange's half sphere
        points.append(
            top[:, None]
            + radius_m * np.sin(theta) * axis[:, None]
            + radius_m * np.cos(theta) * ring
        )
    points = np.concatenate(points, axis=1)  # (M, P, 3)
    far = np.linalg.norm(points - tip[:, None], axis=2) >= contact_radius_m
    height = np.where(far, points[..., 2] - band_m, np.inf)
    return float(height.min())


@pytest.mark.parametrize("scanned", [True, False], ids=["scanned", "no-scan"])
@pytest.mark.parametrize("tilt_deg", [0, 30, 45, 60, 75])
@pytest.mark.parametrize("plate_mm", [2, 10])
def test_a_thin_plate_on_the_table_is_worked_and_a_leaning_body_is_refused(
    plate_mm, tilt_deg, scanned
):
    """A 2 mm sheet on the table could not be worked at all (the default 20 mm tool's round
    end reaches 20 mm below the tip; with a scan the table is tested 5 mm up): every plate
    under about 40 mm was refused against the mounting plane. The tip's own region (within the
    contact radius of the TCP) is now left out of that test during contact, as it is for the
    scan; the rest of the tool is not. Judged against an independent computation: refused where
    the tool's body outside that region comes within the margin of the table, clear where it
    stays farther than the margin plus the check's tolerance."""
    arm = model("ur5e")
    top = plate_mm / 1000
    plate_hi = (WORKPIECE_HI[0], WORKPIECE_HI[1], top)
    cell = (
        Cell(scan_points_m=_box_scan(WORKPIECE_LO, plate_hi, 0.002), voxel_m=0.002)
        if scanned
        else Cell()
    )
    joints, phase, T_ft, _, t = _contact_plan(arm, float(tilt_deg), top_m=top)
    radius_m, margin_m = 0.02, 0.01
    report = check_motion(
        arm, joints.q_rad, phase, cell, T_flange_tcp=T_ft, tool=CapsuleTool(radius_m),
        margin_m=margin_m, t_s=t,
        contact_zone=ContactZone.of_process(arm, joints.q_rad[phase == Phase.PROCESS], T_ft),
    )  # fmt: skip
    band = cell.mounting_band_m if scanned else 0.0
    # Every 5th sample of the process (where the tip is exempt; the orientation is constant).
    exempt = np.flatnonzero(phase == Phase.PROCESS)[::5]
    truth = _body_over_table_m(
        arm, joints.q_rad[exempt], T_ft, radius_m, report.contact_radius_m, band
    )
    print(
        f"\n{plate_mm} mm plate, tool tilted {tilt_deg} deg, {'scanned' if scanned else 'no scan'}:"
        f" body {truth * 1e3:.1f} mm over the table; "
        f"{'clear' if report.clear else 'refused: ' + report.first_collision.obstacle}"
    )
    if truth < margin_m:
        assert not report.clear  # first by the tool, or by wrist 2 where it leans further
        assert report.link_clearance_m[:, report.names.index("tool")].min() < margin_m
    elif truth > margin_m + report.tolerance_m:
        assert report.clear, report.lines()
    if tilt_deg == 0:
        assert report.clear, report.lines()  # an upright tool on a sheet: the everyday case


def test_a_path_under_the_table_is_refused_whatever_the_contact():
    """The tip's region is left out only where the tip is no deeper than the contact zone's
    radius below the table: a trace 15 mm under it (a tracker calibrated wrong, no scan to
    correct it) has the whole tool tested and is refused against the mounting plane."""
    arm = model("ur5e")
    joints, phase, T_ft, _, t = _contact_plan(arm, 0.0, top_m=-0.015)
    zone = ContactZone.of_process(arm, joints.q_rad[phase == Phase.PROCESS], T_ft)
    assert zone.radius_m < 0.015
    report = check_motion(
        arm, joints.q_rad, phase, Cell(), T_flange_tcp=T_ft, tool=CapsuleTool(0.02),
        margin_m=0.01, t_s=t, contact_zone=zone,
    )  # fmt: skip
    hit = report.first_collision
    assert hit is not None and hit.link == "tool" and hit.obstacle == "mounting plane"
    assert report.clearance_m[phase == Phase.PROCESS].max() < 0


# --- the arm against itself --------------------------------------------------------------------


@pytest.mark.slow
def test_segment_segment_closest_points_match_a_dense_search():
    from recon.collision import segment_segment_closest

    rng = np.random.default_rng(7)
    for k in range(300):
        p0, p1, q0, q1 = rng.normal(size=(4, 3))
        if k % 5 == 0:
            p1 = p0.copy()  # a point
        if k % 7 == 0:
            q1 = q0 + 0.5 * (p1 - p0)  # parallel
        distance, on_p, on_q = segment_segment_closest(p0, p1, q0, q1)
        s = np.linspace(0.0, 1.0, 2001)
        dense = np.linalg.norm(
            (p0 + s[:, None] * (p1 - p0))[:, None] - (q0 + s[:, None] * (q1 - q0))[None], axis=-1
        ).min()
        assert distance <= dense + 1e-12 and distance >= dense - 2e-3
        assert np.linalg.norm(on_p - on_q) == pytest.approx(distance, abs=1e-12)


def _self_clearance(arm, q, T_ft, tool_radius_m):
    """The least clearance of the self-checked pairs at one configuration, by dense sampling of
    the capsules' axes (apart from the check's closed form)."""
    from recon.collision import SELF_PAIRS, _place, _tool_local, capsule_model

    cm = capsule_model(arm)
    tool_local, tool_r = _tool_local(T_ft, CapsuleTool(tool_radius_m))
    ends = _place(
        joint_frames(arm, q[None]), np.r_[cm.frames, 6], np.concatenate([cm.local_m, tool_local])
    )[0]
    radii = np.r_[cm.radii_m, tool_r]
    s = np.linspace(0.0, 1.0, 301)[:, None]
    best = np.inf
    for i, j in SELF_PAIRS:
        a = ends[i, 0] + s * (ends[i, 1] - ends[i, 0])
        b = ends[j, 0] + s * (ends[j, 1] - ends[j, 0])
        gap = np.linalg.norm(a[:, None] - b[None], axis=-1).min() - radii[i] - radii[j]
        best = min(best, gap)
    return best


@pytest.mark.slow
def test_the_arm_folding_onto_itself_is_refused_where_it_comes_within_the_margin():
    """Nothing checked the arm against itself: folding the elbow past 150 deg swings wrist 3
    into the shoulder. Now the tool and the wrists are checked against the base, the shoulder
    and the upper arm (same report shape: the link, the arm's own part it meets, where), and
    the refusal agrees with an independent dense computation within the stated tolerance."""
    arm = model("ur5e")
    n = 100
    q = np.tile(HOME_Q_RAD, (n, 1))
    q[:, 2] = np.linspace(np.pi / 2, 2.95, n)
    T_ft = _tcp_transform(0.1)
    report = check_motion(arm, q, np.zeros(n, int), Cell(mounting=None), T_flange_tcp=T_ft)
    hit = report.first_collision
    assert hit is not None and hit.kind == ObstacleKind.SELF
    assert {hit.link, hit.obstacle} == {"shoulder", "wrist 3"}
    truth = np.array([_self_clearance(arm, qq, T_ft, 0.02) for qq in q])  # every sample
    # A sample's clearance is its period's (to the next sample): conservative, never more
    # than the truth there, and at most the stated tolerance less.
    period = np.minimum(truth, np.r_[truth[1:], truth[-1]])
    every = slice(None)
    assert np.all(report.clearance_m[every] <= period[every] + 1e-6)
    lowest = np.minimum(period[every], 0.1) - report.tolerance_m - 1e-6
    assert np.all(report.clearance_m[every] >= lowest)
    # Refused in the first period whose true clearance may be within the margin, not before.
    assert period[hit.sample] < report.margin_m + report.tolerance_m
    assert np.all(period[: hit.sample] >= report.margin_m - 1e-6)
    print(
        f"\nrefused at elbow {np.degrees(q[hit.sample, 2]):.1f} deg: true clearance "
        f"{period[hit.sample] * 1e3:.1f} mm, reported {hit.clearance_m * 1e3:.1f} mm"
    )
    # Turning the base with the arm at home never meets itself.
    turn = np.tile(HOME_Q_RAD, (n, 1))
    turn[:, 0] = np.linspace(0.0, 1.5, n)
    assert check_motion(arm, turn, np.zeros(n, int), Cell(mounting=None), T_flange_tcp=T_ft).clear


def test_the_scan_the_contact_touches_is_what_a_brute_force_finds():
    """``_touched_by_contact`` (pairs from two trees, heights a chunk at a time) against every
    (path point, scan point) pair measured directly; chunks smaller than the pairs."""
    from recon import collision

    rng = np.random.default_rng(7)
    on_path = np.c_[np.linspace(0.0, 0.2, 60), 0.01 * np.sin(np.linspace(0, 6, 60)), np.zeros(60)]
    axes = rng.normal([0.0, 0.0, 1.0], 0.3, size=(60, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    points = rng.uniform([-0.02, -0.04, -0.02], [0.22, 0.04, 0.03], size=(20_000, 3))
    tree = cKDTree(points)
    for radius_m, band_m in ((0.01, 0.002), (0.02, -0.005), (0.0, 0.0)):
        distance = np.linalg.norm(points[None, :, :] - on_path[:, None, :], axis=2)
        height = np.einsum("kpj,kj->kp", points[None, :, :] - on_path[:, None, :], axes)
        expected = ((distance <= radius_m) & (height <= band_m)).any(axis=0)
        got = collision._touched_by_contact(tree, points, on_path, axes, radius_m, band_m)
        assert np.array_equal(got, expected)
        assert radius_m == 0.0 or 0 < expected.sum() < len(points)  # not vacuous
    old = collision._PAIR_CHUNK
    try:
        collision._PAIR_CHUNK = 97
        got = collision._touched_by_contact(tree, points, on_path, axes, 0.01, 0.002)
    finally:
        collision._PAIR_CHUNK = old
    assert np.array_equal(
        got, collision._touched_by_contact(tree, points, on_path, axes, 0.01, 0.002)
    )


@pytest.mark.parametrize("tilt_deg", [0.0, 60.0])
def test_the_exempt_tool_skips_only_full_scan_queries_no_bound_reads(
    tilt_deg, workpiece_cell, monkeypatch
):
    """The exempt capsules' clearance to the whole scan is computed only at the configurations
    that bound a period not exempt; every report is the same as with it computed everywhere."""
    from dataclasses import replace

    from recon import collision

    arm = model("ur5e")
    joints, phase, _, kw = _tilted_contact(arm, tilt_deg)
    seen = []
    exemption_of = collision._contact_exemption

    def recorded(*args, **kwargs):
        seen.append(exemption_of(*args, **kwargs))
        return seen[-1]

    monkeypatch.setattr(collision, "_contact_exemption", recorded)
    skipped = check_motion(arm, joints.q_rad, phase, workpiece_cell, **kw)
    assert seen[-1].full_rows is not None
    assert 0 < len(seen[-1].full_rows) < len(skipped.checked_samples)  # something was skipped
    monkeypatch.setattr(
        collision,
        "_contact_exemption",
        lambda *a, **k: replace(exemption_of(*a, **k), full_rows=None),
    )
    everywhere = check_motion(arm, joints.q_rad, phase, workpiece_cell, **kw)
    for name in ("clearance_m", "link_clearance_m", "nearest_link", "nearest_kind"):
        assert np.array_equal(getattr(skipped, name), getattr(everywhere, name)), name
    assert repr(skipped.first_collision) == repr(everywhere.first_collision)
    assert (skipped.first_collision is None) == (tilt_deg == 0.0)
