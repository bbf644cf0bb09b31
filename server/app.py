"""The console's ASGI application, built by :func:`create_app` from typed :class:`Settings`.

Lifespan (start-up, in order): one Zenoh session listening on the hub endpoint (campaign
processes connect to it; ``settings.connect`` reaches a robot's bridge), liveliness presence, the
safety journal (server.safety_journal, fed by the live state's sampler), the live fan-out and its
broadcaster task, the viser 3D view (its own thread and port), the campaign manager — which first
recovers archives a crash left unfinished (per-file errors are logged and shown on the records,
they never stop start-up). Shutdown reverses it; the session is closed
last so no Zenoh callback outlives its objects.

Before all that, :func:`create_app` takes the data directory (:class:`server.datadir.DataDirLock`:
one console per directory) and raises :class:`server.datadir.DataDirError` — one line, which
``xneck server`` prints — when it cannot. :class:`server.guard.ConsoleGuard` wraps the app: Host,
Origin, token and body limits are checked before any route reads anything.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles

from bridge import bus_credentials, bus_tls, small_file
from bridge.archive import software_version, storage_reason
from bridge.session import access_summary, free_tcp_port, open_session
from server import (
    routes_camera,
    routes_campaigns,
    routes_live,
    routes_params,
    routes_system,
    routes_truths,
    routes_workspace,
)
from server.bridge_transitions import BridgeTransitions
from server.camera_feed import CameraFeed
from server.campaigns import CampaignManager, NotFound, StorageError
from server.console import include_console_routes
from server.datadir import DataDirError, DataDirLock
from server.guard import ConsoleGuard, document_responses
from server.live import (
    CHOSEN_CAMPAIGN,
    CHOSEN_STACK,
    Broadcaster,
    LiveBus,
    bridge_estop,
    bus_campaign,
    bus_settled,
    receiver_checks,
)
from server.paramsets import MAX_UPLOAD_BYTES, ParameterStore
from server.presence import Presence
from server.process_faults import ProcessFaults
from server.quality import TWIN_CAMERA
from server.routes_jog import jog_status, request_jog, stop_jog
from server.routes_studies import router as studies_router
from server.safety_journal import SafetyJournal
from server.settings import Settings, resolve_token
from server.workspace_maps import WorkspaceCache

log = logging.getLogger("xneck.server")

WEB_DIR = Path(__file__).resolve().parent.parent / "web"


def concrete_hub(endpoint: str) -> str:
    """``tcp/127.0.0.1:0`` -> a free port now: child processes need a port they can connect to."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if port == "0":
        return f"{proto}/{host}:{free_tcp_port(host)}"
    return endpoint


def create_app(settings: Settings | None = None) -> FastAPI:
    """The console on ``settings.data_dir``, which it owns from now until its lifespan ends.
    Raises :class:`DataDirError` (one line) if the directory is another server's or unusable."""
    settings = settings or Settings()  # pyright: ignore[reportCallIssue] - pydantic-settings fills the fields from XNECK_*
    data_dir = Path(settings.data_dir)
    lock = DataDirLock(data_dir)
    try:
        token, generated = resolve_token(settings)
        params = ParameterStore(data_dir)
        workspace = WorkspaceCache(data_dir / "workspace", grid_3x=settings.workspace_grid)
        (data_dir / "campaigns").mkdir(exist_ok=True)
    except OSError as exc:
        lock.release()
        raise DataDirError(f"cannot use the data directory {data_dir}: {storage_reason(exc)}") from None

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state = app.state
        state.started = time.monotonic()
        state.hub = concrete_hub(settings.hub)
        session = open_session(listen=[state.hub], connect=list(settings.connect))
        creds, tls = bus_credentials.from_env(), bus_tls.from_env()
        state.bus_access = access_summary([state.hub], list(settings.connect), creds, tls)
        # Zenoh reads them once, at start: a file replaced since (a user revoked) is not in force here
        state.bus_files = small_file.stamps(([creds.path] if creds else []) + ([tls.ca, tls.cert, tls.key] if tls else []))
        state.session = session
        state.scene = None
        tasks: list[asyncio.Task] = []
        try:
            state.presence = Presence(session)
            # every e-stop this console sends (routes_system) and every transition of a bridge's
            # state it sees (the live state's sampler): user audit of session 42
            state.journal = SafetyJournal(data_dir)
            state.process_faults = ProcessFaults()  # what xneck up reported, for the header (health)
            state.transitions = BridgeTransitions(state.journal.record)
            state.live = LiveBus(session)
            state.live.on_state = state.transitions.observe
            state.camera = CameraFeed(session)
            state.broadcaster = Broadcaster(state.live.values, settings.live_rate_hz)
            tasks.append(asyncio.create_task(state.broadcaster.run(), name="live-broadcaster"))
            active, state.default_params = state.params.load_active()
            state.live.values.checks = receiver_checks(state.default_params.n_cables, state.default_params.n_joints)
            state.camera.n_joints = state.default_params.n_joints
            if state.params.fallback is not None:
                # A set that no longer loads must not keep the console (and its e-stop) down.
                named, reason = state.params.fallback
                log.error("active parameter set %r does not load, the console uses %s instead: %s",
                          named, active, reason)
            if settings.viser:
                from server.scene import NeckScene

                state.scene = NeckScene(state.live.values, state.default_params, host=settings.host,
                                        port=settings.viser_port, rate_hz=settings.scene_rate_hz,
                                        jog=lambda alpha_deg: request_jog(state, alpha_deg), hold=lambda: stop_jog(state),
                                        token=lambda: app.state.token,  # the panel jogs as POST /api/jog: with the token
                                        jog_state=lambda: jog_status(state))
            state.campaigns = CampaignManager(data_dir, session, state.hub,
                                              service_alive=lambda: state.presence.any_alive("campaign-service"),
                                              min_free_bytes=int(settings.min_free_mb * 1e6),
                                              bridge_estop=lambda: bridge_estop(state.live.values),
                                              bus_campaign=lambda: bus_campaign(state.live),
                                              bus_heard=lambda: bus_settled(state.live))
            # The live α_IP is one camera's (server.live): the one the running campaign records, else
            # the stack's own (`xneck up`'s camera process, or its twin's white noise), else the first seen.
            # The dashboard says which camera it is and why (server.live.CHOSEN).
            own_camera = settings.twin_camera or (TWIN_CAMERA if settings.twin_alpha_ip == "noise" else "")

            def prefer_camera() -> tuple[str, str]:
                recorded = state.campaigns.recorded_camera()
                return (recorded, CHOSEN_CAMPAIGN) if recorded else (own_camera, CHOSEN_STACK)

            state.live.values.prefer_camera = prefer_camera
            recovered = state.campaigns.recover_all()
            if recovered:
                log.warning("recovered interrupted campaigns: %s", ", ".join(recovered))
            for name, reason in state.campaigns.recovery_errors.items():
                log.error("recovery left %s as it is: %s", name, reason)
            yield
        finally:
            for task in tasks:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
            idle = True
            if getattr(state, "campaigns", None) is not None:
                idle = await asyncio.to_thread(state.campaigns.close)
            if state.scene is not None:
                state.scene.close()
            for name in ("live", "camera", "presence", "journal"):  # the journal after the state's sampler
                obj = getattr(state, name, None)
                if obj is not None:
                    obj.close()
            session.close()
            if idle:
                lock.release()
            else:  # the worker may still write the archive: the folder stays this process's until it ends
                log.warning("a campaign's worker is still stopping: the data directory stays locked until it ends")
                state.campaigns.when_idle(lock.release)

    app = FastAPI(
        title="xneck experiment console",
        version=software_version(),
        description="Campaigns, parameter sets, live data and archives of the X-joint cable-driven neck. "
                    "SI units (angles in rad) unless a field name says otherwise. Mutating endpoints need "
                    "`Authorization: Bearer <token>`.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.token = token
    app.state.token_generated = generated
    app.state.params = params
    app.state.workspace = workspace
    app.state.data_dir_lock = lock

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        # Same shape as FastAPI's, minus the echoed input (it may be a whole uploaded file).
        detail = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", ""), "type": e.get("type", "")}
                  for e in exc.errors()]
        return JSONResponse(status_code=422, content={"detail": detail})

    @app.exception_handler(NotFound)
    async def _not_found(request: Request, exc: NotFound) -> JSONResponse:
        # A campaign deleted between a route's own lookup and a later one (stop, results, a set
        # saved from it): gone, a 404 as at the first lookup, not a 500 (audit of 2026-11-27).
        return JSONResponse(status_code=404, content={"detail": f"no campaign {exc.args[0] if exc.args else ''!r}"})

    @app.exception_handler(StorageError)
    async def _storage(request: Request, exc: StorageError) -> JSONResponse:
        return JSONResponse(status_code=507, content={"detail": str(exc)})

    @app.exception_handler(OSError)
    async def _storage_fault(request: Request, exc: OSError) -> JSONResponse:
        # A full, read-only or failing disk under any route: the client gets the reason, not a 500.
        log.error("%s %s: storage fault: %s", request.method, request.url.path, storage_reason(exc))
        return JSONResponse(status_code=507, content={"detail": f"storage fault: {storage_reason(exc)}"})

    include_console_routes(app)  # before /api/campaigns/{id}: the console's own paths
    for router in (routes_campaigns.router, routes_params.router, routes_system.router, routes_live.router,
                   routes_workspace.router, routes_camera.router, routes_truths.router):
        document_responses(router.routes)
        app.include_router(router)
    app.include_router(studies_router)  # /api/studies (issue 19)
    if WEB_DIR.is_dir():
        app.mount("/", StaticFiles(directory=WEB_DIR, html=True), name="web")
    app.add_middleware(ConsoleGuard, bind_host=settings.host, token=lambda: app.state.token,
                       max_body_bytes=MAX_UPLOAD_BYTES, allowed_hosts=settings.allowed_hosts,
                       allowed_origins=settings.allowed_origins)
    return app
