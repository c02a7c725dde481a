"""Who sends a body and how big it is are decided before any of it is received."""

from __future__ import annotations

import asyncio
import concurrent.futures
import json

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.guards import BodyLimit, TokenGate
from tests.service.conftest import AUTH, TOKEN, make_settings


class Inner:
    """An application that reads the whole body: it records whether it was called."""

    def __init__(self) -> None:
        self.called = False

    async def __call__(self, scope, receive, send):
        self.called = True
        while (await receive()).get("more_body"):
            pass
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})


def call(app, *, method="POST", headers=(), chunks=(b"{}",)):
    """Run one request through an ASGI app; returns (status, body, chunks received by it)."""
    received = []
    sent = []
    pending = list(chunks)

    async def receive():
        body = pending.pop(0) if pending else b""
        received.append(body)
        return {"type": "http.request", "body": body, "more_body": bool(pending)}

    async def send(message):
        sent.append(message)

    scope = {
        "type": "http",
        "method": method,
        "path": "/sessions",
        "headers": [(k.lower().encode(), v.encode()) for k, v in headers],
    }
    # In a thread of its own: in a process that ran a browser test before, Playwright's sync
    # API leaves an event loop running in the main thread, where asyncio.run() refuses to start.
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        pool.submit(asyncio.run, app(scope, receive, send)).result()
    status = next(m["status"] for m in sent if m["type"] == "http.response.start")
    body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    return status, body, received


@pytest.mark.parametrize(
    ("headers", "message"),
    [
        ((), "missing access token"),
        ((("Authorization", "Bearer wrong"),), "wrong access token"),
        ((("Authorization", "Basic " + TOKEN),), "missing access token"),
        ((("Authorization", "Bearer "),), "missing access token"),
    ],
)
def test_a_body_without_the_token_is_refused_before_a_byte_of_it_is_received(headers, message):
    inner = Inner()
    status, body, received = call(
        TokenGate(inner, lambda: TOKEN), headers=headers, chunks=[b"x" * 65536] * 1500
    )
    assert status == 401 and message in json.loads(body)["message"]
    assert received == [] and not inner.called  # not one chunk of the 98 MB was read


def test_with_the_token_the_body_goes_on_and_reads_need_no_gate():
    inner = Inner()
    status, _, received = call(
        TokenGate(inner, lambda: TOKEN), headers=[("Authorization", f"Bearer {TOKEN}")]
    )
    assert status == 200 and received == [b"{}"]
    # A GET carries no body: the routes' own token check answers it.
    inner = Inner()
    assert call(TokenGate(inner, lambda: TOKEN), method="GET")[0] == 200 and inner.called


def test_before_the_service_has_a_token_nothing_with_a_body_is_accepted():
    status, _body, received = call(TokenGate(Inner(), lambda: None), headers=[])
    assert status == 503 and received == []


def test_json_bodies_are_capped_by_declared_size_and_as_they_arrive():
    inner = Inner()
    limit = BodyLimit(inner, max_bytes=10_000_000, max_json_bytes=1000)
    json_type = ("Content-Type", "application/json")
    status, body, received = call(limit, headers=[json_type, ("Content-Length", "5000")])
    assert status == 413 and "JSON body exceeds" in json.loads(body)["message"]
    assert received == [] and not inner.called
    # No declared length (chunked): refused as the count passes the limit.
    status, _, received = call(limit, headers=[json_type], chunks=[b"x" * 600] * 10)
    assert status == 413 and len(received) == 2
    # Another content type (a multipart upload) has the upload limit.
    status, _, _ = call(limit, headers=[("Content-Length", "5000")], chunks=[b"x" * 5000])
    assert status == 200


def test_the_service_refuses_hostile_json_with_clear_errors(tmp_path):
    with TestClient(create_app(make_settings(tmp_path)), headers=AUTH) as client:
        big = client.post(
            "/sessions",
            content=b"[" * 200_000 + b"]" * 200_000,
            headers={"content-type": "application/json"},
        )
        assert big.status_code == 413 and big.json()["code"] == "upload_too_large"
        deep = client.post(
            "/sessions", content=b"[" * 100_000, headers={"content-type": "application/json"}
        )
        assert deep.status_code == 422 and "nested too deeply" in deep.json()["message"]
        keys = b"{" + b",".join(b'"k%d":1' % i for i in range(20_000)) + b"}"
        many = client.post("/sessions", content=keys, headers={"content-type": "application/json"})
        assert many.status_code == 422
        assert len(many.json()["detail"]) == 20 and "19999 more" in many.json()["message"]
        unauthorized = client.post(
            "/sessions", json={"name": "x"}, headers={"Authorization": "Bearer nope"}
        )
        assert unauthorized.status_code == 401
        assert [s["name"] for s in client.get("/sessions").json()] == []  # nothing was made
