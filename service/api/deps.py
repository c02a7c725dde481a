"""Dependencies shared by the routers: the services bundle, the access token, a session id."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.core import Services
from service.errors import ApiError

_bearer = HTTPBearer(auto_error=False, description="the access token printed at start-up")


async def services(request: Request) -> Services:
    """The app's :class:`~service.core.Services` (built in the lifespan)."""
    services: Services = request.app.state.services
    return services


async def require_token(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Every route but /health needs ``Authorization: Bearer TOKEN``.

    Async, like :func:`services`: a sync dependency would send every request through the
    thread pool just to compare a string.
    """
    if credentials is None:
        raise ApiError(
            401,
            "unauthorized",
            "missing access token: send "
            "'Authorization: Bearer TOKEN' (the token is printed at start-up)",
        )
    expected = request.app.state.services.token
    if not hmac.compare_digest(credentials.credentials.encode(), expected.encode()):
        raise ApiError(401, "unauthorized", "wrong access token")


def has_token(request: Request) -> bool:
    """Whether a request to a route that needs no token carries the right one anyway."""
    scheme, _, given = request.headers.get("authorization", "").partition(" ")
    expected = request.app.state.services.token
    return scheme.lower() == "bearer" and hmac.compare_digest(
        given.strip().encode(), expected.encode()
    )


#: The services bundle, for a route's signature.
ServicesDep = Annotated[Services, Depends(services)]
