"""The command line's touches and several demonstrations: `calibrate scan`, `reconstruct
TRACE... --touches`, and their bad inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivers.calibration import read_calibration
from drivers.scanning.pointcloud import write_scan
from drivers.tracking.canonical_csv import write_trace_csv
from recon import scenes
from recon.inputs import Recording
from recon.metrics import score_path
from recon.transforms import apply_transform, invert_transform
from tests.service.test_cli import run

MM = 1e-3


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("touches")
    scene = scenes.box_corner(1)
    write_scan(folder / "scan.ply", scene.scan)
    write_trace_csv(folder / "trace.csv", scene.recording)
    for k, recording in enumerate(scene.traces(2, 1)):
        write_trace_csv(folder / f"trace{k + 2}.csv", recording)
    touches = scenes.touch_recording(scene, 1)
    write_trace_csv(folder / "touches.csv", touches.recording)
    # Touches on the box's top only: sliding in its plane is left free.
    top_only = scenes.touch_recording(scene, 1, n_faces=1, n_touches=4)
    write_trace_csv(folder / "top_only.csv", top_only.recording)
    return folder, scene


def test_calibrate_scan_finds_the_touches_and_writes_a_calibration_the_others_read(files):
    folder, scene = files
    out = folder / "T_scan_tracker.json"
    result = run(
        "calibrate", "scan", folder / "touches.csv", "--scan", folder / "scan.ply",
        "--trace", folder / "trace.csv", "--out", out,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    # What the touches leave at the path, in millimetres (recon.touches.touch_uncertainty).
    assert "6 touches found, 6 used; they place the scan to 0." in result.stdout
    assert "mm (1 sigma, at most) at the traced path, across its features" in result.stdout
    assert "residual per touch (mm):" in result.stdout
    calibration = read_calibration(out, expect="T_scan_tracker")
    saved = json.loads(out.read_text())
    assert saved["fixed_motions"] == 6 and len(saved["touches_m"]) == 6
    assert 0 < saved["uncertainty_m"] < 0.5 * MM
    assert saved["judged"] == "at the traced path, across its features"
    assert saved["source"] == "touches.csv"
    # Against ground truth: the scanner's error at the traced feature.
    error = invert_transform(calibration.matrix) @ scene.T_scan_tracker
    moved = apply_transform(error, scene.truth_m)
    assert score_path(moved, scene.truth_m).max_m < 0.5 * MM

    # The calibration then places the scan for `reconstruct` (nothing registered again).
    csv = folder / "out.csv"
    result = run(
        "reconstruct", folder / "trace.csv", "--scan", folder / "scan.ply",
        "--scan-from-tracker", out, "--no-register", "--out", csv,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    points = np.loadtxt(csv, delimiter=",", skiprows=1, usecols=(0, 1, 2))
    assert score_path(points, scene.truth_m).max_m < 0.6 * MM


def test_touches_on_one_face_are_refused_for_a_path_along_two_edges(files):
    folder, _ = files
    out = folder / "refused.json"
    result = run(
        "calibrate", "scan", folder / "top_only.csv", "--scan", folder / "scan.ply",
        "--trace", folder / "trace.csv", "--out", out,
    )  # fmt: skip
    assert result.returncode == 1
    assert "(1 sigma) at the traced path, across its features, more than the 0.50 mm" in (
        result.stderr
    )
    assert "sliding along (" in result.stderr and " mm (the touches pin it too little" in (
        result.stderr
    )
    assert "touch a face that faces" in result.stderr
    assert not out.exists()
    # Without a trace to judge by, the same rule over the scanned box around the touches, in
    # every direction: refused too, saying where it judged.
    result = run(
        "calibrate", "scan", folder / "top_only.csv", "--scan", folder / "scan.ply",
        "--out", out,
    )  # fmt: skip
    assert result.returncode == 1
    assert "over the scanned workpiece around the touches (no path given" in result.stderr
    assert "give the path these touches are for (--trace PATH_FILE)" in result.stderr
    assert not out.exists()


def test_reconstruct_fuses_demonstrations_and_registers_by_touches(files):
    folder, scene = files
    out = folder / "fused.csv"
    result = run(
        "reconstruct", folder / "trace.csv", folder / "trace2.csv", folder / "trace3.csv",
        "--scan", folder / "scan.ply", "--touches", folder / "touches.csv", "--out", out,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "3 of 3 demonstrations fused" in result.stdout
    assert "traced the other way round and turned" in result.stdout
    assert "scanner registered by touches" in result.stdout
    header = out.read_text().splitlines()[0].split(",")
    column = header.index("uncertainty_m")
    table = np.genfromtxt(out, delimiter=",", skip_header=1, usecols=range(column + 1))
    points, uncertainty = table[:, :3], table[:, column]
    assert np.all(np.isfinite(uncertainty)) and np.all(uncertainty > 0)
    raw = score_path(scene.recording.points_m, scene.truth_m)
    ours = score_path(points, scene.truth_m)
    assert ours.max_m < 0.5 * MM and ours.mean_m < 0.3 * raw.mean_m


@pytest.mark.parametrize(
    "args, message",
    [
        (
            lambda d: ["reconstruct", d / "trace.csv", "--touches", d / "touches.csv",
                       "--out", d / "x.csv"],
            "give the scan too",
        ),
        (
            lambda d: ["calibrate", "scan", d / "still.csv", "--scan", d / "scan.ply",
                       "--out", d / "x.json"],
            "at least 3 are needed",
        ),
        (
            lambda d: ["calibrate", "scan", d / "untimed.csv", "--scan", d / "scan.ply",
                       "--out", d / "x.json"],
            "no sample times",
        ),
        (
            lambda d: ["calibrate", "scan", d / "touches.csv", "--out", d / "x.json"],
            "required: --scan",
        ),
        (
            lambda d: ["reconstruct", d / "trace.csv", d / "elsewhere.csv", "--out",
                       d / "x.csv"],
            "same path",
        ),
    ],
    ids=["touches-without-scan", "too-few-rests", "no-times", "no-scan", "different-paths"],
)  # fmt: skip
def test_bad_touches_and_demonstrations_are_refused_with_what_to_do(files, args, message):
    folder, _ = files
    # Two rests only; a file without times; a trace of somewhere else.
    still = np.repeat([[0.02, 0.02, 0.0], [0.06, 0.02, 0.0]], 120, axis=0)
    write_trace_csv(folder / "still.csv", Recording(points_m=still, t_s=np.arange(240) / 120))
    (folder / "untimed.csv").write_text("x,y,z\n" + "0.02,0.02,0\n" * 50 + "0.05,0.02,0\n")
    line = np.column_stack([np.linspace(0.5, 0.6, 200), np.full(200, 0.5), np.zeros(200)])
    write_trace_csv(folder / "elsewhere.csv", Recording(points_m=line))
    result = run(*args(folder))
    assert result.returncode in (1, 2)
    assert message in result.stderr, result.stderr
    assert not (folder / "x.csv").exists() and not (folder / "x.json").exists()
