"""The command line: the reconstruct contract, its bad inputs, and the demo."""

import csv
import re
import subprocess
import sys

import matplotlib.pyplot as plt
import numpy as np
import pytest

from drivers.scanning.pointcloud import write_scan
from drivers.tracking.canonical_csv import write_trace_csv
from recon import scenes
from recon.inputs import Recording, Scan
from service.cli import main


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("inputs")
    scene = scenes.box_corner(0)
    write_trace_csv(folder / "trace.csv", scene.recording)
    write_scan(folder / "scan.ply", scene.scan)
    write_trace_csv(folder / "trace_mm.csv", Recording(points_m=scene.recording.points_m * 1000))
    write_scan(folder / "scan_mm.ply", Scan(points_m=scene.scan.points_m * 1000))
    return folder


def run(*args):
    """Run the real console script, as a user would."""
    return subprocess.run(
        [sys.executable, "-m", "service.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_reconstruct_writes_the_contracted_csv_and_a_plot(inputs, tmp_path):
    out, plot = tmp_path / "out.csv", tmp_path / "out.png"
    result = run(
        "reconstruct",
        inputs / "trace.csv",
        "--scan",
        inputs / "scan.ply",
        "--out",
        out,
        "--plot",
        plot,
    )
    assert result.returncode == 0, result.stderr
    assert "edge" in result.stdout and "registered" in result.stdout
    rows = list(csv.reader(out.open()))
    assert rows[0][:4] == ["x", "y", "z", "t"]
    assert "displacement_m" in rows[0] and "mode" in rows[0] and "alpha" in rows[0]
    assert {r[rows[0].index("mode")] for r in rows[1:]} <= {"edge", "surface", "path"}
    assert plot.read_bytes()[:4] == b"\x89PNG"


def test_options_reach_the_reconstruction(inputs, tmp_path):
    out = tmp_path / "out.csv"
    assert (
        main(
            [
                "reconstruct",
                str(inputs / "trace.csv"),
                "--scan",
                str(inputs / "scan.ply"),
                "--alpha",
                "1",
                "--radius-m",
                "0.01",
                "--degree",
                "3",
                "--method",
                "paper",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = list(csv.DictReader(out.open()))
    assert {r["mode"] for r in rows} == {"path"}  # alpha = 1: the path alone
    assert {r["n_path"] for r in rows} == {"21"}  # r = 10 mm at 1 mm spacing


def test_millimetre_files_with_units_mm_give_the_same_result(inputs, tmp_path):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    assert (
        main(
            [
                "reconstruct",
                str(inputs / "trace.csv"),
                "--scan",
                str(inputs / "scan.ply"),
                "--out",
                str(a),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "reconstruct",
                str(inputs / "trace_mm.csv"),
                "--scan",
                str(inputs / "scan_mm.ply"),
                "--units",
                "mm",
                "--out",
                str(b),
            ]
        )
        == 0
    )
    xa = np.loadtxt(a, delimiter=",", skiprows=1, usecols=(0, 1, 2))
    xb = np.loadtxt(b, delimiter=",", skiprows=1, usecols=(0, 1, 2))
    np.testing.assert_allclose(xa, xb, atol=1e-6)


def test_path_only_without_a_scan(inputs, tmp_path):
    out = tmp_path / "out.csv"
    assert main(["reconstruct", str(inputs / "trace.csv"), "--out", str(out)]) == 0
    assert {r["mode"] for r in csv.DictReader(out.open())} == {"path"}


@pytest.mark.parametrize(
    "make_args, message",
    [
        (lambda d, i: ["reconstruct", d / "missing.csv", "--out", d / "o.csv"], "does not exist"),
        (
            lambda d, i: ["reconstruct", i / "scan.ply", "--out", d / "o.csv"],
            "cannot tell the trace format",
        ),
        (
            lambda d, i: [
                "reconstruct",
                i / "trace.csv",
                "--scan",
                i / "trace.csv",
                "--out",
                d / "o.csv",
            ],
            "scan format",
        ),
        (lambda d, i: ["reconstruct", i / "trace_mm.csv", "--out", d / "o.csv"], "--units mm"),
        (
            lambda d, i: [
                "reconstruct",
                i / "trace.csv",
                "--scan",
                i / "scan_mm.ply",
                "--out",
                d / "o.csv",
            ],
            "millimetres",
        ),
        (lambda d, i: ["reconstruct", d / "nan.csv", "--out", d / "o.csv"], "NaN"),
        (lambda d, i: ["reconstruct", d / "short.csv", "--out", d / "o.csv"], "at least"),
        (
            lambda d, i: [
                "reconstruct",
                i / "trace.csv",
                "--scan",
                d / "far.ply",
                "--out",
                d / "o.csv",
            ],
            "same frame and units",
        ),
        (
            lambda d, i: ["reconstruct", i / "trace.csv", "--alpha", "2", "--out", d / "o.csv"],
            "alpha",
        ),
        (lambda d, i: ["reconstruct", i / "trace.csv", "--out", d / "o.txt"], "should end in .csv"),
        (
            lambda d, i: ["reconstruct", i / "trace.csv", "--out", d / "no" / "o.csv"],
            "does not exist",
        ),
        (lambda d, i: ["reconstruct", i / "trace.csv"], "--out"),
    ],
    ids=[
        "missing",
        "not-csv",
        "scan-not-a-scan",
        "mm-as-m",
        "mixed-units",
        "nan",
        "too-short",
        "far-scan",
        "bad-alpha",
        "bad-suffix",
        "no-folder",
        "no-out",
    ],
)
def test_bad_input_is_one_line_non_zero_and_no_output(inputs, tmp_path, make_args, message):
    (tmp_path / "nan.csv").write_text("x,y,z\n0,0,0\nnan,1,1\n0.01,0,0\n")
    (tmp_path / "short.csv").write_text("x,y,z\n0,0,0\n0.001,0,0\n0.0015,0,0\n")
    write_scan(
        tmp_path / "far.ply", Scan(points_m=np.random.default_rng(0).uniform(5, 6, (500, 3)))
    )
    result = run(*make_args(tmp_path, inputs))
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    import re

    assert re.search(message, lines[0]), lines[0]
    assert not (tmp_path / "o.csv").exists() and not (tmp_path / "o.png").exists()


def test_demo_writes_its_table_and_pictures(tmp_path):
    result = run("demo", "--out-dir", tmp_path / "demo")
    assert result.returncode == 0, result.stderr
    assert "| anchored alpha=auto |" in result.stdout
    for name in (
        "trace.csv",
        "scan.ply",
        "reconstruction.csv",
        "reconstruction.png",
        "accuracy.md",
        "accuracy.png",
    ):
        assert (tmp_path / "demo" / name).stat().st_size > 0


@pytest.fixture(scope="module")
def reconstructed(inputs, tmp_path_factory):
    folder = tmp_path_factory.mktemp("plan")
    out = folder / "recon.csv"
    assert (
        main(
            [
                "reconstruct",
                str(inputs / "trace.csv"),
                "--scan",
                str(inputs / "scan.ply"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    (folder / "T.json").write_text(
        '{"name": "T_base_tracker", "units": "mm", '
        '"matrix": [[1,0,0,350],[0,1,0,-50],[0,0,1,100],[0,0,0,1]]}'
    )
    return folder


def test_plan_then_dry_run(inputs, reconstructed, tmp_path):
    traj = tmp_path / "traj.csv"
    result = run(
        "plan",
        reconstructed / "recon.csv",
        "--scan",
        inputs / "scan.ply",
        "--robot",
        "ur5e",
        "--speed-m-s",
        "0.05",
        "--base-from-tracker",
        reconstructed / "T.json",
        "--out",
        traj,
        "--plot",
        tmp_path / "plan.png",
    )
    assert result.returncode == 0, result.stderr
    assert "tool axis from the scan" in result.stdout and "margins" in result.stdout
    assert "tool checked as a capsule of radius 10.0 mm from the flange to the TCP" in result.stdout
    picture = plt.imread(tmp_path / "plan.png")
    assert picture.shape[:2] == (900, 1000) and picture[..., :3].std() > 0.05
    meta, header = traj.read_text().splitlines()[:2]
    assert meta.startswith("# teachpath: ") and '"robot": "ur5e"' in meta
    assert header == "t,q0,q1,q2,q3,q4,q5,x,y,z,rx,ry,rz,phase"
    result = run("dry-run", traj, "--robot", "ur5e")
    assert result.returncode == 0, result.stderr
    assert "completed" in result.stdout and "off the path" in result.stdout
    result = run("dry-run", traj, "--robot", "ur5e", "--mode", "movepath", "--tolerance-m", "0.001")
    assert result.returncode == 0, result.stderr
    assert "(movepath): completed" in result.stdout
    # Off the path by no more than the waypoints' tolerance (1 mm) plus the servo's corner
    # rounding (measured 0.5 mm on this path's corner).
    off_path_mm = float(re.search(r"([0-9.]+) mm off the path", result.stdout).group(1))
    assert off_path_mm < 2.0


def test_a_tool_given_as_spheres_is_the_tool_checked(inputs, reconstructed, tmp_path):
    """``--tool-spheres-m``: the tool as spheres (a spindle's flat end), the same parameter as
    the API's, and the report says which tool was checked."""
    result = _plan_in_cell(
        inputs,
        reconstructed,
        tmp_path / "traj.csv",
        "--tool-spheres-m=0,0,0.097,0.003,0,0,0.06,0.02",
    )
    assert result.returncode == 0, result.stderr
    assert (
        "tool checked as 2 sphere(s), X, Y, Z, R in the flange frame (mm): "
        "0.0, 0.0, 97.0, 3.0; 0.0, 0.0, 60.0, 20.0" in result.stdout
    ), result.stdout


def test_a_plan_with_the_arms_calibration_says_so_and_records_it(inputs, reconstructed, tmp_path):
    from tests.drivers.test_ur_calibration import conf_text

    conf = tmp_path / "calibration.conf"
    conf.write_text(conf_text())  # a UR10e's
    out = tmp_path / "traj.csv"
    result = _plan_in_cell(inputs, reconstructed, out, "--robot", "ur10e", "--ur-calibration", conf)
    assert result.returncode == 0, result.stderr
    assert "kinematics: ur10e, calibrated kinematics from calibration.conf" in result.stdout
    assert '"calibration": {"delta_theta_rad"' in out.read_text().splitlines()[0]
    result = run("dry-run", out)
    assert result.returncode == 0, result.stderr
    # Another arm's calibration, and a file that is none, are refused before any work.
    refused = _plan_in_cell(inputs, reconstructed, out, "--ur-calibration", conf)
    assert refused.returncode != 0 and "is the robot model right" in refused.stderr
    conf.write_text("[mounting]\ndelta_theta = [0, 0, 0]\n")
    refused = _plan_in_cell(
        inputs, reconstructed, out, "--robot", "ur10e", "--ur-calibration", conf
    )
    assert refused.returncode != 0 and "delta_theta must be six finite numbers" in refused.stderr


def _plan_in_cell(inputs, reconstructed, out, *cell):
    return run(
        "plan",
        reconstructed / "recon.csv",
        "--scan",
        inputs / "scan.ply",
        "--speed-m-s",
        "0.05",
        "--base-from-tracker",
        reconstructed / "T.json",
        *cell,
        "--out",
        out,
    )


@pytest.mark.parametrize(
    "cell, obstacle",
    [
        # A wall at x = 0.42 m: the path runs from x = 0.37 to 0.45 m in the base frame.
        (["--cell-plane=-1,0,0,-0.42"], "cell plane 1"),
        # The same wall behind a harmless one: named by its place on the command line.
        (["--cell-plane=-1,0,0,-1.5", "--cell-plane=-1,0,0,-0.42"], "cell plane 2"),
        # A box around the path's end (0.45, 0.01, 0.10).
        (["--keep-out-box", "0.44,0.0,0.09,0.46,0.02,0.11"], "keep-out box 1"),
    ],
    ids=["wall", "second-wall", "box"],
)
def test_a_plan_through_the_cell_is_refused_naming_the_obstacle(
    inputs, reconstructed, tmp_path, cell, obstacle
):
    out = tmp_path / "traj.csv"
    result = _plan_in_cell(inputs, reconstructed, out, *cell)
    assert result.returncode != 0
    assert "the motion collides" in result.stderr and obstacle in result.stderr, result.stderr
    assert not out.exists()


def test_cell_surfaces_the_motion_keeps_clear_of_are_planned_and_recorded(
    inputs, reconstructed, tmp_path
):
    out = tmp_path / "traj.csv"
    # A wall 1.5 m in front and a box behind the base, both far from the whole motion.
    result = _plan_in_cell(
        inputs,
        reconstructed,
        out,
        # Values that start with a minus go after "=" (argparse reads them as options otherwise).
        "--cell-plane=-1,0,0,-1.5",
        "--keep-out-box=-2,1.2,0,-1,2,1",
    )
    assert result.returncode == 0, result.stderr
    checked = "against: mounting plane, cell plane 1, keep-out box 1, scan ("
    assert checked in result.stdout and "clear: no part comes within" in result.stdout
    assert out.exists()


@pytest.mark.parametrize(
    "cell, message",
    [
        (["--cell-plane", "0,0,0,1"], "non-zero"),
        (["--cell-plane", "1,0,0"], "4 finite numbers"),
        (["--cell-plane", "1,0,0,inf"], "4 finite numbers"),
        (["--keep-out-box", "1,1,1,0,0,0"], "must be >= min_m"),
        (["--keep-out-box", "0,0,0,1,1,nan"], "6 finite numbers"),
    ],
    ids=["zero-normal", "three-numbers", "infinite-offset", "inverted-box", "nan-box"],
)
def test_bad_cell_surfaces_are_refused_before_any_work(
    inputs, reconstructed, tmp_path, cell, message
):
    out = tmp_path / "traj.csv"
    result = _plan_in_cell(inputs, reconstructed, out, *cell)
    assert result.returncode == 2
    assert message in result.stderr, result.stderr
    assert not out.exists()


@pytest.mark.parametrize(
    "make_args, message",
    [
        (
            lambda d, r: ["plan", r / "recon.csv", "--speed-m-s", "0.05", "--out", d / "o.csv"],
            r"waypoint \d+ .* cannot be followed",
        ),  # at the base's origin without a calibration
        (
            lambda d, r: [
                "plan",
                r / "recon.csv",
                "--speed-m-s",
                "9",
                "--base-from-tracker",
                r / "T.json",
                "--out",
                d / "o.csv",
            ],
            "speed_m_s must be",
        ),
        (
            lambda d, r: [
                "plan",
                r / "recon.csv",
                "--robot",
                "kuka",
                "--speed-m-s",
                "0.05",
                "--out",
                d / "o.csv",
            ],
            "unknown robot",
        ),
        (
            lambda d, r: [
                "plan",
                r / "recon.csv",
                "--speed-m-s",
                "0.05",
                "--base-from-tracker",
                r / "recon.csv",
                "--out",
                d / "o.csv",
            ],
            "JSON",
        ),
        (
            lambda d, r: ["plan", r / "T.json", "--speed-m-s", "0.05", "--out", d / "o.csv"],
            "no column x",
        ),
        (lambda d, r: ["dry-run", r / "recon.csv", "--robot", "ur5e"], "does not start with"),
        (lambda d, r: ["dry-run", d / "missing.csv"], "does not exist"),
        (
            lambda d, r: ["dry-run", r / "recon.csv", "--mode", "movepath", "--tolerance-m", "0"],
            "tolerance-m must be positive",
        ),
    ],
    ids=[
        "unreachable",
        "too-fast",
        "unknown-robot",
        "bad-calibration",
        "not-a-recon",
        "not-a-trajectory",
        "missing",
        "zero-tolerance",
    ],
)
def test_plan_and_dry_run_bad_input(reconstructed, tmp_path, make_args, message):
    result = run(*make_args(tmp_path, reconstructed))
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert re.search(message, lines[0]), lines[0]
    assert not (tmp_path / "o.csv").exists()


@pytest.mark.parametrize("placement", ["registered", "given"])
def test_a_scan_given_is_always_in_the_collision_check(inputs, reconstructed, tmp_path, placement):
    """`plan PATH.csv --scan S --orientation fixed` (a CSV without its .npz) checked against the
    mounting plane only: the scan, given, was left out. Now it is placed (registered, or by the
    transform given) and checked, whatever the tool axis comes from."""
    alone = tmp_path / "alone.csv"
    alone.write_bytes((reconstructed / "recon.csv").read_bytes())  # without recon.npz
    extra = []
    if placement == "given":
        (tmp_path / "S.json").write_text(
            '{"name": "T_scan_tracker", "matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}'
        )
        extra = ["--scan-from-tracker", tmp_path / "S.json"]
    result = run(
        "plan", alone, "--scan", inputs / "scan.ply", "--orientation", "fixed",
        "--speed-m-s", "0.05", "--base-from-tracker", reconstructed / "T.json", *extra,
        "--out", tmp_path / "t.csv",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert re.search(r"against: mounting plane, scan \(\d+ points\)", result.stdout), result.stdout
    assert ("registered the path to the scan" in result.stderr) == (placement == "registered")


def test_a_scan_whose_place_is_unknown_is_refused_not_left_out():
    from recon.inputs import Scan
    from service.pipelines import cell_for

    scan = Scan(points_m=np.tile([0.4, 0.0, 0.1], (10, 1)))
    with pytest.raises(ValueError, match="cannot be checked against the workpiece"):
        cell_for(scan, None, None)
    assert cell_for(scan, np.eye(4), None).has_scan
    assert not cell_for(None, None, None).has_scan


def test_a_trajectory_file_with_a_spike_is_refused_by_dry_run_and_export(
    inputs, reconstructed, tmp_path
):
    """A 0.3 rad one-sample spike (about 150 rad/s) passed `dry-run` ("completed") and
    `export-urscript`: the file was trusted. Each consumer checks the samples against the arm's
    limits first and names the sample and the joint."""
    traj = tmp_path / "traj.csv"
    planned = run(
        "plan", reconstructed / "recon.csv", "--scan", inputs / "scan.ply", "--speed-m-s", "0.05",
        "--base-from-tracker", reconstructed / "T.json", "--out", traj,
    )  # fmt: skip
    assert planned.returncode == 0, planned.stderr
    lines = traj.read_text().splitlines()
    row = 2 + 1000  # a sample in the middle (after the metadata and header lines)
    fields = lines[row].split(",")
    fields[3] = repr(float(fields[3]) + 0.3)  # joint 3 (q2) jumps 0.3 rad for one sample
    lines[row] = ",".join(fields)
    spiked = tmp_path / "spiked.csv"
    spiked.write_text("\n".join(lines) + "\n")
    for command in (
        ["dry-run", spiked],
        ["export-urscript", spiked, "--out", tmp_path / "p.script"],
    ):
        result = run(*command)
        assert result.returncode == 1, (command, result.stdout)
        assert "break the ur5e's limits" in result.stderr, result.stderr
        assert "sample 1000" in result.stderr and "joint 3 moves at" in result.stderr
    assert not (tmp_path / "p.script").exists()
    # The file as planned passes both.
    assert run("dry-run", traj).returncode == 0
    assert run("export-urscript", traj, "--out", tmp_path / "ok.script").returncode == 0


def test_each_command_is_built_alone_and_the_same_as_in_the_full_parser():
    """``teachpath CMD`` builds only CMD's options: its help is the full parser's, and
    ``teachpath --help`` lists every command with the same lines."""
    import argparse

    from service.cli import COMMANDS, build_parser

    def commands_of(parser):
        (action,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        return action.choices

    full = build_parser()
    assert build_parser(["--help"]).format_help() == full.format_help()
    for command in COMMANDS:
        alone = commands_of(build_parser([command.NAME, "--help"]))
        assert alone[command.NAME].format_help() == commands_of(full)[command.NAME].format_help()
        others = [name for name in alone if name != command.NAME]
        assert all(not alone[name]._actions[1:] for name in others)  # listed, not built


def test_the_command_list_imports_no_numerical_or_schema_code():
    """``teachpath --help`` stays light: neither SciPy nor the parameter schemas are imported
    (they took about 0.9 s of its 1.1 s before the commands were built one at a time)."""
    probe = (
        "import sys; from service.cli import build_parser; build_parser(['--help']); "
        "print(sorted(m for m in ('scipy', 'pydantic', 'service.schemas') if m in sys.modules))"
    )
    light = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert light.returncode == 0, light.stderr
    assert light.stdout.strip() == "[]"
    full = subprocess.run(
        [sys.executable, "-c", probe.replace("['--help']", "['plan']")],
        capture_output=True,
        text=True,
    )
    assert "service.schemas" in full.stdout  # the command named is built in full
