"""The service guide's REST walk-through (docs/guides/service.md) runs as pasted: bash at a
repository root (``.venv`` there), ``teachpath serve`` with its generated token in
``teachpath_data/token``, real files from ``teachpath demo``, ids chained with jq, a wait loop
for the jobs, ``curl --fail-with-body``."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.server_process import Server

REPO = Path(__file__).resolve().parents[2]


def walk_through() -> str:
    """The shell block under "The whole job over REST" in the service guide."""
    text = (REPO / "docs" / "guides" / "service.md").read_text()
    start = text.index("The whole job over REST")
    block = re.search(r"```sh\n(.*?)```", text[start:], re.S)
    assert block, "the service guide's REST walk-through has no ```sh block"
    return block.group(1)


def test_the_rest_walk_through_runs_as_pasted(tmp_path):
    for tool in ("bash", "curl", "jq"):
        if shutil.which(tool) is None:
            pytest.fail(f"{tool} is missing: run scripts/setup.sh (make setup), which installs it")
    root = tmp_path / "checkout"
    root.mkdir()
    (root / ".venv").symlink_to(REPO / ".venv")
    server = Server(root / "teachpath_data", token=None)
    try:
        assert (root / "teachpath_data" / "token").read_text().strip() == server.token
        run = subprocess.run(
            ["bash", "-e", "-o", "pipefail", "-c", walk_through()],
            cwd=root,
            env={**os.environ, "U": server.url},
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
        # The feasibility report, then the dry run's verdict.
        assert re.search(r"^ur5e: \d+ mm of path in [\d.]+ s", run.stdout, re.M), run.stdout
        assert '"completed": true' in run.stdout and '"faults": []' in run.stdout, run.stdout
        sessions = server.client.get("/sessions").json()
        assert [s["name"] for s in sessions] == ["door"]
        executions = server.client.get(f"/sessions/{sessions[0]['id']}/executions").json()
        assert len(executions) == 1 and executions[0]["params"]["dry_run"] is True
    finally:
        server.stop()
