"""The ICP: known transforms recovered, free motions left alone, checked against Open3D."""

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from recon.errors import RegistrationError
from recon.icp import register_icp
from recon.transforms import apply_transform, invert_transform


def transform(rotvec_deg, translation_m):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = translation_m
    return T


def l_shaped_edge(spacing=0.0005):
    """Two perpendicular straight edges meeting at the origin, with their directions."""
    leg = np.arange(0, 0.08, spacing)
    a = np.column_stack([leg, np.zeros_like(leg), np.zeros_like(leg)])
    b = np.column_stack([np.zeros_like(leg), leg, np.zeros_like(leg)])
    directions = np.concatenate(
        [np.tile([1.0, 0, 0], (len(leg), 1)), np.tile([0, 1.0, 0], (len(leg), 1))]
    )
    return np.concatenate([a, b]), directions


def test_recovers_a_known_transform_on_a_corner():
    target, directions = l_shaped_edge()
    T_true = transform([0.4, -0.3, 0.6], [0.002, -0.0015, 0.001])
    source = apply_transform(invert_transform(T_true), target[::3])
    reg = register_icp(
        source,
        target,
        init_T_target_source=np.eye(4),
        max_distance_m=0.01,
        target_directions=directions,
        target_label="edge",
    )
    moved = apply_transform(reg.T_scan_tracker, source)
    assert np.abs(moved - target[::3]).max() < 2e-5
    assert reg.constrained_dof == 6


def test_agrees_with_open3d_point_to_point_where_the_problem_is_well_posed():
    rng = np.random.default_rng(0)
    target, directions = l_shaped_edge()
    T_true = transform([0.3, 0.2, -0.5], [0.0015, 0.001, -0.002])
    source = apply_transform(invert_transform(T_true), target[::4]) + rng.normal(
        0, 1e-4, (len(target[::4]), 3)
    )
    ours = register_icp(
        source,
        target,
        init_T_target_source=np.eye(4),
        max_distance_m=0.01,
        target_directions=directions,
        target_label="edge",
    )
    result = o3d.pipelines.registration.registration_icp(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source)),
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target)),
        0.01,
        np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPoint(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=200),
    )
    theirs = np.asarray(result.transformation)
    probe = np.array([[0.0, 0, 0], [0.08, 0, 0], [0, 0.08, 0]])
    assert (
        np.abs(apply_transform(ours.T_scan_tracker, probe) - apply_transform(theirs, probe)).max()
        < 2e-4
    )


def test_a_plane_fixes_only_height_and_tilt():
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.05, 0.05, (4000, 2))
    target = np.column_stack([xy, np.zeros(4000)])
    normals = np.tile([0.0, 0.0, 1.0], (4000, 1))
    a = np.linspace(0, 2 * np.pi, 200, endpoint=False)  # a circle spans the plane in 2-D
    source = np.column_stack([0.03 * np.cos(a), 0.03 * np.sin(a), np.full_like(a, 0.0015)])
    init = transform([0, 0, 5.0], [0.003, -0.002, 0.0])  # in-plane offset the plane cannot see
    reg = register_icp(
        source,
        target,
        init_T_target_source=init,
        max_distance_m=0.01,
        target_normals=normals,
        target_label="surface",
    )
    moved = apply_transform(reg.T_scan_tracker, source)
    assert np.abs(moved[:, 2]).max() < 1e-6  # brought down onto the plane
    # The in-plane part of the initial guess is kept, not wandered away from.
    np.testing.assert_allclose(reg.T_scan_tracker[:2, 3], init[:2, 3], atol=1e-6)
    np.testing.assert_allclose(reg.T_scan_tracker[:2, :2], init[:2, :2], atol=1e-6)
    assert reg.constrained_dof == 3
    # Brought down by 1.5 mm, all of it off the surface (the move's in-plane part is zero).
    assert abs(reg.path_moved_max_m - 0.0015) < 1e-6
    assert abs(reg.path_moved_off_feature_median_m - 0.0015) < 1e-6


def test_ignores_a_lifted_stretch_of_the_path():
    rng = np.random.default_rng(2)
    xy = rng.uniform(-0.06, 0.06, (6000, 2))
    target = np.column_stack([xy, np.zeros(6000)])
    s = np.linspace(-0.05, 0.05, 300)
    lift = 0.006 * np.exp(-0.5 * (s / 0.008) ** 2)
    source = np.column_stack([s, 0.01 * np.sin(s * 40), lift])
    reg = register_icp(
        source,
        target,
        init_T_target_source=np.eye(4),
        max_distance_m=0.01,
        target_normals=np.tile([0.0, 0, 1], (6000, 1)),
        target_label="surface",
    )
    # The lift's flanks below the 2 mm Tukey scale still count a little.
    assert abs(reg.T_scan_tracker[2, 3]) < 2e-4


def test_a_nearly_straight_path_leaves_the_roll_about_itself_alone():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.06, 0.06, (6000, 2))
    target = np.column_stack([xy, np.zeros(6000)])
    s = np.linspace(-0.05, 0.05, 200)
    source = np.column_stack([s, 0.0005 * np.sin(s * 200), np.full_like(s, 0.001)])
    init = transform([2.0, 0, 0], [0, 0, 0])  # a roll about the path's own axis
    reg = register_icp(
        source,
        target,
        init_T_target_source=init,
        max_distance_m=0.01,
        target_normals=np.tile([0.0, 0, 1], (6000, 1)),
        target_label="surface",
    )
    assert reg.constrained_dof == 2  # height and pitch; roll about the path is not observable
    np.testing.assert_allclose(
        Rotation.from_matrix(reg.T_scan_tracker[:3, :3]).as_rotvec()[0], np.radians(2.0), atol=1e-6
    )


def test_no_overlap_is_an_error():
    target, directions = l_shaped_edge()
    source = target[::3] + [0.0, 0.0, 0.05]
    with pytest.raises(RegistrationError, match="lies within"):
        register_icp(
            source,
            target,
            init_T_target_source=np.eye(4),
            max_distance_m=0.01,
            target_directions=directions,
            target_label="edge",
        )


def test_registration_reports_how_far_the_path_moved_not_where_the_scanner_stands():
    """A scanner 4 m from the tracker's origin: the transform's translation is metres, the
    path itself moved by about the misalignment (issue: "moved 326.05 mm" for a 1.2 mm move)."""
    from recon import scenes
    from recon.inputs import Scan
    from recon.reconstruct import reconstruct
    from recon.transforms import apply_transform, translation_m

    scene = scenes.cylinder_edge(0)
    far = np.eye(4)
    far[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    far[:3, 3] = [4.0, -1.0, 0.5]
    T_true = far @ scene.T_scan_tracker  # tracker -> scan, with the scanner far away
    scan = Scan(points_m=apply_transform(far, scene.scan.points_m))
    result = reconstruct(scene.recording, scan, T_scan_tracker_init=far)
    reg = result.registration
    assert np.linalg.norm(translation_m(reg.T_scan_tracker)) > 3.5
    # How far the path moved from the initial placement: about the scene's misalignment.
    expected = np.linalg.norm(
        apply_transform(T_true, scene.recording.points_m)
        - apply_transform(far, scene.recording.points_m),
        axis=1,
    )
    print(f"path moved {reg.path_moved_mean_m * 1e3:.2f} mm (true {expected.mean() * 1e3:.2f})")
    assert abs(reg.path_moved_mean_m - expected.mean()) < 1e-3
    assert reg.path_moved_max_m < expected.max() + 1e-3


def test_a_motion_and_its_opposite_read_the_same():
    """Eigenvectors come with an arbitrary sign, which rounding can flip: the words must not."""
    from recon.icp import RigidMotion

    motion = RigidMotion(np.zeros(3), 0.1)
    rng = np.random.default_rng(3)
    for _ in range(50):
        twist = rng.normal(size=6)
        twist[rng.integers(0, 2) * 3 : rng.integers(0, 2) * 3 + 3] *= 1e-3  # either kind
        words = motion.describe(twist)
        assert words == motion.describe(-twist)
        x, y, z = (float(v) for v in words.split("(")[1].rstrip(")").split(", "))
        assert max((x, y, z), key=abs) > 0
    assert motion.describe(np.r_[0, 0, 0, -1.0, 0, 0]) == "sliding along (1.00, 0.00, 0.00)"
    assert motion.describe(np.r_[0, 0, -2.0, 0, 0, 0]) == "turning about (0.00, 0.00, 1.00)"
