"""Bodies the framework cannot read (not UTF-8, nested too deeply, a number too long, a broken
multipart) are 422 invalid_request like any other malformed request, not an undocumented 400.

Schemathesis found the first: ``POST /sessions`` with random bytes as its JSON body.
"""

from __future__ import annotations

import base64

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from tests.service.conftest import AUTH, make_settings

JSON = {"Content-Type": "application/json"}


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    app = create_app(make_settings(tmp_path_factory.mktemp("data")))
    with TestClient(app, headers=AUTH) as test_client:
        yield test_client


def _refused(response, words: str) -> None:
    assert response.status_code == 422, response.text
    body = response.json()
    assert body["code"] == "invalid_request"
    assert words in body["message"]
    assert set(body) == {"code", "message", "detail"}


def test_the_request_schemathesis_found(client):
    before = client.get("/sessions").json()
    body = base64.b64decode("DBJges+ZREIiIDmX723M")
    _refused(client.post("/sessions", content=body, headers=JSON), "not valid UTF-8")
    assert client.get("/sessions").json() == before


def test_bodies_that_are_not_utf8_json_on_every_json_route(client):
    sid = client.post("/sessions", json={"name": "bodies"}).json()["id"]
    for method, path in (
        ("PUT", f"/sessions/{sid}/calibration"),
        ("POST", f"/sessions/{sid}/calibration/base"),
        ("POST", f"/sessions/{sid}/captures"),
        ("POST", f"/sessions/{sid}/trajectories"),
    ):
        response = client.request(method, path, content=b"\xad\xa0\xa9", headers=JSON)
        _refused(response, "not valid UTF-8")


@pytest.mark.parametrize(
    "body, words",
    [
        (b"[" * 50_000 + b"]" * 50_000, "nested too deeply"),
        (b'{"name": ' + b"9" * 5000 + b"}", "not valid JSON: Exceeds the limit"),
    ],
    ids=["deep", "huge-integer"],
)
def test_json_the_parser_gives_up_on(client, body, words):
    response = client.post("/sessions", content=body, headers=JSON)
    _refused(response, words)
    assert "set_int_max_str_digits" not in response.json()["message"]


def test_a_multipart_body_without_its_boundary(client):
    sid = client.post("/sessions", json={"name": "multipart"}).json()["id"]
    response = client.put(
        f"/sessions/{sid}/recording",
        content=b"garbage",
        headers={"Content-Type": "multipart/form-data"},
    )
    _refused(response, "could not be read")
