"""The real-arm gate on its own: every refusal by name, and dry runs that must not count."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from drivers.robot.monitor import ArmState
from recon import kinematics, motion
from recon.collision import Box, Cell
from recon.kinematics import HOME_Q_RAD
from recon.plan_params import DEFAULT_TCP_POSE
from recon.trajectory import JointTrajectory
from recon.transforms import transform_from_pose
from service import errors as refusals
from service import gate
from service.artifacts import TrajectorySummary
from service.robot import Reading
from service.settings import Settings
from service.store import ArtifactRow

START = HOME_Q_RAD
TRAJECTORY_SUMMARY = {
    "robot": "ur5e",
    "requested_speed_m_s": 0.05,
    "duration_s": 4.0,
    "n_samples": 2000,
    "rate_hz": 500.0,
    "path_length_m": 0.2,
    "tool_axis_from": "scan",
    "ik_branch": 0,
    "min_limit_margin_rad": 1.0,
    "min_wrist_singularity": 0.5,
    "min_elbow_singularity": 0.5,
    "min_shoulder_margin_m": 0.1,
}


def passed_dry_run(**changes) -> dict:
    summary = {
        "backend": "sim",
        "dry_run": True,
        "robot": "ur5e",
        "mode": "servoj",
        "tolerance_m": 5e-4,
        "completed": True,
        "faults": [],
        "n_samples": 2050,
    }
    summary.update(changes)
    return summary


def row(artifact_id: str, summary: dict, trajectory_id: str = "trj_1") -> ArtifactRow:
    return ArtifactRow(
        id=artifact_id, kind="execution", inputs={"trajectory_id": trajectory_id}, summary=summary
    )


@pytest.fixture
def settings(tmp_path):
    return Settings(data_dir=tmp_path, ur_host="127.0.0.9", ur_robot="ur5e", max_speed_m_s=0.1)


@pytest.fixture
def trajectory():
    return ArtifactRow(id="trj_1", kind="trajectory", inputs={}, summary=TRAJECTORY_SUMMARY)


def arm_at(q, **state) -> Reading:
    """A fresh reading of a healthy arm at joints ``q`` (fields of ArmState to change)."""
    fields = {
        "robot_mode": "RUNNING",
        "safety_status": "NORMAL",
        "remote_control": True,
        "q_rad": tuple(q),
        **state,
    }
    return Reading(ArmState(backend="ur_rtde", reachable=True, **fields), time.monotonic(), None)


def a_trajectory(robot: str = "ur5e") -> JointTrajectory:
    """A real motion from the start: a joint move at the transit's default limits and cap."""
    arm = kinematics.model(robot)
    move = motion.joint_move(
        arm,
        np.array(START),
        np.array(START) + [0.4, -0.2, 0.3, 0.1, 0.0, 0.2],
        speed_scale=0.3,
        acceleration_scale=0.3,
        tcp_speed_max_m_s=0.1,
        T_flange_tcp=TOOL,
    )
    return motion.assemble(arm, [move], T_flange_tcp=TOOL, requested_speed_m_s=0.05)


TOOL = transform_from_pose(np.array(DEFAULT_TCP_POSE))
EMPTY_CELL = gate.CellHere(cell=Cell(), T_flange_tcp=TOOL, tool_radius_m=0.02, clearance_m=0.01)


def checked(trajectory_id: str = "trj_1") -> gate.CheckedHere:
    loaded = a_trajectory()
    return gate.CheckedHere(
        trajectory_id=trajectory_id,
        trajectory=loaded,
        summary=TrajectorySummary.model_validate(TRAJECTORY_SUMMARY),
        min_clearance_m=1.0,
        fastest_tcp_m_s=0.1,
    )


def check(
    settings,
    trajectory,
    dry_runs,
    *,
    confirm=True,
    mode="servoj",
    tolerance_m=5e-4,
    owner=None,
    arm=None,
    made_here=None,
):
    """The whole gate as the service runs it: the samples here, then the rest."""
    here = gate.check_here(settings, trajectory, a_trajectory(), EMPTY_CELL)
    gate.check_real_arm(
        settings,
        here,
        dry_runs,
        dry_runs_made_here={r.id for r in dry_runs} if made_here is None else made_here,
        confirm=confirm,
        mode=mode,
        tolerance_m=tolerance_m,
        owner=owner,
        arm=arm_at(START) if arm is None else arm,
    )
    return here.summary


def test_a_passed_dry_run_in_the_same_mode_lets_the_arm_run(settings, trajectory):
    summary = check(settings, trajectory, [row("exe_1", passed_dry_run())])
    assert summary.robot == "ur5e" and summary.requested_speed_m_s == 0.05


@pytest.mark.parametrize(
    ("dry_run", "why"),
    [
        (passed_dry_run(faults=["protective stop"]), "faulted"),
        (passed_dry_run(completed=False), "incomplete"),
        (passed_dry_run(mode="movepath"), "another mode"),
        (passed_dry_run(backend="ur_rtde", dry_run=False), "a real run, not a dry run"),
        (passed_dry_run(dry_run=False), "not marked as a dry run"),
        ({"completed": True, "faults": []}, "an older record without mode, backend, ..."),
        ({**passed_dry_run(), "completed": "yes"}, "a field of the wrong type"),
        ({}, "an empty summary"),
    ],
)
def test_dry_runs_that_do_not_count(settings, trajectory, dry_run, why):
    with pytest.raises(refusals.DryRunRequired):
        check(settings, trajectory, [row("exe_1", dry_run)])


def test_a_dry_run_of_another_trajectory_does_not_count(settings, trajectory):
    with pytest.raises(refusals.DryRunRequired):
        check(settings, trajectory, [row("exe_1", passed_dry_run(), trajectory_id="trj_2")])


def test_movepath_needs_a_dry_run_with_the_same_tolerance(settings, trajectory):
    dry = [row("exe_1", passed_dry_run(mode="movepath", tolerance_m=1e-3))]
    with pytest.raises(refusals.DryRunRequired, match="tolerance_m"):
        check(settings, trajectory, dry, mode="movepath", tolerance_m=5e-4)
    assert check(settings, trajectory, dry, mode="movepath", tolerance_m=1e-3)


@pytest.mark.parametrize("confirm", [False, None, "yes", 1, "true"])
def test_only_the_boolean_true_confirms(settings, trajectory, confirm):
    with pytest.raises(refusals.ConfirmationRequired):
        check(settings, trajectory, [row("exe_1", passed_dry_run())], confirm=confirm)


def test_the_speed_cap(settings, trajectory):
    fast = ArtifactRow(
        id="trj_1",
        kind="trajectory",
        inputs={},
        summary={**TRAJECTORY_SUMMARY, "requested_speed_m_s": 0.2},
    )
    with pytest.raises(refusals.SpeedCapExceeded, match="0.1 m/s"):
        check(settings, fast, [row("exe_1", passed_dry_run())])


def test_no_arm_configured(tmp_path, trajectory):
    with pytest.raises(refusals.NoRobotConfigured):
        check(Settings(data_dir=tmp_path), trajectory, [row("exe_1", passed_dry_run())])


def test_a_trajectory_for_another_robot(settings):
    other = ArtifactRow(
        id="trj_1", kind="trajectory", inputs={}, summary={**TRAJECTORY_SUMMARY, "robot": "ur10e"}
    )
    with pytest.raises(refusals.TrajectoryForAnotherRobot, match="ur10e"):
        check(settings, other, [row("exe_1", passed_dry_run())])


def test_a_trajectory_whose_summary_cannot_be_read_is_refused(settings):
    broken = ArtifactRow(id="trj_1", kind="trajectory", inputs={}, summary={"robot": "ur5e"})
    with pytest.raises(refusals.UnreadableTrajectory):
        check(settings, broken, [row("exe_1", passed_dry_run())])


def test_one_arm_owner(settings, trajectory):
    with pytest.raises(refusals.ArmBusy, match="exe_7") as refused:
        check(settings, trajectory, [row("exe_1", passed_dry_run())], owner="exe_7")
    assert refused.value.detail == {"execution_id": "exe_7"}


def test_an_arm_away_from_the_start_is_refused_with_the_distance(settings, trajectory):
    moved = np.array(START) + [0.0, 0.0, 0.05, 0.0, 0.0, 0.0]
    with pytest.raises(refusals.StartMoved, match="joint 3") as refused:
        check(settings, trajectory, [row("exe_1", passed_dry_run())], arm=arm_at(moved))
    assert refused.value.detail["max_joint_deg"] == pytest.approx(np.degrees(0.05))
    assert refused.value.detail["flange_distance_m"] > 0.01
    # Within the tolerance it runs.
    close = np.array(START) + 0.5 * gate.START_TOLERANCE_RAD
    assert check(settings, trajectory, [row("exe_1", passed_dry_run())], arm=arm_at(close))


@pytest.mark.parametrize(
    ("state", "refusal"),
    [
        (
            {"protective_stop": True, "safety_status": "PROTECTIVE_STOP"},
            refusals.ArmInProtectiveStop,
        ),
        ({"emergency_stop": True}, refusals.ArmInEmergencyStop),
        ({"remote_control": False}, refusals.RemoteControlOff),
        # Released after an emergency stop, the arm is still powered off; a mode not read
        # decides nothing.
        ({"robot_mode": "POWER_OFF"}, refusals.ArmNotRunning),
        ({"robot_mode": "IDLE"}, refusals.ArmNotRunning),
        ({"robot_mode": "UNKNOWN"}, refusals.ArmNotRunning),
    ],
)
def test_an_arm_that_cannot_run_now_is_refused(settings, trajectory, state, refusal):
    with pytest.raises(refusal):
        check(settings, trajectory, [row("exe_1", passed_dry_run())], arm=arm_at(START, **state))


def test_an_arm_whose_state_is_not_known_is_refused(settings, trajectory):
    unreachable = Reading(ArmState.unreachable("ur_rtde", "127.0.0.9: no answer"), 0.0, None)
    with pytest.raises(refusals.RobotUnavailable, match="127.0.0.9"):
        check(settings, trajectory, [row("exe_1", passed_dry_run())], arm=unreachable)
    stale = Reading(arm_at(START).state, time.monotonic() - 60.0, None)
    with pytest.raises(refusals.RobotUnavailable, match="60"):
        check(settings, trajectory, [row("exe_1", passed_dry_run())], arm=stale)


def test_every_refusal_has_its_own_code():
    """Every reason the gate can give (each subclass of RealArmRefused) has a 409 and a code of
    its own, not the base's generic one: a new reason without its code fails here."""
    from service.errors import classify

    reasons = refusals.RealArmRefused.__subclasses__()
    assert len(reasons) >= 17
    codes = [classify(cls("x")) for cls in reasons]
    assert all(status == 409 for status, _ in codes)
    assert "real_arm_refused" not in {code for _, code in codes}
    assert len({code for _, code in codes}) == len(reasons)


def test_a_dry_run_not_made_here_does_not_count(settings, trajectory):
    """An imported dry run (no job of this service made it) proves nothing here."""
    with pytest.raises(refusals.DryRunRequired, match="imported"):
        check(settings, trajectory, [row("exe_1", passed_dry_run())], made_here=set())


# -- the samples, judged here -----------------------------------------------------------------


def retimed(trajectory: JointTrajectory, factor: float) -> JointTrajectory:
    """The same joint path run ``factor`` times faster, on the controller's grid (a forgery)."""
    from dataclasses import replace

    t = trajectory.t_s / factor
    grid = np.arange(int(np.ceil(t[-1] * 500)) + 1) / 500
    q = np.stack([np.interp(grid, t, trajectory.q_rad[:, j]) for j in range(6)], axis=1)
    zeros = np.zeros_like(q)
    return replace(
        trajectory,
        t_s=grid,
        q_rad=q,
        qd_rad_s=zeros,
        qdd_rad_s2=zeros,
        tcp_m=np.zeros((len(grid), 3)),
        tcp_rotvec=np.zeros((len(grid), 3)),
        arc_length_m=np.zeros(len(grid)),
        phase=None,
    )


def test_the_samples_of_a_planned_motion_pass(settings, trajectory):
    here = gate.check_here(settings, trajectory, a_trajectory(), EMPTY_CELL)
    assert here.trajectory_id == "trj_1"
    assert 0.05 < here.fastest_tcp_m_s <= 0.1  # the transit's cap held, seen on the samples


def test_samples_faster_than_the_arm_or_the_cap_are_refused_whatever_the_summary_says(
    settings, trajectory
):
    """The forged bundle: arrays run several times faster than planned, a summary that says
    0.05 m/s. The samples decide."""
    fast = retimed(a_trajectory(), 40.0)
    with pytest.raises(refusals.SamplesOutsideLimits) as refused:
        gate.check_here(settings, trajectory, fast, EMPTY_CELL)
    assert {"speed", "tcp_speed"} <= set(refused.value.detail["checks"])
    assert "mm/s" in str(refused.value) or "rad/s" in str(refused.value)


def test_a_transit_above_the_servers_tcp_cap_is_refused(tmp_path, trajectory):
    """Joint speeds within the arm's limits, the TCP (and the wrists with it) faster than this
    server allows: the cap holds for every point of the arm, as UR's safety limits do."""
    slow_cap = Settings(data_dir=tmp_path, ur_host="127.0.0.9", ur_robot="ur5e", max_speed_m_s=0.05)
    with pytest.raises(refusals.SamplesOutsideLimits, match="50 mm/s cap") as refused:
        gate.check_here(slow_cap, trajectory, a_trajectory(), EMPTY_CELL)
    assert refused.value.detail["checks"] == ["tcp_speed", "link_speed"]


def test_samples_off_the_controllers_grid_are_refused(settings, trajectory):
    from dataclasses import replace

    planned = a_trajectory()
    stretched = replace(planned, t_s=planned.t_s * 1.5)
    with pytest.raises(refusals.SamplesOutsideLimits, match="every 2 ms"):
        gate.check_here(settings, trajectory, stretched, EMPTY_CELL)


def test_a_keep_out_box_of_this_cell_on_the_motion_is_refused(settings, trajectory):
    """A plan made in a cell without this box (imported) collides here."""
    planned = a_trajectory()
    tcp = (kinematics.forward(kinematics.model("ur5e"), planned.q_rad) @ TOOL)[:, :3, 3]
    middle = tcp[len(tcp) // 2]
    box = Box(min_m=middle - 0.03, max_m=middle + 0.03, name="keep-out box 1")
    cell = gate.CellHere(
        cell=Cell(boxes=(box,)), T_flange_tcp=TOOL, tool_radius_m=0.02, clearance_m=0.01
    )
    with pytest.raises(refusals.CollidesHere, match="keep-out box 1") as refused:
        gate.check_here(settings, trajectory, planned, cell)
    assert refused.value.detail["obstacle"] == "keep-out box 1"


def test_the_tool_is_checked_here_as_it_was_planned_spheres_included(settings, trajectory):
    """A box 90 mm beside the tool's tip: clear of the planned 20 mm capsule, inside a tool
    given as a 100 mm sphere at the tip (``tool_spheres_m``): refused for the spheres."""
    planned = a_trajectory()
    tcp = (kinematics.forward(kinematics.model("ur5e"), planned.q_rad) @ TOOL)[:, :3, 3]
    beside = tcp[len(tcp) // 2] + np.array([0.0, 0.0, -0.09])
    box = Box(min_m=beside - 0.02, max_m=beside + 0.02, name="keep-out box 1")
    capsule = gate.CellHere(
        cell=Cell(boxes=(box,)), T_flange_tcp=TOOL, tool_radius_m=0.02, clearance_m=0.01
    )
    gate.check_here(settings, trajectory, planned, capsule)
    tip = TOOL[:3, 3]
    spheres = replace(capsule, tool_spheres_m=(*tip, 0.1))
    with pytest.raises(refusals.CollidesHere, match="keep-out box 1") as refused:
        gate.check_here(settings, trajectory, planned, spheres)
    assert refused.value.detail["link"] == "tool"


def test_a_trajectory_for_another_arm_is_refused_even_if_the_summary_agrees(settings, trajectory):
    with pytest.raises(refusals.TrajectoryForAnotherRobot):
        gate.check_here(settings, trajectory, a_trajectory("ur10e"), EMPTY_CELL)
