"""GET /health: no token needed."""

from __future__ import annotations

import functools
from importlib import metadata

from fastapi import APIRouter, Depends

from service.api.deps import context
from service.schemas import Health

router = APIRouter(tags=["health"])


@functools.cache
def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


@router.get("/health", response_model=Health)
def health(ctx=Depends(context)) -> dict:
    """Liveness, versions and the robot backends' state."""
    running = ctx.store.count_jobs("running")
    return {
        "status": "ok",
        "version": _version("teachpath"),
        "versions": {
            name: _version(name)
            for name in ("numpy", "scipy", "open3d-cpu", "toppra", "ur-rtde", "fastapi")
        },
        "robot_backends": {
            "sim": "available",
            "ur_rtde": (
                f"configured: {ctx.settings.ur_robot} at {ctx.settings.ur_host}"
                if ctx.settings.ur_host
                else "not configured"
            ),
        },
        "jobs_running": running,
    }
