"""Event streams hold no threads: 64 open ``/robot/events`` streams (each held a worker thread
before, and at 45 of them a read took 1.4 s) leave ordinary requests and the Stop answered, and
one more stream is refused (429) instead of piling up."""

from __future__ import annotations

import threading
import time

import httpx
import pytest

from service.api.robot import MAX_ANONYMOUS_STREAMS, MAX_EVENT_STREAMS
from tests.server_process import Server

pytestmark = pytest.mark.timeout(300)

TOKEN = "streams-token-abcdefghijklmnop"


def _listen(
    url: str, started: threading.Semaphore, stop: threading.Event, errors: list, token=TOKEN
) -> None:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    try:
        with (
            httpx.Client(base_url=url, timeout=30.0, headers=headers) as client,
            client.stream("GET", "/robot/events") as response,
        ):
            if response.status_code != 200:
                errors.append(response.status_code)
                started.release()
                return
            first = True
            for line in response.iter_lines():
                if first and line.startswith("data:"):
                    started.release()
                    first = False
                if stop.is_set():
                    return
    except httpx.HTTPError as error:
        errors.append(type(error).__name__)


def _open_streams(server, count: int, token, shared, threads: list) -> None:
    """Open ``count`` streams (with ``token``, or none), each in a thread appended to
    ``threads``, and wait until every one has had its first event."""
    started, stop, errors = shared
    for _ in range(count):
        thread = threading.Thread(
            target=_listen, args=(server.url, started, stop, errors, token), daemon=True
        )
        thread.start()
        threads.append(thread)
    for _ in range(count):
        assert started.acquire(timeout=60), "a stream got no first event"
    assert errors == []


def test_many_open_event_streams_leave_requests_answered_and_the_next_is_refused(tmp_path):
    server = Server(tmp_path / "data", token=TOKEN)
    stop = threading.Event()
    started = threading.Semaphore(0)
    errors: list = []
    threads: list = []
    try:
        _open_streams(server, MAX_EVENT_STREAMS, TOKEN, (started, stop, errors), threads)
        # Every stream is open and served: ordinary requests are answered.
        before = time.monotonic()
        for _ in range(5):
            assert server.client.get("/sessions").status_code == 200
            assert server.client.get("/robot").status_code == 200
        latency_s = (time.monotonic() - before) / 10
        print(f"\n{MAX_EVENT_STREAMS} streams open: a request answered in {latency_s * 1e3:.0f} ms")
        assert latency_s < 1.0
        # Stopping an execution that does not exist is answered (404) at once, as any stop is.
        assert server.client.post("/executions/exe_000000000000/stop").status_code == 404
        # Streams beyond the cap, up to 200 asked for in all, are refused, not queued; the
        # Stop route is answered after them as before.
        for _ in range(200 - MAX_EVENT_STREAMS):
            refused = server.client.get("/robot/events")
            assert refused.status_code == 429 and refused.json()["code"] == "too_many_streams"
        assert server.client.post("/executions/exe_000000000000/stop").status_code == 404
        assert server.client.get("/robot").status_code == 200
    finally:
        stop.set()
        server.stop()
        for thread in threads:
            thread.join(timeout=10)


def test_screens_without_the_token_cannot_take_the_signed_in_pendants_streams(tmp_path):
    """The safety state streams to any screen, signed in or not; but the screens that are not
    cannot hold more than 16 streams, so the pendants' slots stay free."""
    server = Server(tmp_path / "data", token=TOKEN)
    stop = threading.Event()
    started = threading.Semaphore(0)
    errors: list = []
    threads: list = []
    try:
        _open_streams(server, MAX_ANONYMOUS_STREAMS, None, (started, stop, errors), threads)
        anonymous = httpx.get(f"{server.url}/robot/events", timeout=10)
        assert anonymous.status_code == 429 and "without the token" in anonymous.json()["message"]
        signed_in = threading.Thread(
            target=_listen, args=(server.url, started, stop, errors), daemon=True
        )
        signed_in.start()
        threads.append(signed_in)
        assert started.acquire(timeout=60) and errors == []
    finally:
        stop.set()
        server.stop()
        for thread in threads:
            thread.join(timeout=10)
