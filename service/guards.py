"""ASGI guards that act on a request before its body is read: who sends it, and how big it is.

FastAPI reads and parses a request's body before it runs the route's dependencies, on the event
loop, so a check in a dependency comes too late: an unauthenticated client could make the server
receive and parse a 100 MB JSON document (delaying a Stop by seconds) before it is told it has no
access. These guards sit in front of the application:

* :class:`TokenGate` refuses every request that can carry a body (anything but GET, HEAD and
  OPTIONS) without the right ``Authorization: Bearer`` token with 401, from its headers alone;
  nothing of the body is received. (GET routes keep the token dependency.) The few paths that
  need no token (Stop, pairing) may send at most :data:`OPEN_BODY_BYTES`.
* :class:`BodyLimit` refuses bodies above a size with 413: a JSON body above
  ``max_json_bytes`` (no JSON document the API takes comes near it), any other body above the
  upload limit; a declared Content-Length at once, a chunked body as it arrives.
"""

from __future__ import annotations

import hmac
import json
import re
from collections.abc import Callable, Iterable

from starlette.types import ASGIApp, Message, Receive, Scope, Send

#: The largest body a request without the token may send (bytes).
OPEN_BODY_BYTES = 1024
#: Methods that never carry a body the application reads.
BODILESS = frozenset({"GET", "HEAD", "OPTIONS"})


async def _answer(send: Send, status: int, code: str, message: str) -> None:
    body = json.dumps({"code": code, "message": message, "detail": None}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    if status == 401:
        headers.append((b"www-authenticate", b"Bearer"))
    # The body is not read: ask the client to close, so that it stops sending.
    headers.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


class TokenGate:
    """401 for a request that can carry a body and lacks the token, before any of it is read.

    Parameters
    ----------
    app : ASGI application
    token : callable returning str or None
        The expected token (read per request: the services hold it once started; None before).
    open_paths : tuple of str
        Regular expressions of paths that need no token (matched whole).
    """

    def __init__(
        self, app: ASGIApp, token: Callable[[], str | None], open_paths: tuple[str, ...] = ()
    ) -> None:
        self.app, self.token = app, token
        self.open_paths = re.compile("|".join(f"(?:{p})" for p in open_paths) or "(?!)")
        # What needs no token takes no more than a pairing code: nobody without the token can
        # make the server receive a large body.
        self.open_limited = BodyLimit(app, OPEN_BODY_BYTES, OPEN_BODY_BYTES)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("method", "GET") in BODILESS:
            return await self.app(scope, receive, send)
        if self.open_paths.fullmatch(scope.get("path", "")):
            return await self.open_limited(scope, receive, send)
        expected = self.token()
        given = _bearer(scope)
        if expected is None:
            # Not started yet (no token to compare against): nothing is accepted.
            return await _answer(send, 503, "starting", "the service is starting: retry")
        if given is None:
            return await _answer(
                send,
                401,
                "unauthorized",
                "missing access token: send 'Authorization: Bearer TOKEN' (the token is printed "
                "at start-up)",
            )
        if not hmac.compare_digest(given.encode(), expected.encode()):
            return await _answer(send, 401, "unauthorized", "wrong access token")
        return await self.app(scope, receive, send)


def _bearer(scope: Scope) -> str | None:
    headers: Iterable[tuple[bytes, bytes]] = scope.get("headers") or ()  # ASGI: name, value
    for name, value in headers:
        if name == b"authorization":
            scheme, _, credentials = value.decode("latin-1").partition(" ")
            if scheme.lower() == "bearer" and credentials.strip():
                return credentials.strip()
            return None
    return None


class BodyLimit:
    """413 for a body above its limit, before it is read into memory.

    A JSON body (``Content-Type: application/json``) may hold ``max_json_bytes``, any other
    (the multipart uploads) ``max_bytes``. A declared Content-Length above the limit is refused
    at once; a chunked body is counted as it arrives.
    """

    def __init__(self, app: ASGIApp, max_bytes: int, max_json_bytes: int) -> None:
        self.app, self.max_bytes, self.max_json_bytes = app, max_bytes, max_json_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers: dict[bytes, bytes] = dict(scope.get("headers") or [])
        content_type = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
        is_json = content_type == b"application/json" or content_type.endswith(b"+json")
        limit = self.max_json_bytes if is_json else self.max_bytes
        declared = headers.get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            return await self._refuse(send, limit, is_json)
        received, refused = 0, False

        async def counted() -> Message:
            # Past the limit the 413 goes out at once and the application is told the client
            # left (its own answer to that is dropped): a framework that turns any error while
            # reading a body into its own 400 never hides the refusal.
            nonlocal received, refused
            if refused:
                return {"type": "http.disconnect"}
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    refused = True
                    await self._refuse(send, limit, is_json)
                    return {"type": "http.disconnect"}
            return message

        async def unless_refused(message: Message) -> None:
            if not refused:
                await send(message)

        try:
            await self.app(scope, counted, unless_refused)
        except Exception:
            if not refused:
                raise

    @staticmethod
    async def _refuse(send: Send, limit: int, is_json: bool) -> None:
        if is_json:
            message = (
                f"the JSON body exceeds {limit // 1024} KB: no request of this API needs that "
                "much (files go as multipart uploads)"
            )
        elif limit < 1024 * 1024:
            message = f"the request body exceeds {limit // 1024} KB"
        else:
            message = f"the request body exceeds {limit // (1024 * 1024)} MB"
        await _answer(send, 413, "upload_too_large", message)
