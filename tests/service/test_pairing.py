"""A second screen: the safety state and Stop without the token, and pairing by a one-time code."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.pairing import CODE_TTL_S, MAX_WRONG_TRIES, Pairing
from tests.service.conftest import AUTH, TOKEN, make_settings

NO_TOKEN = {"Authorization": ""}


class Clock:
    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


@pytest.fixture
def app_client(tmp_path):
    app = create_app(make_settings(tmp_path / "data"))
    with TestClient(app, headers=AUTH) as client:
        yield app, client


def _error(response, status: int, code: str) -> str:
    assert response.status_code == status, response.text
    body = response.json()
    assert body["code"] == code, body
    return body["message"]


def test_a_code_is_good_once_and_only_within_its_time():
    clock = Clock()
    pairing = Pairing(clock)
    assert not pairing.redeem("123456").ok  # none issued yet
    code = pairing.issue()
    assert len(code) == 6 and code.isdigit()
    assert 0 < pairing.expires_in_s() <= CODE_TTL_S
    assert pairing.redeem(code).ok
    second = pairing.redeem(code)
    assert not second.ok and "used" in second.reason
    code = pairing.issue()
    clock.now_s += CODE_TTL_S
    late = pairing.redeem(code)
    assert not late.ok and "expired" in late.reason
    assert pairing.expires_in_s() == 0.0


def test_wrong_guesses_void_the_code_and_a_new_code_voids_the_old():
    pairing = Pairing(Clock())
    code = pairing.issue()
    wrong = f"{(int(code) + 1) % 10**6:06d}"
    for left in range(MAX_WRONG_TRIES - 1, 0, -1):
        outcome = pairing.redeem(wrong)
        assert not outcome.ok and f"{left} tries left" in outcome.reason
    assert "void" in pairing.redeem(wrong).reason
    assert not pairing.redeem(code).ok  # the right code after five wrong ones: void too
    old = pairing.issue()
    new = pairing.issue()
    if old != new:
        assert not pairing.redeem(old).ok
    assert pairing.redeem(new).ok


def test_a_signed_in_screen_makes_a_code_and_a_screen_without_the_token_pairs_with_it(app_client):
    _, client = app_client
    made = client.post("/pairing/code")
    assert made.status_code == 201, made.text
    code = made.json()["code"]
    assert 0 < made.json()["expires_in_s"] <= CODE_TTL_S
    paired = client.post("/pairing", json={"code": code}, headers=NO_TOKEN)
    assert paired.status_code == 200 and paired.json() == {"token": TOKEN}
    message = _error(
        client.post("/pairing", json={"code": code}, headers=NO_TOKEN), 401, "pairing_failed"
    )
    assert "Pair a screen" in message
    # Making a code needs the token (else any screen could pair itself).
    _error(client.post("/pairing/code", headers=NO_TOKEN), 401, "unauthorized")


@pytest.mark.parametrize(
    "body",
    [
        {"code": "12345"},
        {"code": "1234567"},
        {"code": 123456},
        {"code": "12a456"},
        {"code": "１２３４５６"},  # full-width digits are not ASCII digits
        {"code": "123456", "extra": 1},
        {},
        [],
        "123456",
    ],
)
def test_bad_pairing_bodies_are_422_and_cost_no_try(app_client, body):
    app, client = app_client
    code = app.state.pairing.issue()
    _error(client.post("/pairing", json=body, headers=NO_TOKEN), 422, "invalid_request")
    assert client.post("/pairing", json={"code": code}, headers=NO_TOKEN).status_code == 200


def test_hostile_pairing_bodies_are_refused_before_they_are_read(app_client):
    app, client = app_client
    code = app.state.pairing.issue()
    huge = '{"code": "' + "1" * 100_000 + '"}'
    refused = client.post(
        "/pairing", content=huge, headers={**NO_TOKEN, "Content-Type": "application/json"}
    )
    _error(refused, 413, "upload_too_large")
    deep = "[" * 600 + "]" * 600
    refused = client.post(
        "/pairing", content=deep, headers={**NO_TOKEN, "Content-Type": "application/json"}
    )
    assert refused.status_code in (413, 422), refused.text
    # Another content type without the token is capped as small (not at the upload limit).
    refused = client.post(
        "/pairing", content=b"x" * 5000, headers={**NO_TOKEN, "Content-Type": "text/plain"}
    )
    _error(refused, 413, "upload_too_large")
    assert "KB" in refused.json()["message"]
    assert client.post("/pairing", json={"code": code}, headers=NO_TOKEN).status_code == 200


def test_the_safety_state_and_stop_need_no_token_and_nothing_else_opens(app_client):
    _, client = app_client
    state = client.get("/robot", headers=NO_TOKEN)
    assert state.status_code == 200 and state.json()["backend"] == "sim"
    # Stop is answered (here: no such execution), never 401; without the token only for
    # executions this instance started (no search of the database for made-up ids).
    message = _error(client.post("/executions/exe_nope/stop", headers=NO_TOKEN), 404, "not_found")
    assert "not started by this instance" in message
    assert "not started by this instance" not in _error(
        client.post("/executions/exe_nope/stop"), 404, "not_found"
    )
    # Acting on the arm or the sessions still needs the token.
    _error(client.post("/robot/unlock", headers=NO_TOKEN), 401, "unauthorized")
    _error(client.post("/sessions", json={"name": "x"}, headers=NO_TOKEN), 401, "unauthorized")
    _error(client.get("/sessions", headers=NO_TOKEN), 401, "unauthorized")
    # A path that only looks like the stop's is not open.
    _error(client.post("/executions/a/b/stop", headers=NO_TOKEN), 401, "unauthorized")
    _error(client.post("/pairing/code/x", headers=NO_TOKEN), 401, "unauthorized")


def test_the_code_printed_at_start_signs_a_screen_in_once(tmp_path):
    from tests.server_process import Server

    server = Server(tmp_path / "data", token=None, timeout_s=30)
    try:
        anonymous = {"Authorization": ""}
        paired = server.client.post(
            "/pairing", json={"code": server.pairing_code}, headers=anonymous
        )
        assert paired.status_code == 200 and paired.json()["token"] == server.token
        again = server.client.post(
            "/pairing", json={"code": server.pairing_code}, headers=anonymous
        )
        assert again.status_code == 401 and again.json()["code"] == "pairing_failed"
    finally:
        server.stop()
