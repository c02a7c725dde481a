"""Dependencies shared by the routers: the app context and the access token."""

from __future__ import annotations

import hmac

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.context import AppContext
from service.errors import ApiError

_bearer = HTTPBearer(auto_error=False, description="the access token printed at start-up")


async def context(request: Request) -> AppContext:
    return request.app.state.ctx


async def require_token(
    request: Request,
    credentials: HTTPAuthorizationCredentials | None = Depends(_bearer),
) -> None:
    """Every route but /health needs ``Authorization: Bearer TOKEN``.

    Async, like :func:`context`: a sync dependency would send every request through the
    thread pool just to compare a string.
    """
    if credentials is None:
        raise ApiError(
            401,
            "unauthorized",
            "missing access token: send "
            "'Authorization: Bearer TOKEN' (the token is printed at start-up)",
        )
    expected = request.app.state.ctx.token
    if not hmac.compare_digest(credentials.credentials.encode(), expected.encode()):
        raise ApiError(401, "unauthorized", "wrong access token")
