"""Schemathesis against the running server, from its OpenAPI spec.

Two runs on one server; in both no request may cause a 5xx, and every status code and content
type must be one the spec documents for the operation:

- the stateless phases (examples, coverage, fuzzing), with a real session id set through a
  config file, so the routes below /sessions/{session_id} are reached and not just 404ed;
- the stateful phase, which follows the spec's links (service/api/links.py): ids from responses
  (a session created, the session listed first, a job's result, an artifact listed) go into the
  next requests. The first session is seeded with a recording, a scan, a reconstruction, a
  trajectory and a dry run, so the chains reach real artifacts and finished jobs.

The server's arm is the fake UR controller, so executions the fuzzer asks for on the arm reach
the real-arm gate and the runner; and a session made elsewhere is imported as a bundle (with its
plan and its passed dry run) before the runs, so the chains reach imported plans too. Whatever
the runs did, no imported plan ever ran on the arm.
"""

from __future__ import annotations

import collections
import json
import re
import subprocess
import sys
from pathlib import Path

from fastapi.testclient import TestClient

from service.api.links import LINKS
from service.app import create_app
from tests.drivers import fake_ur_fixture
from tests.e2e.test_server_flow import TOKEN
from tests.server_process import Server
from tests.service.conftest import AUTH, T_BASE_TRACKER, make_settings, planned_session

fake_ur_process = fake_ur_fixture.fake_ur_process
fake_ur = fake_ur_fixture.fake_ur

#: Time budgets of the two runs (the whole test stays within about a minute and a half; the
#: stateful run covered 56 links of 108 in 60 s, 25 are required).
STATELESS_BUDGET_S = 30
STATEFUL_BUDGET_S = 45

#: status_code_conformance and content_type_conformance hold for this API; the schema checks
#: are left to the unit tests (response models are FastAPI's own).
CHECKS = "not_a_server_error,status_code_conformance,content_type_conformance"

#: Links the stateful run must follow at least (it followed 56 of the 108 in 60 s, on a machine
#: busy with other work).
MIN_LINKS_COVERED = 25

#: The stateful run uses the spec's links only: schemathesis would otherwise infer hundreds
#: more from field names (any `id` into any `{..._id}`), and the budget would go to those.
STATEFUL_CONFIG = "[phases.stateful.inference]\nalgorithms = []\n"

#: The stateful run starts real reconstructions and plans on the seeded session, and an upload
#: is parsed by the same worker after every job queued before it: with a backlog it can take
#: longer than schemathesis's default 10 s. Slow is not wrong here; 60 s still catches a hang.
#: The stateless run gets the same bound: with the whole suite and other work sharing the two
#: cores, one 404 answer took over 10 s once (`make test`, 2026-12-02).
STATEFUL_REQUEST_TIMEOUT_S = 60


def _schemathesis(
    server: Server, config: Path, phases: str, budget_s: int, report: Path, *extra: str
):
    st = Path(sys.executable).parent / "schemathesis"
    return subprocess.run(
        [
            str(st),
            "--config-file",
            str(config),
            "run",
            f"{server.url}/openapi.json",
            "-H",
            f"Authorization: Bearer {TOKEN}",
            "--checks",
            CHECKS,
            "--phases",
            phases,
            "--max-time",
            str(budget_s),
            "--seed",
            "1",
            "--report",
            "ndjson",
            "--report-ndjson-path",
            str(report),
            *extra,
        ],
        capture_output=True,
        text=True,
        timeout=budget_s + 180,
    )


def _seed(server: Server, scene_files) -> str:
    """A session with one artifact of every kind and finished jobs."""
    client = server.client
    sid = client.post("/sessions", json={"name": "seed"}).json()["id"]
    for route, name, content in (
        ("recording", "trace.csv", scene_files["trace"]),
        ("scan", "scan.ply", scene_files["scan"]),
    ):
        response = client.put(f"/sessions/{sid}/{route}", files={"file": (name, content)})
        assert response.status_code == 201, response.text
    client.put(f"/sessions/{sid}/calibration", json={"T_base_tracker": T_BASE_TRACKER})
    job = server.wait(client.post(f"/sessions/{sid}/reconstructions", json={}).json())
    assert job["state"] == "succeeded", job
    job = server.wait(
        client.post(
            f"/sessions/{sid}/trajectories",
            json={"reconstruction_id": job["result"]["reconstruction_id"], "speed_m_s": 0.05},
        ).json()
    )
    assert job["state"] == "succeeded", job
    trajectory = job["result"]["trajectory_id"]
    job = server.wait(
        client.post(f"/sessions/{sid}/executions", json={"trajectory_id": trajectory}).json()
    )
    assert job["state"] == "succeeded", job
    return sid


def _bundle_from_elsewhere(folder: Path, scene_files) -> tuple[bytes, str]:
    """A session planned and dry-run in another data folder, as a bundle; its id."""
    with TestClient(create_app(make_settings(folder)), headers=AUTH) as client:
        sid, trajectories = planned_session(client, scene_files, [0.05], name="from elsewhere")
        dry = client.post(f"/sessions/{sid}/executions", json={"trajectory_id": trajectories[0.05]})
        assert dry.status_code == 202, dry.text
        return client.get(f"/sessions/{sid}/bundle").content, sid


def _followed_links(report: Path) -> dict[str, collections.Counter]:
    """Link -> the statuses of the requests the stateful run made by following it."""
    followed: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for line in report.read_text().splitlines():
        event = json.loads(line)
        recorder = (event.get("ScenarioFinished") or {}).get("recorder") or {}
        for case_id, case in (recorder.get("cases") or {}).items():
            transition = case.get("transition")
            if not (transition and case.get("is_transition_applied")):
                continue
            response = (recorder.get("interactions", {}).get(case_id) or {}).get("response")
            followed[transition["id"]][(response or {}).get("status_code")] += 1
    return followed


def _output(result) -> str:
    return result.stdout[-6000:] + result.stderr[-2000:]


def test_no_server_errors_and_documented_responses(tmp_path, scene_files, fake_ur_process, fake_ur):
    bundle, imported = _bundle_from_elsewhere(tmp_path / "elsewhere", scene_files)
    server = Server(
        tmp_path / "data",
        token=TOKEN,
        settings={
            "TEACHPATH_UR_HOST": fake_ur_process.host,
            "TEACHPATH_UR_ROBOT": "ur5e",
            "TEACHPATH_UR_WATCHDOG_HZ": str(fake_ur_fixture.SERVICE_WATCHDOG_HZ),
            "TEACHPATH_UR_STALE_AFTER_S": str(fake_ur_fixture.SERVICE_STALE_AFTER_S),
        },
    )
    try:
        # The fuzzer sends no valid bundle: the import is made here, first, so that the
        # imported session (made earlier, elsewhere) is the one `GET /sessions` lists first and
        # its link's `0/id` leads the chains to the imported plan and dry run.
        response = server.client.post(
            "/sessions/import", files={"file": ("elsewhere.zip", bundle, "application/zip")}
        )
        assert response.status_code == 201, response.text
        from_bundle = {
            e["id"] for e in server.client.get(f"/sessions/{imported}/executions").json()
        }
        # Before any fuzzing (which may dry-run it here): the imported plan is not runnable.
        plan = server.client.get(f"/sessions/{imported}/trajectories").json()[0]["id"]
        refused = server.client.post(
            f"/sessions/{imported}/executions",
            json={"trajectory_id": plan, "backend": "ur_rtde", "confirm": True},
        )
        assert refused.status_code == 409 and refused.json()["code"] == "dry_run_required"
        _seed(server, scene_files)
        assert server.client.get("/sessions").json()[0]["id"] == imported
        fuzz = server.client.post("/sessions", json={"name": "fuzz"}).json()["id"]

        config = tmp_path / "stateless.toml"
        # Real ids, so the routes below /sessions/{session_id} are reached and not just 404ed.
        config.write_text(f'[parameters]\n"path.session_id" = "{fuzz}"\n')
        report = tmp_path / "stateless.ndjson"
        result = _schemathesis(
            server,
            config,
            "examples,coverage,fuzzing",
            STATELESS_BUDGET_S,
            report,
            "--request-timeout",
            str(STATEFUL_REQUEST_TIMEOUT_S),
        )
        assert result.returncode == 0, _output(result)
        assert "passed" in result.stdout

        # No fixed session id here: it would override the ids the links carry.
        config = tmp_path / "stateful.toml"
        config.write_text(STATEFUL_CONFIG)
        report = tmp_path / "stateful.ndjson"
        result = _schemathesis(
            server,
            config,
            "stateful",
            STATEFUL_BUDGET_S,
            report,
            "--request-timeout",
            str(STATEFUL_REQUEST_TIMEOUT_S),
        )
        assert result.returncode == 0, _output(result)
        links = re.search(
            r"API Links:\s+(\d+) covered / (\d+) selected / (\d+) total", result.stdout
        )
        scenarios = re.search(r"Scenarios:\s+(\d+)", result.stdout)
        assert links and scenarios, _output(result)
        covered, selected, total = map(int, links.groups())
        declared = sum(len(entries) for entries in LINKS.values())
        # Every declared link was loaded (none refused as invalid) and none was inferred.
        assert selected == total == declared, _output(result)
        assert covered >= MIN_LINKS_COVERED, _output(result)
        assert int(scenarios.group(1)) > 0

        # The links carried real ids: the seeded artifacts were found by them, not only 404s.
        followed = _followed_links(report)
        found = {
            link
            for link, statuses in followed.items()
            if any(status and 200 <= status < 300 for status in statuses)
            and "{artifact_id}" in link.rsplit(" -> ", 1)[-1]
        }
        assert found, (dict(followed), _output(result))
        # A run on the arm is legitimate only after a dry run made here (the fuzzer may make
        # one): never on the bundle's own dry run.
        executions = server.client.get(f"/sessions/{imported}/executions").json()
        made_here = [
            e
            for e in executions
            if e["id"] not in from_bundle
            and e["summary"]["backend"] == "sim"
            and e["summary"]["completed"]
        ]
        for execution in executions:
            if execution["summary"]["backend"] == "sim":
                continue
            assert any(
                dry["inputs"]["trajectory_id"] == execution["inputs"]["trajectory_id"]
                and dry["summary"]["mode"] == execution["summary"]["mode"]
                and dry["created_at"] < execution["created_at"]
                for dry in made_here
            ), (execution, executions)
        # Shown with `pytest -s`: what the stateful run reached.
        print(f"stateful: {scenarios.group(1)} scenarios, links {covered}/{declared} covered")
        for link in sorted(followed):
            print(f"  {dict(followed[link])} {link}")
    finally:
        server.stop()
