"""Schemathesis fuzzes the running server from its OpenAPI spec: no request may cause a 5xx."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.e2e.test_server_flow import TOKEN, Server

#: Time budget of the fuzzing run (the full suite should stay within minutes).
BUDGET_S = 60


def test_no_server_errors(tmp_path):
    server = Server(tmp_path / "data")
    try:
        session = server.client.post("/sessions", json={"name": "fuzz"}).json()["id"]
        config = tmp_path / "schemathesis.toml"
        # Real ids, so the routes below /sessions/{session_id} are reached and not just 404ed.
        config.write_text(f'[parameters]\n"path.session_id" = "{session}"\n')
        st = Path(sys.executable).parent / "schemathesis"
        result = subprocess.run(
            [
                str(st),
                "--config-file",
                str(config),
                "run",
                f"{server.url}/openapi.json",
                "-H",
                f"Authorization: Bearer {TOKEN}",
                "--checks",
                "not_a_server_error",
                "--max-time",
                str(BUDGET_S),
                "--seed",
                "1",
            ],
            capture_output=True,
            text=True,
            timeout=BUDGET_S + 120,
        )
        assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
        assert "passed" in result.stdout
    finally:
        server.stop()
