"""UR kinematics: FK/IK round trips for every model, and an independent implementation."""

import numpy as np
import pytest
import ur_analytic_ik

from recon.errors import InfeasibleTrajectoryError
from recon.kinematics import UR_MODELS, follow_path, forward, inverse, model

MODELS = sorted(UR_MODELS)


@pytest.mark.parametrize("name", MODELS)
def test_ik_round_trips_random_poses(name):
    arm = model(name)
    rng = np.random.default_rng(0)
    q = rng.uniform(-np.pi, np.pi, (500, 6))
    poses = forward(arm, q)
    sol = inverse(arm, poses)
    reached = forward(arm, sol.q_rad)
    error = np.abs(reached - poses[:, None]).max(axis=(2, 3))
    assert error[sol.valid].max() < 1e-9
    # The configuration that made the pose is always among the eight solutions.
    diff = np.abs((sol.q_rad - q[:, None] + np.pi) % (2 * np.pi) - np.pi).max(axis=2)
    assert np.all((diff < 1e-6).any(axis=1))
    assert sol.valid.sum(axis=1).min() >= 1


@pytest.mark.parametrize("name", MODELS)
def test_forward_kinematics_matches_ur_analytic_ik(name):
    arm = model(name)
    other = getattr(ur_analytic_ik, name)
    rng = np.random.default_rng(1)
    for q in rng.uniform(-np.pi, np.pi, (50, 6)):
        np.testing.assert_allclose(forward(arm, q), other.forward_kinematics(*q), atol=1e-12)


@pytest.mark.parametrize("name", MODELS)
def test_every_ur_analytic_ik_solution_is_one_of_ours(name):
    """ur-analytic-ik may miss a branch at some poses; whatever it finds, we find too."""
    arm = model(name)
    other = getattr(ur_analytic_ik, name)
    rng = np.random.default_rng(2)
    q = rng.uniform(-np.pi, np.pi, (100, 6))
    poses = forward(arm, q)
    ours = inverse(arm, poses)
    missing = 0
    for i, pose in enumerate(poses):
        for theirs in other.inverse_kinematics(pose):
            diff = np.abs((ours.q_rad[i] - theirs + np.pi) % (2 * np.pi) - np.pi).max(axis=1)
            missing += int(not np.any((diff < 1e-6) & ours.valid[i]))
    assert missing == 0


def test_unknown_model_lists_the_known_ones():
    with pytest.raises(ValueError, match="ur5e"):
        model("kuka")


def _line_poses(start, end, n=200):
    """Flange poses along a straight line, tool pointing down."""
    T = np.tile(np.diag([1.0, -1.0, -1.0, 1.0]), (n, 1, 1))
    T[:, :3, 3] = np.linspace(start, end, n)
    return T


def test_a_reachable_line_keeps_one_branch_without_jumps():
    arm = model("ur5e")
    path = follow_path(arm, _line_poses([0.4, -0.2, 0.2], [0.4, 0.2, 0.2]))
    assert np.abs(np.diff(path.q_rad, axis=0)).max() < 0.05
    np.testing.assert_allclose(
        forward(arm, path.q_rad)[:, :3, 3],
        np.linspace([0.4, -0.2, 0.2], [0.4, 0.2, 0.2], 200),
        atol=1e-9,
    )
    assert np.all(path.q_rad >= arm.q_min_rad) and np.all(path.q_rad <= arm.q_max_rad)


def test_an_unreachable_waypoint_is_named():
    arm = model("ur5e")
    with pytest.raises(InfeasibleTrajectoryError, match=r"waypoint \d+ .* out of reach"):
        follow_path(arm, _line_poses([0.5, 0.0, 0.2], [1.5, 0.0, 0.2]))


def test_a_path_through_the_shoulder_singularity_is_refused():
    arm = model("ur5e")
    with pytest.raises(InfeasibleTrajectoryError, match="shoulder|base's axis"):
        follow_path(arm, _line_poses([-0.2, -0.133, 0.4], [0.2, -0.133, 0.4]))


def test_a_wrist_singularity_is_avoided_by_another_branch_or_refused():
    arm = model("ur5e")
    # Poses made by sweeping joint 5 through zero: on that branch joints 4 and 6 align.
    q = np.tile([0.3, -1.2, 1.4, -1.7, 0.0, 0.4], (100, 1))
    q[:, 4] = np.linspace(-0.3, 0.3, 100)
    poses = forward(arm, q)
    path = follow_path(arm, poses)  # another branch follows it far from the singularity
    assert path.wrist_singularity.min() > 0.2
    singular = [
        b
        for b in range(8)
        if inverse(arm, poses[:1]).valid[0, b]
        and abs(inverse(arm, poses[:1]).q_rad[0, b, 4] - q[0, 4]) < 1e-6
    ]
    with pytest.raises(InfeasibleTrajectoryError, match="wrist|jump"):
        follow_path(arm, poses, allowed_branches=tuple(singular))


def test_the_nearest_branch_to_the_current_joints_is_kept():
    arm = model("ur5e")
    poses = _line_poses([0.4, -0.1, 0.2], [0.4, 0.1, 0.2], 50)
    sol = inverse(arm, poses[:1])
    for branch in np.flatnonzero(sol.valid[0]):
        near = sol.q_rad[0, branch]
        path = follow_path(arm, poses, q_near_rad=near)
        diff = np.abs((path.q_rad[0] - near + np.pi) % (2 * np.pi) - np.pi).max()
        if path.branch == branch:
            assert diff < 1e-9


@pytest.mark.parametrize("y_m", [-0.25, -0.1, 0.0, 0.15])
def test_equally_good_branches_are_told_apart_by_the_elbow_not_by_rounding(y_m):
    """Elbow-up and elbow-down solutions of a pose have the same margins; which one is kept must
    not depend on the last bits of the arithmetic (a numpy upgrade flipped it once)."""
    from recon.kinematics import configuration_of

    arm = model("ur5e")
    poses = _line_poses([0.45, y_m, 0.15], [0.45, y_m + 0.1, 0.15], 40)
    path = follow_path(arm, poses)
    assert configuration_of(arm, path.q_rad[0]).elbow == "up"
    # Rounding noise below the comparison's precision does not change the choice.
    nudged = poses.copy()
    nudged[:, :3, 3] += 1e-13
    assert follow_path(arm, nudged).branch == path.branch


@pytest.mark.parametrize("name", MODELS)
def test_joint_frames_end_at_the_flange_and_put_each_joint_axis_on_z(name):
    from recon.kinematics import joint_frames

    arm = model(name)
    q = np.random.default_rng(3).uniform(-np.pi, np.pi, (20, 6))
    frames = joint_frames(arm, q)
    assert frames.shape == (20, 7, 4, 4)
    np.testing.assert_allclose(frames[:, 0], np.broadcast_to(np.eye(4), (20, 4, 4)))
    np.testing.assert_allclose(frames[:, 6], forward(arm, q), atol=1e-12)
    # Turning joint k + 1 leaves frame k where it is and turns the next about frame k's z-axis.
    q2 = q.copy()
    q2[:, 2] += 0.3
    moved = joint_frames(arm, q2)
    np.testing.assert_allclose(moved[:, :3], frames[:, :3], atol=1e-12)
    np.testing.assert_allclose(moved[:, 3, :3, 2], frames[:, 3, :3, 2], atol=1e-12)
