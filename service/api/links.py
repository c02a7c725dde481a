"""OpenAPI links: which value of a response a later request takes (a session's id, a job's
result, an artifact's id), for clients and for schemathesis's stateful phase.

Declared here, in one table, by method and path: :func:`add_links` looks up the operationIds
FastAPI generated when the spec is built, and refuses a link whose route or parameter does not
exist (a renamed route fails the spec, not a client later).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

SESSION = "/sessions/{session_id}"
RECORDING = SESSION + "/recordings/{artifact_id}"
SCAN = SESSION + "/scans/{artifact_id}"
RECONSTRUCTION = SESSION + "/reconstructions/{artifact_id}"
TRAJECTORY = SESSION + "/trajectories/{artifact_id}"
EXECUTION = SESSION + "/executions/{artifact_id}"
JOB = "/jobs/{job_id}"
CAPTURE = SESSION + "/captures/{capture_id}"

#: The source request's session id.
REQUEST_SESSION = "$request.path.session_id"


def body(pointer: str) -> str:
    """The runtime expression of a value in the response body (a JSON pointer, no leading /)."""
    return f"$response.body#/{pointer}"


@dataclass(frozen=True)
class Link:
    """A link to the operation ``method path``: its parameters (name -> runtime expression)
    and, for a JSON body, fields set from the response (merged into the generated body)."""

    name: str
    method: str
    path: str
    description: str
    parameters: dict[str, str] = field(default_factory=dict)
    request_body: dict[str, Any] | None = None

    def openapi(self, operation_id: str) -> dict[str, Any]:
        entry: dict[str, Any] = {
            "operationId": operation_id,
            "description": self.description,
            "parameters": dict(self.parameters),
        }
        if self.request_body is not None:
            entry["requestBody"] = self.request_body
        return entry


def _session(session: str, *, including_self: bool = True) -> list[Link]:
    """What a session's id opens: the session, its inputs, its lists, its jobs.

    Not the routes that need another id too (planning, running, replaying: they are linked
    from the artifact whose id they take), nor the calibrations from a file or point pairs a
    response cannot supply.
    """

    def at(name: str, method: str, path: str, description: str) -> Link:
        return Link(name, method, path, description, {"session_id": session})

    links = [
        at("artifacts", "GET", SESSION + "/artifacts", "every artifact of the session"),
        at("set_calibration", "PUT", SESSION + "/calibration", "set its calibrations"),
        at("upload_recording", "PUT", SESSION + "/recording", "upload its recording"),
        at("upload_scan", "PUT", SESSION + "/scan", "upload its scan"),
        at("start_reconstruction", "POST", SESSION + "/reconstructions", "reconstruct"),
        at("recordings", "GET", SESSION + "/recordings", "its recordings"),
        at("scans", "GET", SESSION + "/scans", "its scans"),
        at("reconstructions", "GET", SESSION + "/reconstructions", "its reconstructions"),
        at("trajectories", "GET", SESSION + "/trajectories", "its trajectories"),
        at("executions", "GET", SESSION + "/executions", "its executions"),
        at("jobs", "GET", SESSION + "/jobs", "its jobs"),
    ]
    if including_self:
        links.insert(0, at("get_session", "GET", SESSION, "the session"))
    return links


def _artifact(
    kind: str, path: str, downloads: dict[str, str], session: str, artifact: str
) -> list[Link]:
    """The artifact ``artifact`` of ``kind`` at ``path`` and its downloads (name -> suffix)."""
    parameters = {"session_id": session, "artifact_id": artifact}
    links = [Link(f"get_{kind}", "GET", path, f"the {kind}", parameters)]
    for name, suffix in downloads.items():
        links.append(
            Link(f"{kind}_{name}", "GET", f"{path}/{suffix}", f"the {kind} as {name}", parameters)
        )
    return links


def _recording(session: str, artifact: str) -> list[Link]:
    return _artifact("recording", RECORDING, {"csv": "csv"}, session, artifact)


def _scan(session: str, artifact: str) -> list[Link]:
    return _artifact("scan", SCAN, {"ply": "ply"}, session, artifact)


def _reconstruction(session: str, artifact: str, *, including_self: bool = True) -> list[Link]:
    links = _artifact(
        "reconstruction",
        RECONSTRUCTION,
        {"csv": "csv", "preview": "preview.png"},
        session,
        artifact,
    )
    plan = Link(
        "plan_trajectory",
        "POST",
        SESSION + "/trajectories",
        "plan a trajectory along the reconstruction",
        {"session_id": session},
        {"reconstruction_id": artifact},
    )
    return [*(links if including_self else links[1:]), plan]


def _trajectory(session: str, artifact: str, *, including_self: bool = True) -> list[Link]:
    links = _artifact(
        "trajectory", TRAJECTORY, {"csv": "csv", "urscript": "urscript"}, session, artifact
    )
    run = Link(
        "run_trajectory",
        "POST",
        SESSION + "/executions",
        "dry-run the trajectory",
        {"session_id": session},
        {"trajectory_id": artifact},
    )
    return [*(links if including_self else links[1:]), run]


def _execution(session: str, artifact: str) -> list[Link]:
    return _artifact("execution", EXECUTION, {"csv": "csv"}, session, artifact)


def _job(job: str) -> list[Link]:
    """What a job's id opens."""
    return [
        Link("get_job", "GET", JOB, "the job", {"job_id": job}),
        Link("cancel_job", "POST", JOB + "/cancel", "cancel the job", {"job_id": job}),
        Link("job_events", "GET", JOB + "/events", "the job's events", {"job_id": job}),
    ]


def _capture(session: str, capture: str) -> list[Link]:
    parameters = {"session_id": session, "capture_id": capture}
    return [
        Link("get_capture", "GET", CAPTURE, "the capture", parameters),
        Link("stop_capture", "POST", CAPTURE + "/stop", "stop the capture", parameters),
    ]


def _recorded(session: str, recording: str) -> list[Link]:
    """Uses of a recording's id: the recording, reconstructing it, replaying it."""
    return [
        *_recording(session, recording),
        Link(
            "reconstruct_recording",
            "POST",
            SESSION + "/reconstructions",
            "reconstruct the recording",
            {"session_id": session},
            {"recording_id": recording},
        ),
        Link(
            "replay_recording",
            "POST",
            SESSION + "/captures",
            "capture a replay of the recording",
            {"session_id": session},
            {"source": {"kind": "replay", "recording_id": recording}},
        ),
    ]


def _stop_execution(execution: str) -> Link:
    return Link(
        "stop_execution",
        "POST",
        "/executions/{execution_id}/stop",
        "stop the execution",
        {"execution_id": execution},
    )


def _delete_session(session: str) -> Link:
    return Link("delete_session", "DELETE", SESSION, "delete the session", {"session_id": session})


#: (method, path, status) of a response -> the links from it.
LINKS: dict[tuple[str, str, int], list[Link]] = {
    ("POST", "/sessions", 201): [*_session(body("id")), _delete_session(body("id"))],
    # The oldest session (listed first): a client's, or the fuzzer's, way to an existing one.
    ("GET", "/sessions", 200): [
        *_session(body("0/id")),
        *_recording(body("0/id"), body("0/recording_id")),
        *_scan(body("0/id"), body("0/scan_id")),
    ],
    ("GET", SESSION, 200): [
        *_session(body("id"), including_self=False),
        *_recording(body("id"), body("recording_id")),
        *_scan(body("id"), body("scan_id")),
    ],
    ("PUT", SESSION + "/calibration", 200): [
        Link("get_session", "GET", SESSION, "the session", {"session_id": body("id")})
    ],
    ("PUT", SESSION + "/recording", 201): _recorded(body("session_id"), body("id")),
    ("GET", SESSION + "/recordings", 200): _recorded(REQUEST_SESSION, body("0/id")),
    ("GET", RECORDING, 200): _recorded(body("session_id"), body("id"))[1:],
    ("PUT", SESSION + "/scan", 201): [
        *_scan(body("session_id"), body("id")),
        Link(
            "reconstruct_scan",
            "POST",
            SESSION + "/reconstructions",
            "reconstruct the session's recording with the scan",
            {"session_id": body("session_id")},
            {"scan_id": body("id")},
        ),
    ],
    ("GET", SESSION + "/scans", 200): _scan(REQUEST_SESSION, body("0/id")),
    ("POST", SESSION + "/reconstructions", 202): _job(body("id")),
    ("GET", SESSION + "/reconstructions", 200): _reconstruction(REQUEST_SESSION, body("0/id")),
    ("GET", RECONSTRUCTION, 200): _reconstruction(
        body("session_id"), body("id"), including_self=False
    ),
    ("POST", SESSION + "/trajectories", 202): _job(body("id")),
    ("GET", SESSION + "/trajectories", 200): _trajectory(REQUEST_SESSION, body("0/id")),
    ("GET", TRAJECTORY, 200): _trajectory(body("session_id"), body("id"), including_self=False),
    ("POST", SESSION + "/executions", 202): [
        *_job(body("id")),
        _stop_execution(body("params/execution_id")),
    ],
    ("GET", SESSION + "/executions", 200): _execution(REQUEST_SESSION, body("0/id")),
    ("GET", SESSION + "/jobs", 200): _job(body("0/id")),
    # A finished job's result names what it made; the links of another kind's job resolve to
    # nothing (the client, or the fuzzer, has no id to follow).
    ("GET", JOB, 200): [
        *_reconstruction(body("session_id"), body("result/reconstruction_id")),
        *_trajectory(body("session_id"), body("result/trajectory_id")),
        *_execution(body("session_id"), body("result/execution_id")),
        _stop_execution(body("params/execution_id")),
    ],
    # An imported session: its lists lead to its imported plans and dry runs (never runnable on
    # the arm as they came, see service/gate.py).
    ("POST", "/sessions/import", 201): _session(body("session/id")),
    ("POST", "/sessions/import", 200): _session(body("session/id")),
    ("POST", SESSION + "/captures", 201): _capture(body("session_id"), body("id")),
    ("GET", CAPTURE, 200): [
        *_capture(body("session_id"), body("id"))[1:],
        *_recording(body("session_id"), body("recording_id")),
    ],
    ("POST", CAPTURE + "/stop", 200): _recording(body("session_id"), body("recording_id")),
}


def add_links(spec: dict[str, Any]) -> dict[str, Any]:
    """``spec`` (FastAPI's OpenAPI document) with :data:`LINKS` on its responses."""
    paths = spec["paths"]

    def operation(method: str, path: str) -> dict[str, Any]:
        try:
            found: dict[str, Any] = paths[path][method.lower()]
        except KeyError:
            raise ValueError(
                f"OpenAPI link to or from a missing operation {method} {path}"
            ) from None
        return found

    for (method, path, status), links in LINKS.items():
        response = operation(method, path)["responses"].get(str(status))
        if response is None:
            raise ValueError(f"OpenAPI links from {method} {path}: no {status} response")
        entries = response.setdefault("links", {})
        for link in links:
            target = operation(link.method, link.path)
            names = {p["name"] for p in target.get("parameters", []) if p.get("in") == "path"}
            missing = set(link.parameters) - names
            if missing:
                raise ValueError(
                    f"OpenAPI link {link.name} from {method} {path}: {link.method} {link.path} "
                    f"has no path parameter {', '.join(sorted(missing))}"
                )
            if link.name in entries:
                raise ValueError(f"two OpenAPI links named {link.name} from {method} {path}")
            entries[link.name] = link.openapi(target["operationId"])
    return spec
