"""Rigid transforms: inverse, the one rigidity check and its refusals, angles, UR poses."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.transforms import (
    RIGID_TOLERANCE,
    apply_transform,
    check_rigid,
    invert_transform,
    is_rigid,
    pose_from_transform,
    rotate_vectors,
    rotation_angle_deg,
    transform_from_pose,
    translation_m,
)


def transform(rotvec_deg, translation):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = translation
    return T


def test_the_inverse_undoes_the_transform_and_matches_a_general_inverse():
    T = transform([10.0, -35.0, 120.0], [0.4, -0.2, 0.9])
    inverse = invert_transform(T)
    np.testing.assert_allclose(inverse @ T, np.eye(4), atol=1e-15)
    np.testing.assert_allclose(inverse, np.linalg.inv(T), atol=1e-14)
    points = np.random.default_rng(0).normal(size=(50, 3))
    np.testing.assert_allclose(
        apply_transform(inverse, apply_transform(T, points)), points, atol=1e-14
    )


def test_apply_and_rotate_agree_with_homogeneous_coordinates():
    T = transform([0.0, 90.0, 0.0], [1.0, 2.0, 3.0])
    p = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    homogeneous = (T @ np.column_stack([p, np.ones(2)]).T).T[:, :3]
    np.testing.assert_allclose(apply_transform(T, p), homogeneous, atol=1e-15)
    np.testing.assert_allclose(rotate_vectors(T, p), homogeneous - T[:3, 3], atol=1e-15)


def test_rotation_angle_and_translation():
    T = transform([0.0, 0.0, 30.0], [0.003, -0.004, 0.0])
    assert rotation_angle_deg(T) == pytest.approx(30.0)
    assert rotation_angle_deg(np.eye(4)) == 0.0
    assert rotation_angle_deg(transform([180.0, 0.0, 0.0], [0, 0, 0])) == pytest.approx(180.0)
    np.testing.assert_array_equal(translation_m(T), [0.003, -0.004, 0.0])


@pytest.mark.parametrize(
    "bad", [np.eye(3), np.full((4, 4), np.nan), np.diag([1.0, 1, -1, 1]), np.diag([2.0, 1, 1, 1])]
)
def test_check_rigid_refuses_non_rigid_matrices(bad):
    with pytest.raises(ValueError):
        check_rigid(bad)
    assert not is_rigid(bad)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda T: T[:3], "finite 4x4"),
        (lambda T: np.where(np.eye(4, dtype=bool), np.inf, T), "finite 4x4"),
        (lambda T: T @ np.diag([1.0, 1.0, -1.0, 1.0]), "not a proper rotation"),  # mirrored
        (lambda T: T @ np.diag([1.001, 1.0, 1.0, 1.0]), "not a proper rotation"),  # scaled
        (lambda T: T + np.array([[0, 0.01, 0, 0], [0] * 4, [0] * 4, [0] * 4]), "proper rotation"),
        (lambda T: T + np.array([[0] * 4, [0] * 4, [0] * 4, [0.0, 0.0, 0.01, 0.0]]), "last row"),
    ],
)
def test_check_rigid_names_what_is_wrong(change, message):
    T = change(transform([5.0, 10.0, 80.0], [0.4, 0.1, -0.05]))
    with pytest.raises(ValueError, match=message):
        check_rigid(T, name="the matrix")
    assert not is_rigid(T)


def test_a_matrix_written_with_six_digits_is_rigid_and_a_visible_scale_error_is_not():
    T = transform([5.0, 10.0, 80.0], [0.4, 0.1, -0.05])
    rounded = np.round(T, 6)
    assert is_rigid(rounded)
    np.testing.assert_array_equal(check_rigid(rounded), rounded)
    assert not is_rigid(T @ np.diag([1 + 3 * RIGID_TOLERANCE, 1.0, 1.0, 1.0]))


def test_ur_poses_round_trip_one_and_many():
    T = transform([5.0, -170.0, 30.0], [0.4, 0.1, -0.05])
    pose = pose_from_transform(T)
    assert pose.shape == (6,)
    np.testing.assert_allclose(pose[:3], T[:3, 3])
    np.testing.assert_allclose(transform_from_pose(pose), T, atol=1e-14)
    many = np.stack([T, np.eye(4), invert_transform(T)])
    poses = pose_from_transform(many)
    assert poses.shape == (3, 6)
    np.testing.assert_allclose(transform_from_pose(poses), many, atol=1e-14)


def test_a_half_turn_reads_the_same_whatever_its_last_bits():
    """r and -r are the same half turn; the pose picks one, however the matrix was rounded."""
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    poses = []
    for wobble in (-1e-13, 0.0, 1e-13):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(axis * (np.pi + wobble)).as_matrix()
        poses.append(pose_from_transform(T))
        np.testing.assert_allclose(transform_from_pose(poses[-1]), T, atol=1e-12)
    for pose in poses:
        np.testing.assert_allclose(pose[3:], np.pi * axis, atol=1e-9)
    # Away from the half turn a rotation vector is unique and kept as it is.
    T = transform([0.0, 0.0, -170.0], [0, 0, 0])
    assert pose_from_transform(T)[5] == pytest.approx(np.radians(-170.0))
