"""The README's worked example ("From the demonstration to the arm, safely") runs as written:
its commands, in a fresh folder, make the files it names and print what it shows."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[2] / "README.md"


def _example_commands() -> list[list[str]]:
    text = README.read_text()
    section = text[text.index("## From the demonstration to the arm, safely") :]
    block = re.search(r"```sh\n(.*?)```", section, re.S).group(1)
    commands = []
    for line in block.replace("\\\n", " ").splitlines():
        words = shlex.split(line)
        if not words:
            continue
        if words == ["make", "demo"]:  # what `make demo` runs, without the set-up
            words = ["teachpath", "demo", "--out-dir", "demo_out"]
        assert words[0].endswith("teachpath"), line
        commands.append([sys.executable, "-m", "service.cli", *words[1:]])
    return commands


@pytest.mark.timeout(300)
def test_the_worked_example_runs_as_written(tmp_path):
    commands = _example_commands()
    assert len(commands) == 4
    outputs = []
    for command in commands:
        result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=240)
        assert result.returncode == 0, (command, result.stderr)
        outputs.append(result.stdout)
    for name in (
        "trace.csv",
        "scan.ply",
        "reconstruction.csv",
        "reconstruction.npz",
        "T_base_tracker.json",
        "traj.csv",
        "plan.png",
        "program.script",
    ):
        assert (tmp_path / "demo_out" / name).is_file(), name
    plan, dry_run, export = outputs[1:]
    # What the README quotes of the outputs (the numbers are this machine's, the words hold).
    assert "tool axis from the scan" in plan and "elbow up" in plan
    assert "phases: transit" in plan and "clear: no part comes within" in plan
    assert "completed" in dry_run and "mean TCP speed along the path" in dry_run
    assert "wrote demo_out/program.script" in export and "servoj" in export
    program = (tmp_path / "demo_out" / "program.script").read_text()
    assert "set_tcp(p[0.000000, 0.000000, 0.100000" in program and "movej(" in program
