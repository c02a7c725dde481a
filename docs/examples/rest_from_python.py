"""Drive the service's REST API from Python: one session from the files to a passed dry run.

Start the service first (``make run``), then, from the repository root::

    .venv/bin/teachpath demo --out-dir demo_files      # a trace, a scan and a calibration
    .venv/bin/python docs/examples/rest_from_python.py

It reads the access token from ``teachpath_data/token`` (what ``make run`` uses) unless
``TEACHPATH_TOKEN`` is set, and the address from ``TEACHPATH_URL`` (default
http://127.0.0.1:8000). Every request that computes answers 202 with a job at once; the job is
followed until it ends. An error answer carries a ``code`` and a message that says what to do.
"""

import json
import os
import time
from pathlib import Path

import httpx

URL = os.environ.get("TEACHPATH_URL", "http://127.0.0.1:8000")
TOKEN = os.environ.get("TEACHPATH_TOKEN") or Path("teachpath_data/token").read_text().strip()
FILES = Path(os.environ.get("TEACHPATH_DEMO_FILES", "demo_files"))

api = httpx.Client(base_url=URL, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60)


def ok(response: httpx.Response) -> dict:
    """The answer's body, or the service's own explanation of why not."""
    if response.is_error:
        body = response.json()
        raise SystemExit(f"{response.status_code} {body['code']}: {body['message']}")
    return response.json()


def finished(job: dict) -> dict:
    """Follow a job until it ends; its result."""
    while job["state"] not in ("succeeded", "failed", "cancelled"):
        time.sleep(0.5)
        job = ok(api.get(f"/jobs/{job['id']}"))
    if job["state"] != "succeeded":
        raise SystemExit(f"job {job['id']} {job['state']}: {job['error']}")
    return job["result"]


session = ok(api.post("/sessions", json={"name": "from python"}))["id"]
with open(FILES / "trace.csv", "rb") as trace:
    ok(api.put(f"/sessions/{session}/recording", files={"file": trace}))
with open(FILES / "scan.ply", "rb") as scan:
    ok(api.put(f"/sessions/{session}/scan", files={"file": scan}))
T_base_tracker = json.loads((FILES / "T_base_tracker.json").read_text())["matrix"]
ok(api.put(f"/sessions/{session}/calibration", json={"T_base_tracker": T_base_tracker}))

job = ok(api.post(f"/sessions/{session}/reconstructions", json={"radius_m": 0.008}))
reconstruction = finished(job)["reconstruction_id"]
job = ok(
    api.post(
        f"/sessions/{session}/trajectories",
        json={"reconstruction_id": reconstruction, "robot": "ur5e", "speed_m_s": 0.05},
    )
)
trajectory = finished(job)["trajectory_id"]
plan = ok(api.get(f"/sessions/{session}/trajectories/{trajectory}"))
print("\n".join(plan["summary"]["report"][:3]))

job = ok(api.post(f"/sessions/{session}/executions", json={"trajectory_id": trajectory}))
execution = finished(job)["execution_id"]
summary = ok(api.get(f"/sessions/{session}/executions/{execution}"))["summary"]
print(
    f"dry run: completed {summary['completed']}, faults {summary['faults']}, "
    f"{summary['max_path_deviation_m'] * 1000:.3f} mm off the path at most"
)
