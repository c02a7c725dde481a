"""GET /health: no token needed."""

from __future__ import annotations

import functools
import shutil
from importlib import metadata
from typing import Any

from fastapi import APIRouter

from service.api.deps import ServicesDep
from service.errors import STORAGE_FAULT_WINDOW_S, storage_fault
from service.schemas import Health

router = APIRouter(prefix="/health", tags=["health"])


@functools.cache
def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


#: Less free space than this in the data folder is a full disk (an upload or a record would
#: not fit).
MIN_FREE_BYTES = 64 << 20


@router.get("", response_model=Health)
def health(services: ServicesDep) -> dict[str, Any]:
    """Liveness, versions and the robot backends' state. ``degraded`` while the worker pool is
    being replaced after a worker died (jobs queue and run once it is back), while the data
    folder's disk is (nearly) full, and for 30 s after a request met a full disk or a busy
    database (``problems`` names which)."""
    settings = services.settings
    problems = ["worker_pool_replaced"] if services.jobs.degraded else []
    problems += services.store.faults.within(STORAGE_FAULT_WINDOW_S)
    try:
        if shutil.disk_usage(services.store.data_dir).free < MIN_FREE_BYTES:
            problems.append("storage_full")
    except OSError:
        problems.append("storage_full")
    try:
        running = services.store.count_jobs("running")
    except Exception as error:
        fault = storage_fault(error)
        problems.append(fault[0] if fault else "database_unreadable")
        running = None
    problems = sorted(set(problems))
    return {
        "status": "degraded" if problems else "ok",
        "problems": problems,
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
        "jobs_running": running,
    }
