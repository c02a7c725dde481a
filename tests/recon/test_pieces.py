"""A trace in pieces (long dropouts, lift-offs): reconstructed piece by piece against one
registration, planned as one motion that lifts, transits and approaches between the pieces."""

import numpy as np
import pytest

from recon import scenes
from recon.arrays import piece_labels, piece_slices
from recon.collision import ContactZone
from recon.inputs import Recording
from recon.kinematics import forward, model
from recon.metrics import distance_to_curve
from recon.paths import Phase
from recon.plan import PlanParams, plan_path
from recon.recon_params import ReconParams
from recon.reconstruct import reconstruct


@pytest.fixture(scope="module")
def box_in_two():
    """The box-corner scene with 0.4 s of its trace lost at 30 %: two pieces."""
    scene = scenes.box_corner(0)
    rec = scene.recording
    cut = rec.t_s[int(0.3 * len(rec))]
    parts = [rec.t_s < cut - 0.2, rec.t_s > cut + 0.2]
    pieces = [Recording(points_m=rec.points_m[k], t_s=rec.t_s[k]) for k in parts]
    return scene, pieces, Recording.joined(pieces)


def test_piece_labels_count_in_order_and_refuse_anything_else():
    assert piece_labels(None, 3).tolist() == [0, 0, 0]
    assert [(s.start, s.stop) for s in piece_slices(piece_labels([0, 0, 1, 1, 1], 5))] == [
        (0, 2),
        (2, 5),
    ]
    for bad, words in (
        ([1, 1, 1], "in order"),
        ([0, 0, 2, 2], "in order"),
        ([0, 1, 1, 0], "in order"),
        ([0, 0, 1], "at least two"),
        ([0, 0], "2 values for 3"),
        ([0, 10**12, 0], "in order"),
    ):
        with pytest.raises(ValueError, match=words):
            piece_labels(bad, 3 if len(bad) != 4 and len(bad) != 5 else len(bad))


def test_a_joined_recording_keeps_its_pieces_and_gives_them_back(box_in_two):
    _, pieces, joined = box_in_two
    assert joined.n_pieces == 2 and len(joined) == sum(len(p) for p in pieces)
    for mine, theirs in zip(joined.pieces(), pieces, strict=True):
        np.testing.assert_array_equal(mine.points_m, theirs.points_m)
        np.testing.assert_array_equal(mine.t_s, theirs.t_s)


def test_pieces_are_reconstructed_apart_with_one_registration(box_in_two):
    scene, pieces, joined = box_in_two
    recon = reconstruct(joined, scene.scan)
    assert recon.piece[0] == 0 and recon.piece[-1] == 1
    # No segment spans the two pieces, and nothing was resampled across the gap: the largest
    # step along each piece is the spacing, the gap is the only long one.
    boundary = int(np.flatnonzero(np.diff(recon.piece))[0]) + 1
    assert all(s.stop <= boundary or s.start >= boundary for s in recon.segments)
    steps = np.linalg.norm(np.diff(recon.input_points_m, axis=0), axis=1)
    assert steps[boundary - 1] > 5 * np.delete(steps, boundary - 1).max()
    # Against the ground truth, in the tracker frame: every point and the four ends.
    error = distance_to_curve(recon.points_m, scene.truth_m)
    ends = error[[0, boundary - 1, boundary, -1]]
    print(f"max {error.max() * 1e3:.2f} mm, ends {np.round(ends * 1e3, 2)} mm")
    assert error.max() < 1.5e-3 and ends.max() < 1.5e-3
    # Independent check: each piece reconstructed alone, at the registration found for both.
    # The scan model is then cropped around one piece instead of both, which moves where the
    # corner's edge fit gives way to the path (up to 1.2 mm there, measured); elsewhere the two
    # agree, and the joined one is as close to the truth.
    fixed = ReconParams(register=False)
    for k, piece in enumerate(pieces):
        alone = reconstruct(
            piece, scene.scan, params=fixed, T_scan_tracker_init=recon.T_scan_tracker
        )
        mine = recon.points_m[recon.piece == k]
        apart = np.linalg.norm(mine - alone.points_m, axis=1)
        alone_error = distance_to_curve(alone.points_m, scene.truth_m)
        joined_error = distance_to_curve(mine, scene.truth_m)
        print(
            f"piece {k}: {np.median(apart) * 1e3:.3f} mm apart (median), truth "
            f"{joined_error.max() * 1e3:.2f} mm joined, {alone_error.max() * 1e3:.2f} alone"
        )
        assert np.median(apart) < 0.1e-3
        assert joined_error.max() < alone_error.max() + 0.1e-3


def test_a_path_in_two_pieces_lifts_transits_and_approaches_between_them():
    s = np.linspace(0.0, 0.08, 81)
    first = np.column_stack([0.4 + 0 * s, -0.12 + s, np.full_like(s, 0.1)])
    second = np.column_stack([0.4 + 0 * s, 0.04 + s, np.full_like(s, 0.1)])
    params = PlanParams(speed_m_s=0.05)
    plan = plan_path(np.vstack([first, second]), params=params, piece=np.repeat([0, 1], [81, 81]))
    traj = plan.trajectory
    assert [phase for phase, _ in traj.runs()] == [
        Phase.TRANSIT,
        Phase.APPROACH,
        Phase.PROCESS,
        Phase.RETRACT,
        Phase.TRANSIT,
        Phase.APPROACH,
        Phase.PROCESS,
        Phase.RETRACT,
    ]
    assert plan.n_pieces == 2 and "in 2 pieces" in plan.report_lines()[0]
    arm = model("ur5e")
    tcp = (forward(arm, traj.q_rad) @ params.T_flange_tcp)[:, :3, 3]
    runs = traj.runs()
    # Each process run follows its own piece, and only its piece.
    processes = [rows for phase, rows in runs if phase is Phase.PROCESS]
    for rows, piece in zip(processes, (first, second), strict=True):
        assert distance_to_curve(tcp[rows], piece).max() < 1e-4
        assert np.linalg.norm(tcp[rows][[0, -1]] - piece[[0, -1]], axis=1).max() < 1e-6
    # Between the pieces the tool is never below the approach height above the work: the
    # untraced gap is crossed in the air, not along the table.
    between = slice(runs[3][1].start, runs[5][1].stop)
    assert tcp[between, 2].min() > 0.1 - 1e-6
    assert tcp[runs[4][1], 2].min() >= 0.1 + plan.approach_m - 1e-3
    # Limits at every sample, and at rest where the runs meet.
    assert np.all(np.abs(traj.qd_rad_s) <= arm.qd_max_rad_s * 1.001)
    for _, rows in runs:
        assert np.abs(traj.qd_rad_s[[rows.start, rows.stop - 1]]).max() < 1e-9
    # One configuration throughout.
    assert plan.configuration.elbow == "up"
    with pytest.raises(ValueError, match="runs"):
        traj.of_phase(Phase.PROCESS)
    # Arc length runs along the traced path only (the gap is not counted).
    assert plan.tool.arc_length_m[-1] == pytest.approx(0.16, abs=1e-9)


def test_the_contact_zone_follows_each_piece_and_not_the_gap():
    path = np.array([[0.0, 0, 0], [0.01, 0, 0], [0.09, 0, 0], [0.1, 0, 0]])
    up = np.tile([0.0, 0.0, 1.0], (len(path), 1))
    one = ContactZone(path_m=path, tool_axes=up).points(0.001)
    two = ContactZone(path_m=path, tool_axes=up, piece=[0, 0, 1, 1]).points(0.001)
    assert np.abs(one[:, 0] - 0.05).min() < 1e-3  # one piece: the zone covers the middle
    assert np.abs(two[:, 0] - 0.05).min() > 0.039  # two: nothing between 10 and 90 mm
