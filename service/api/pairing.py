"""Pairing a second screen: a one-time code for the access token (``service.pairing``)."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import APIRouter, Depends, Request

from service.api.deps import require_token
from service.errors import ApiError
from service.schemas import ErrorBody, PairingCodeOut, PairingIn, PairingOut

log = logging.getLogger("teachpath.pairing")

#: No token needed: the code is what a screen without one has.
router = APIRouter(prefix="/pairing", tags=["pairing"])


@router.post("", response_model=PairingOut, responses={401: {"model": ErrorBody}})
async def pair(body: PairingIn, request: Request) -> dict[str, Any]:
    """Give the pairing code, get the access token. The code works once, for 10 minutes and
    for 5 wrong tries; then ask for a new one ("Pair a screen" on a signed-in pendant)."""
    outcome = request.app.state.pairing.redeem(body.code)
    if not outcome.ok:
        raise ApiError(
            401,
            "pairing_failed",
            f"{outcome.reason}: on a signed-in pendant press “Pair a screen” for a new code "
            "(or sign in with the access token)",
        )
    log.warning("a screen was paired with the pairing code")
    return {"token": request.app.state.services.token}


@router.post(
    "/code",
    status_code=201,
    response_model=PairingCodeOut,
    dependencies=[Depends(require_token)],
    responses={401: {"model": ErrorBody}},
)
async def new_pairing_code(request: Request) -> dict[str, Any]:
    """A new pairing code for another screen (a signed-in screen asks; the old code is void).
    The server's log shows it too."""
    pairing = request.app.state.pairing
    code = pairing.issue()
    log.warning("pairing code for another screen: %s", code)
    return {"code": code, "expires_in_s": pairing.expires_in_s()}
