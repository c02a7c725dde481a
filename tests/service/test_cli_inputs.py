"""The command line's input options: calibrations, tip offsets, pieces, stored scan poses."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivers.calibration import write_calibration, write_tip_calibration
from drivers.scanning.pointcloud import write_scan
from drivers.tracking.canonical_csv import write_trace_csv
from recon import scenes
from recon.inputs import Recording
from tests.recon.test_calibrate import PIVOT_M, TIP_M, pivot_recording
from tests.service.test_cli import run


def test_calibrate_pivot_prints_and_saves_the_tip(tmp_path):
    position, quat = pivot_recording(0)
    rec = Recording(points_m=position, t_s=np.arange(len(position)) / 240.0, orientations_xyzw=quat)
    write_trace_csv(tmp_path / "pivot.csv", rec)
    result = run("calibrate", "pivot", tmp_path / "pivot.csv", "--out", tmp_path / "tip.json")
    assert result.returncode == 0, result.stderr
    assert "tip offset (4.0" in result.stdout and "mm RMS" in result.stdout
    saved = json.loads((tmp_path / "tip.json").read_text())
    assert saved["name"] == "tip_offset"
    assert np.linalg.norm(np.array(saved["offset"]) - TIP_M) < 2e-4
    assert np.linalg.norm(np.array(saved["pivot_point_m"]) - PIVOT_M) < 2e-4


def test_calibrate_base_flags_an_outlier_and_saves_the_transform(tmp_path):
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, 3] = [0.4, 0.0, 0.1]
    tracker = rng.uniform(-0.2, 0.2, (6, 3))
    base = tracker + T[:3, 3]
    base[4] += [0, 0, 0.003]
    rows = np.hstack([base, tracker]) * 1000  # millimetres
    np.savetxt(
        tmp_path / "pairs.csv",
        rows,
        delimiter=",",
        comments="",
        header="base_x,base_y,base_z,tracker_x,tracker_y,tracker_z",
    )
    out = tmp_path / "T.json"
    result = run("calibrate", "base", tmp_path / "pairs.csv", "--units", "mm", "--out", out)
    assert result.returncode == 0, result.stderr
    assert "5 of 6 point pairs used" in result.stdout
    assert "pair 5 (left out)" in result.stdout
    saved = json.loads(out.read_text())
    np.testing.assert_allclose(saved["matrix"], T, atol=1e-9)
    assert saved["used"] == [True] * 4 + [False, True]


@pytest.mark.parametrize(
    "args, message",
    [
        (lambda d: ["calibrate", "pivot", d / "nope.csv", "--out", d / "t.json"], "does not exist"),
        (
            lambda d: ["calibrate", "pivot", d / "line.csv", "--out", d / "t.json"],
            "needs the pen's orientation",
        ),
        (
            lambda d: [
                "calibrate",
                "pivot",
                d / "line.csv",
                "--rigid-body",
                "pen",
                "--out",
                d / "t.json",
            ],
            "Motive CSV exports only",
        ),
        (
            lambda d: ["calibrate", "base", d / "line.csv", "--out", d / "t.json"],
            "lacks the column",
        ),
        (lambda d: ["calibrate", "base", d / "pairs2.csv", "--out", d / "t.json"], "at least 3"),
        (lambda d: ["calibrate", "base", d / "pairs2.csv", "--out", d / "t.txt"], "end in .json"),
    ],
    ids=["missing", "no-orientation", "rigid-body-on-csv", "not-pairs", "two-pairs", "suffix"],
)
def test_calibrate_bad_input(tmp_path, args, message):
    write_trace_csv(
        tmp_path / "line.csv",
        Recording(points_m=np.outer(np.arange(20), [1e-3, 0, 0]), t_s=np.arange(20) / 240.0),
    )
    (tmp_path / "pairs2.csv").write_text(
        "base_x,base_y,base_z,tracker_x,tracker_y,tracker_z\n0,0,0,0,0,0\n1,0,0,1,0,0\n"
    )
    result = run(*args(tmp_path))
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], result.stderr
    assert not (tmp_path / "t.json").exists()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    scene = scenes.box_corner(0)
    write_scan(folder / "scan.ply", scene.scan)
    return folder, scene


def test_reconstruct_with_tip_calibration_pieces_and_a_stored_scan_pose(scene, tmp_path):
    folder, sc = scene
    rec = sc.recording
    # The rigid body 120 mm above the tip, pen upright; 0.4 s lost in the middle.
    tip = np.array([0.0, 0.0, -0.12])
    t = rec.t_s.copy()
    keep = (t < t[len(t) // 2]) | (t > t[len(t) // 2] + 0.4)
    body = Recording(
        points_m=rec.points_m[keep] - tip,
        t_s=t[keep],
        orientations_xyzw=np.tile([0, 0, 0, 1.0], (int(keep.sum()), 1)),
    )
    write_trace_csv(tmp_path / "body.csv", body)
    write_tip_calibration(tmp_path / "tip.json", tip)
    write_calibration(tmp_path / "Tscan.json", "T_scan_tracker", sc.T_scan_tracker)
    out = tmp_path / "out.csv"
    args = [
        "reconstruct",
        tmp_path / "body.csv",
        "--scan",
        folder / "scan.ply",
        "--tip-calibration",
        tmp_path / "tip.json",
        "--scan-from-tracker",
        tmp_path / "Tscan.json",
        "--no-register",
        "--out",
        out,
    ]
    result = run(*args)
    assert result.returncode == 0, result.stderr
    assert "split" in result.stderr and "choose another with --piece" in result.stderr
    first = np.loadtxt(out, delimiter=",", skiprows=1, usecols=(0, 1, 2))
    # On the tip's path, not the rigid body's 120 mm above it.
    assert abs(np.median(first[:, 2]) - np.median(rec.points_m[:, 2])) < 2e-3
    result = run(*args[:-2], "--piece", "0", "--out", tmp_path / "p0.csv")
    assert result.returncode == 0, result.stderr
    assert "using piece 0" in result.stderr
    result = run(*args[:-2], "--piece", "7", "--out", tmp_path / "p7.csv")
    assert result.returncode == 1 and "piece 7 does not exist" in result.stderr
    for bad in ("-1", "some"):
        result = run(*args[:-2], "--piece", bad, "--out", tmp_path / "bad.csv")
        assert result.returncode == 2 and "piece number" in result.stderr
        assert not (tmp_path / "bad.csv").exists()
    result = run(*args[:-2], "--piece", "all", "--out", tmp_path / "all.csv")
    assert result.returncode == 0, result.stderr
    assert "using all 2 pieces" in result.stderr
    header = (tmp_path / "all.csv").read_text().splitlines()[0].split(",")
    pieces = np.loadtxt(
        tmp_path / "all.csv", delimiter=",", skiprows=1, usecols=header.index("piece")
    )
    assert pieces[0] == 0 and pieces[-1] == 1 and np.all(np.diff(pieces) >= 0)
    wrong = run(
        "reconstruct",
        tmp_path / "body.csv",
        "--scan",
        folder / "scan.ply",
        "--scan-from-tracker",
        tmp_path / "tip.json",
        "--out",
        out,
    )
    assert wrong.returncode == 1 and "T_scan_tracker" in wrong.stderr
    write_tip_calibration(tmp_path / "tip_pen.json", tip, rigid_body="Pen")
    other = run(*args[:5], tmp_path / "tip_pen.json", "--rigid-body", "Stylus", "--out", out)
    assert other.returncode == 1
    assert "tip of rigid body 'Pen', but the trace is of 'Stylus'" in other.stderr


@pytest.mark.timeout(120)
def test_record_from_a_natnet_server(tmp_path):
    from drivers.tracking.natnet_server import NatNetReplayServer
    from tests.drivers.test_natnet import synthetic

    recording = synthetic(1.5)
    out = tmp_path / "rec.csv"
    with NatNetReplayServer(recording, rigid_body="Pen", command_port=0) as server:
        port = str(server.command_port)
        result = run(
            "record",
            "--natnet",
            "127.0.0.1",
            "--command-port",
            port,
            "--rigid-body",
            "Pen",
            "--duration",
            "1.0",
            "--out",
            out,
        )
        assert result.returncode == 0, result.stderr
        assert "dropped 0" in result.stdout
        data = np.loadtxt(out, delimiter=",", skiprows=1)
        assert data.shape[1] == 8 and 355 <= len(data) <= 362  # 1 s of stream at 360 Hz
        bad = run(
            "record",
            "--natnet",
            "127.0.0.1",
            "--command-port",
            port,
            "--rigid-body",
            "Stylus",
            "--duration",
            "1",
            "--out",
            tmp_path / "x.csv",
        )
    assert bad.returncode == 1 and "Stylus" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 2  # the "recording ..." line and the error
    assert not (tmp_path / "x.csv").exists()
    nobody = run(
        "record",
        "--natnet",
        "127.0.0.1",
        "--command-port",
        port,
        "--timeout",
        "1",
        "--rigid-body",
        "Pen",
        "--out",
        tmp_path / "y.csv",
    )
    assert nobody.returncode == 1 and "no NatNet server answered" in nobody.stderr
    assert not (tmp_path / "y.csv").exists()
