"""GET /health: no token needed."""

from __future__ import annotations

import functools
from importlib import metadata

from fastapi import APIRouter

from service.api.deps import ServicesDep
from service.schemas import Health

router = APIRouter(prefix="/health", tags=["health"])


@functools.cache
def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


@router.get("", response_model=Health)
def health(services: ServicesDep) -> dict:
    """Liveness, versions and the robot backends' state. ``degraded`` while the worker pool is
    being replaced after a worker died (jobs queue and run once it is back)."""
    settings = services.settings
    return {
        "status": "degraded" if services.jobs.degraded else "ok",
        "version": _version("teachpath"),
        "versions": {
            name: _version(name)
            for name in ("numpy", "scipy", "open3d-cpu", "toppra", "ur-rtde", "fastapi")
        },
        "robot_backends": {
            "sim": "available",
            "ur_rtde": (
                f"configured: {settings.ur_robot} at {settings.ur_host}"
                if settings.ur_host
                else "not configured"
            ),
        },
        "jobs_running": services.store.count_jobs("running"),
    }
