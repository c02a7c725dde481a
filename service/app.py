"""The FastAPI application: ``create_app(settings)`` and its lifespan."""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib import metadata
from typing import Any

from fastapi import Depends, FastAPI
from fastapi.middleware.cors import CORSMiddleware

from service import captures as capture_workflow
from service import errors
from service import executions as execution_workflow
from service.api import (
    captures,
    executions,
    health,
    jobs,
    pairing,
    reconstructions,
    recordings,
    robot,
    scans,
    sessions,
    trajectories,
    ui,
)
from service.api.deps import require_token
from service.api.links import add_links
from service.core import Services
from service.demo import create_demo_session
from service.guards import BodyLimit, TokenGate
from service.jobs import JobManager
from service.pairing import Pairing
from service.robot import RobotWatch
from service.schemas import ErrorBody
from service.settings import Settings
from service.store import HEARTBEAT_S, Store

log = logging.getLogger("teachpath.service")

#: Requests with a body that need no token (TokenGate): stopping an execution and pairing.
TOKEN_FREE_POSTS = (r"/executions/[^/]+/stop", r"/pairing")


def _recover(services: Services) -> None:
    """After a restart: fail jobs that were running, keep what captures received and what real-arm
    executions journalled. With other instances on the same database, only what stopped
    instances left (a live one's jobs, captures and files in progress are its own)."""
    store = services.store
    failed = store.fail_interrupted_jobs()
    if failed:
        log.warning("marked %d interrupted job(s) failed", failed)
    others = store.live_instances() - {store.instance_id}
    if others:
        # Their jobs' outputs are written before their artifacts are recorded: an unnamed file
        # may be one of theirs in progress.
        log.warning(
            "%d other instance(s) use this database (%s): unnamed files are left in place",
            len(others),
            ", ".join(sorted(others)),
        )
    else:
        removed = store.remove_unnamed_files()
        if removed:
            names = ", ".join(removed)
            log.warning("removed %d file(s) no artifact names: %s", len(removed), names)
    capture_workflow.recover(services)
    execution_workflow.recover(services)


class Heartbeat:
    """This instance's heartbeat in the database, every ``HEARTBEAT_S``; with each beat, the jobs
    of instances that stopped meanwhile are failed (a client waiting on one learns it)."""

    def __init__(self, store: Store) -> None:
        self.store = store
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="heartbeat", daemon=True)

    def start(self) -> None:
        self.store.heartbeat()
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            try:
                self.store.heartbeat()
                failed = self.store.fail_interrupted_jobs(unowned=False)
                if failed:
                    log.warning("marked %d job(s) of a stopped instance failed", failed)
                self.store.forget_stopped_instances()
            except Exception:  # a database that is briefly away: beat again next time
                log.exception("heartbeat failed")

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10)
        try:
            self.store.leave()
        except Exception:
            log.exception("could not remove this instance's row")


def create_app(settings: Settings | None = None) -> FastAPI:
    """The service for ``settings`` (default: from the environment, TEACHPATH_*)."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        store = Store(settings.data_dir, settings.db_url)
        heartbeat = Heartbeat(store)
        heartbeat.start()  # before recovery: this instance is live, its own rows are not stale
        services = Services(
            settings=settings,
            store=store,
            jobs=JobManager(store, settings.cpu_workers, warm=settings.warm_workers),
            token=settings.access_token(),
            robot=RobotWatch(settings),
        )
        services.robot.start()
        _recover(services)
        if settings.demo:
            create_demo_session(store)
        app.state.services = services
        try:
            yield
        finally:
            # The arm and the captures stop first; this instance stays live until they have,
            # so that no other instance takes its executions for interrupted meanwhile.
            try:
                services.close()
            finally:
                heartbeat.stop()

    try:
        version = metadata.version("teachpath")
    except metadata.PackageNotFoundError:
        version = "0"
    app = FastAPI(
        title="teachpath",
        version=version,
        description="Robot programming by demonstration: reconstruct a hand-traced path with a "
        "scan of the workpiece, plan it for a Universal Robots arm, dry-run and execute it. "
        "Every route needs `Authorization: Bearer TOKEN` but /health, the arm's state (GET /robot, "
        "/robot/events), Stop (POST /executions/{id}/stop) and POST /pairing.",
        lifespan=lifespan,
        # Served by service.api.ui from local copies of the libraries (no CDN).
        docs_url=None,
        redoc_url=None,
    )
    errors.install(app)
    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["*"],
            allow_headers=["Authorization", "Content-Type"],
        )
    # Multipart framing adds a little to the file itself.
    app.add_middleware(
        BodyLimit,
        max_bytes=int(settings.max_upload_mb * 1024 * 1024) + 65536,
        max_json_bytes=int(settings.max_json_kb * 1024),
    )
    # Outermost: who sends a body is known before any of it is received (service/guards.py).
    app.add_middleware(
        TokenGate,
        token=lambda: getattr(getattr(app.state, "services", None), "token", None),
        open_paths=TOKEN_FREE_POSTS,
    )
    # One code at a time for a second screen (printed by `teachpath serve`).
    app.state.pairing = Pairing()

    # Without the token: liveness, the arm's state and Stop (any screen by the cell shows the
    # safety state and can stop the arm, as anyone may press an emergency stop), and pairing.
    app.include_router(health.router)
    app.include_router(robot.router)
    app.include_router(executions.stop_router)
    app.include_router(pairing.router)
    protected = [Depends(require_token)]
    documented: dict[int | str, dict[str, Any]] = {
        status: {"model": ErrorBody} for status in (401, 404, 409, 413, 422, 503)
    }
    for router in (
        robot.unlock_router,
        robot.cell_router,
        sessions.router,
        recordings.router,
        scans.router,
        reconstructions.router,
        trajectories.router,
        executions.router,
        executions.control_router,
        jobs.router,
        jobs.session_router,
        captures.router,
    ):
        app.include_router(router, dependencies=protected, responses=documented)

    def openapi() -> dict[str, Any]:
        """FastAPI's spec with the links between operations (service/api/links.py)."""
        if app.openapi_schema is None:
            spec = FastAPI.openapi(app)  # caches it in app.openapi_schema
            try:
                add_links(spec)
            except ValueError:
                app.openapi_schema = None  # not served without its links
                raise
            return spec
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented way to extend it

    ui.install(app, settings.guide_dir)

    return app
