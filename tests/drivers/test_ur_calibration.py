"""A UR arm's own kinematics calibration: the controller's calibration.conf read, the calibrated
forward kinematics checked against the controller's DH parameters computed apart, and the
calibrated inverse kinematics round-tripped.

The calibration is the published example of a real UR10e's (the DH parameters its controller
reported, in the documentation of UR's ROS 2 driver, ur_calibration); the offsets are those
minus UR's nominal UR10e parameters.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from drivers.errors import InputFileError
from drivers.robot.ur_calibration import MAX_BYTES, read_ur_calibration
from recon import kinematics

#: The controller's DH parameters of a real UR10e (published example; joint 1..6).
UR10E_DH = {
    "theta": [-2.4147806894359e-07, 1.60233952386695, -1.68607190752171, 0.0837331147700119,
              -1.01260355871158e-07, 3.91986209186124e-08],
    "a": [2.12234865571206e-05, 0.0193171326277006, -0.569251663611088, -4.61409023720934e-05,
          -6.39280053471802e-05, 0.0],
    "d": [0.180539811714259, 439.140974079901, -446.027059806332, 7.0603368964236,
          0.119811341150314, 0.115670917257426],
    "alpha": [1.57014608044242, 0.0013941666682559, 0.00693818880325995, 1.56998468543761,
              -1.57038520649543, 0.0],
}  # fmt: skip


def conf_text(dh=UR10E_DH) -> str:
    """A calibration.conf holding the offsets of ``dh`` from the nominal UR10e."""
    arm = kinematics.model("ur10e")
    nominal = {"theta": np.zeros(6), "a": arm.a, "d": arm.d, "alpha": kinematics.ALPHA}
    lines = ["# written by the controller", "[mounting]"]
    for key in ("theta", "a", "d", "alpha"):
        delta = np.asarray(dh[key]) - nominal[key]
        lines.append(f"delta_{key} = [ " + ", ".join(f"{v:.17g}" for v in delta) + " ]")
    lines += ["joint_checksum = [ 1, 2, 3, 4, 5, 6 ]", "", "[other]", "anything = 1"]
    return "\n".join(lines) + "\n"


def controller_forward(q):
    """The controller's forward kinematics, written apart from recon.kinematics: the chain of
    standard DH transforms of UR10E_DH, one configuration at a time."""
    T = np.eye(4)
    for i in range(6):
        th = q[i] + UR10E_DH["theta"][i]
        a, d, al = UR10E_DH["a"][i], UR10E_DH["d"][i], UR10E_DH["alpha"][i]
        T = T @ np.array(
            [
                [np.cos(th), -np.sin(th) * np.cos(al), np.sin(th) * np.sin(al), a * np.cos(th)],
                [np.sin(th), np.cos(th) * np.cos(al), -np.cos(th) * np.sin(al), a * np.sin(th)],
                [0.0, np.sin(al), np.cos(al), d],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
    return T


@pytest.fixture(scope="module")
def calibrated():
    calibration = read_ur_calibration(conf_text().encode(), name="calibration.conf")
    assert calibration.source == "calibration.conf"
    return kinematics.with_calibration(kinematics.model("ur10e"), calibration)


def test_the_calibrated_flange_is_where_the_controller_puts_it(calibrated):
    q = np.random.default_rng(3).uniform(-np.pi, np.pi, (200, 6))
    ours = kinematics.forward(calibrated, q)
    theirs = np.array([controller_forward(row) for row in q])
    assert np.abs(ours - theirs).max() < 1e-11
    # The links keep their nominal geometry; the flange frame is the calibrated one.
    frames = kinematics.joint_frames(calibrated, q)
    np.testing.assert_allclose(frames[:, 6], ours, atol=1e-15)
    np.testing.assert_allclose(frames[:, 3], kinematics.joint_frames(calibrated.nominal, q)[:, 3])
    assert "calibrated kinematics from calibration.conf" in calibrated.kinematics_words


def test_how_far_a_typical_calibration_moves_the_flange(calibrated):
    """The measurement point 10 asks for: planning with the nominal model puts this UR10e's
    flange 1.9 mm off at median, 3.9 mm at worst (over random configurations)."""
    q = np.random.default_rng(4).uniform(-np.pi, np.pi, (5000, 6))
    difference = kinematics.calibration_difference_m(calibrated, q)
    print(
        f"\nUR10e calibration (published example): flange moved by median "
        f"{np.median(difference) * 1e3:.2f} mm, p99 {np.percentile(difference, 99) * 1e3:.2f} mm, "
        f"max {difference.max() * 1e3:.2f} mm from the nominal model"
    )
    assert 1e-3 < np.median(difference) < 3e-3 and difference.max() < 5e-3


def test_the_calibrated_inverse_kinematics_reaches_the_pose_on_every_branch(calibrated):
    rng = np.random.default_rng(5)
    q = rng.uniform(-np.pi, np.pi, (1000, 6))
    q[:, 2] = rng.uniform(-2.8, 2.8, len(q))
    T = kinematics.forward(calibrated, q)
    solutions = kinematics.inverse(calibrated, T)
    reached = kinematics.forward(calibrated, solutions.q_rad[solutions.valid])
    assert np.abs(reached - np.repeat(T, solutions.valid.sum(axis=1), axis=0)).max() < 1e-9
    # The joints the pose was made from are among the solutions (but at a pose within
    # millimetres of a reach or shoulder boundary, where the nominal branch does not exist).
    dq = np.abs((solutions.q_rad - q[:, None, :] + np.pi) % (2 * np.pi) - np.pi).max(axis=2)
    found = ((dq < 1e-6) & solutions.valid).any(axis=1)
    assert found.mean() > 0.95
    # On average about as many branches as the nominal model finds.
    nominal = kinematics.inverse(calibrated.nominal, T)
    assert solutions.valid.sum() >= 0.98 * nominal.valid.sum()
    # The nominal solutions miss the pose by the calibration's millimetres.
    missed = kinematics.forward(calibrated, nominal.q_rad[nominal.valid])[:, :3, 3]
    target = np.repeat(T, nominal.valid.sum(axis=1), axis=0)[:, :3, 3]
    assert np.median(np.linalg.norm(missed - target, axis=1)) > 1e-3


def test_a_calibration_of_another_arm_type_is_refused():
    calibration = read_ur_calibration(conf_text().encode())
    with pytest.raises(ValueError, match=r"ur5e's flange up to .* mm .* is the robot model right"):
        kinematics.with_calibration(kinematics.model("ur5e"), calibration)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "no [mounting] section"),
        (b"\xff\xfe\x00binary", "is not text"),
        (b"delta_theta = [1,2,3]\n", "not a UR calibration file"),
        (b"[mounting]\ndelta_theta = [0,0,0,0,0,0]\n", "has no delta_a"),
        (conf_text().replace("delta_d = [ ", "delta_d = [ 1, ").encode(), "six finite numbers"),
        (conf_text().replace("delta_a = [ ", "delta_a = [ nan, ").encode(), "six finite"),
        (conf_text().replace("delta_alpha = [ ", "delta_alpha = [ x").encode(), "not six"),
        (re.sub(r"delta_d = \[ [^,]+,", "delta_d = [ 1e300,", conf_text()).encode(), "no arm's"),
        (b"[mounting]\n" + b"delta_theta = [" + b"[" * 5000 + b"\n", "six"),
        (b"[mounting]\n" + b"x" * (MAX_BYTES + 1), "a few"),
    ],
    ids=["empty", "binary", "no-section", "missing-key", "seven", "nan", "text", "huge",
         "nested", "too-big"],
)  # fmt: skip
def test_a_bad_calibration_file_is_refused_saying_what_to_give(content, message):
    with pytest.raises(InputFileError) as refused:
        read_ur_calibration(content, name="calibration.conf")
    assert message in str(refused.value)
    assert "calibration.conf" in str(refused.value)


def test_a_missing_or_oversized_file_is_refused(tmp_path):
    with pytest.raises(InputFileError, match="cannot read the calibration"):
        read_ur_calibration(tmp_path / "missing.conf")
    big = tmp_path / "calibration.conf"
    with big.open("wb") as handle:  # sparse: its size says more than anything read
        handle.truncate(MAX_BYTES * 100)
    with pytest.raises(InputFileError, match="a few kilobytes"):
        read_ur_calibration(big)


# --- the calibration through planning, the trajectory file, the dry run and the gate -----------


@pytest.fixture(scope="module")
def calibrated_plan(calibrated):
    """A 150 mm line in front of a UR10e, planned with its calibration."""
    from recon.plan import plan_path
    from recon.plan_params import PlanParams

    s = np.linspace(0.0, 0.15, 151)
    points = np.column_stack([0.6 + 0 * s, -0.075 + s, np.full_like(s, 0.1)])
    params = PlanParams(robot="ur10e", speed_m_s=0.1)
    return plan_path(points, params=params, calibration=calibrated.calibration)


def test_a_plan_made_with_the_calibration_puts_the_real_flange_on_the_path(
    calibrated_plan, calibrated
):
    """Its joints, run by the controller's kinematics (computed apart), put the TCP where the
    plan says within 1e-9 m; the nominal model's joints would be millimetres off."""
    trajectory = calibrated_plan.trajectory
    assert trajectory.calibration.same_as(calibrated.calibration)
    assert "calibrated kinematics from calibration.conf" in "\n".join(
        calibrated_plan.report_lines()
    )
    T_flange_tcp = calibrated_plan.params.T_flange_tcp
    rows = np.linspace(0, len(trajectory) - 1, 50).astype(int)
    real = np.array([controller_forward(q) @ T_flange_tcp for q in trajectory.q_rad[rows]])
    assert np.abs(real[:, :3, 3] - trajectory.tcp_m[rows]).max() < 1e-9
    nominal = kinematics.forward(calibrated.nominal, trajectory.q_rad[rows]) @ T_flange_tcp
    assert np.linalg.norm(nominal[:, :3, 3] - trajectory.tcp_m[rows], axis=1).max() > 1e-3


def test_the_trajectory_file_keeps_its_calibration_and_a_forged_one_is_refused(
    calibrated_plan, tmp_path
):
    import json

    from drivers.export import read_trajectory_csv, write_trajectory_csv

    path = tmp_path / "plan.csv"
    write_trajectory_csv(path, calibrated_plan.trajectory)
    back = read_trajectory_csv(path).trajectory
    assert back.calibration.same_as(calibrated_plan.trajectory.calibration)
    assert back.arm.calibration is not None
    meta, rest = path.read_text().split("\n", 1)
    head = json.loads(meta.removeprefix("# teachpath: "))
    head["calibration"]["delta_d_m"] = [1.0, 2.0]
    path.write_text("# teachpath: " + json.dumps(head) + "\n" + rest)
    with pytest.raises(InputFileError, match="the calibration it names is not one"):
        read_trajectory_csv(path)


def test_the_gate_refuses_joints_solved_for_another_model_of_the_arm(calibrated_plan, tmp_path):
    """A server with this arm's calibration refuses a plan solved with the nominal model (and
    a server without one a calibrated plan), naming how far the flange would be off."""
    from dataclasses import replace

    from service import errors as refusals
    from service import gate
    from service.settings import Settings

    conf = tmp_path / "calibration.conf"
    conf.write_text(conf_text())
    with_it = Settings(data_dir=tmp_path / "a", ur_robot="ur10e", ur_calibration=conf)
    without = Settings(data_dir=tmp_path / "b", ur_robot="ur10e")
    planned = calibrated_plan.trajectory
    assert gate._arm_here(with_it, planned).calibration is not None
    with pytest.raises(refusals.TrajectoryForAnotherRobot, match=r"nominal kinematics.*mm from"):
        gate._arm_here(with_it, replace(planned, calibration=None))
    with pytest.raises(refusals.TrajectoryForAnotherRobot, match="no ur_calibration"):
        gate._arm_here(without, planned)
    assert gate._arm_here(without, replace(planned, calibration=None)).calibration is None
    # Two calibrations: the difference named is between them, not against the nominal model.
    other = kinematics.DHCalibration(
        **{
            **{k: v for k, v in planned.calibration.as_dict().items() if k != "source"},
            "delta_a_m": planned.calibration.delta_a_m + [0, 0.001, 0, 0, 0, 0],
        },
        source="other.conf",
    )
    with pytest.raises(refusals.TrajectoryForAnotherRobot, match="other.conf") as refused:
        gate._arm_here(with_it, replace(planned, calibration=other))
    assert 0.5e-3 < refused.value.detail["flange_difference_m"] <= 1.0e-3 + 1e-9
    # A calibration that is not this arm type's (a forged file): refused, not a crash.
    wrong = kinematics.DHCalibration(**{**other.as_dict(), "delta_d_m": [0.5] * 6})
    with pytest.raises(refusals.TrajectoryForAnotherRobot, match="not this ur10e's"):
        gate._arm_here(without, replace(planned, calibration=wrong))


def test_a_server_refuses_to_start_with_a_calibration_it_cannot_use(tmp_path):
    from pydantic import ValidationError

    from service.settings import Settings

    conf = tmp_path / "calibration.conf"
    conf.write_text(conf_text())
    with pytest.raises(ValidationError, match="is the robot model right"):
        Settings(data_dir=tmp_path / "a", ur_robot="ur5e", ur_calibration=conf)
    conf.write_text("[mounting]\n")
    with pytest.raises(ValidationError, match="has no delta_theta"):
        Settings(data_dir=tmp_path / "a", ur_robot="ur10e", ur_calibration=conf)


def test_coarse_waypoints_of_a_calibrated_plan_are_judged_on_its_own_arm(calibrated_plan):
    """movePath's waypoints of a plan solved with the calibration: judged with the calibrated
    forward kinematics (the plan's TCP), they keep within the tolerance with about as few
    waypoints as the nominal model's plan needs; judged with the nominal model, every sample
    broke the 0.5 mm tolerance by the calibration's millimetres."""
    from recon.waypoints import coarse_waypoints

    trajectory = calibrated_plan.trajectory
    path = coarse_waypoints(trajectory.arm, trajectory, tolerance_m=5e-4)
    assert path.deviation_max_m <= 5e-4
    assert len(path) < len(trajectory) / 20
