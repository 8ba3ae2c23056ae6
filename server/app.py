"""The application factory: ``create_app(settings)`` wires store, executors, routes and ops.

Everything per-app lives on ``app.state`` (built here, from the settings given); nothing
is read from the environment except by ``app_from_env``, the worker-process entry point.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from collections import Counter
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from typing import Any

import anyio
from fastapi import FastAPI, Request, Response
from starlette.middleware.cors import CORSMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from facecast import __version__

from .channels.hub import ChannelHub
from .channels.routes import router as channel_router
from .compute.blending import BlendBatcher
from .connection.registry import SessionRegistry
from .daemon_pool import DaemonPool
from .errors import LogOnce, install_error_handlers, problem
from .guards.auth import authorize_request
from .guards.origins import OriginGuard
from .heap import serve_frames
from .http.characters import router as character_router
from .http.performers import profile_store
from .http.performers import router as performer_router
from .http.rigs import router as rest_router
from .http.transfer import router as transfer_router
from .metrics import CONTENT_TYPE_LATEST, Metrics
from .pages.api_docs import mount_docs
from .pages.landing import mount_landing
from .pages.perform import mount_perform
from .pages.viewer import mount_viewer
from .serving.seam import TransportSeam
from .settings import Settings
from .storage.rig_store import RigStore
from .stream.route import router as stream_router

__all__ = [
    "SESSIONS_STATE_KEY",
    "SETTINGS_ENV",
    "STOPPING_STATE_KEY",
    "abandoned_work",
    "app_from_env",
    "create_app",
]

log = logging.getLogger("facecast.server")

#: Key of the session registry in the ASGI lifespan state (read by ``runner``).
SESSIONS_STATE_KEY = "facecast_sessions"
#: Key of the app's ``stopping`` event in the lifespan state: ``runner`` sets it when a
#: shutdown begins, and requests still reading a body or waiting for a fit answer 503.
STOPPING_STATE_KEY = "facecast_stopping"
#: How long a stopping server waits for a running transfer job to record its end.
TRANSFER_STOP_SECONDS = 0.5
#: Environment variable carrying serialised settings to worker processes.
SETTINGS_ENV = "FACECAST_SETTINGS_JSON"


def create_app(settings: Settings) -> FastAPI:
    """A new, independent application serving ``settings``.

    Raises ``SettingsError`` for settings the server must not run with (public address
    without tokens), so every way of starting the app refuses them.
    """
    settings.check_startable()
    # glibc's malloc set for frames; uploads set theirs while they run (heap.py).
    serve_frames()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[dict[str, Any]]:
        await anyio.to_thread.run_sync(app.state.store.open)
        app.state.clone_executor = ThreadPoolExecutor(
            settings.clone_threads, thread_name_prefix="facecast-clone"
        )
        # Uploads' parses and fits: daemon threads, which a stopping process abandons
        # rather than waits for (``daemon_pool``).
        app.state.fit_executor = DaemonPool(settings.fit_threads, "facecast-fit")
        # ... and small ones (``small_upload_bytes``) in a lane of their own.
        app.state.small_fit_executor = DaemonPool(1, "facecast-fit-small")
        # Deformation transfer jobs (minutes of scipy for big meshes): their own thread, so
        # they never hold up fits; one at a time (the slot in ``storage.jobs``).
        app.state.transfer_executor = DaemonPool(1, "facecast-transfer")
        app.state.transfer_cancel = threading.Event()
        # One per app, so frames of all its stream sessions on one rig blend together.
        app.state.blend_batcher = BlendBatcher(
            app.state.clone_executor,
            concurrency=settings.clone_threads,
            stages=app.state.metrics.stages if settings.stage_timing else None,
        )
        await app.state.channels.start(app.state.clone_executor)
        log.info(
            "server ready",
            extra={
                "event": "server.start",
                "pid": os.getpid(),
                "rigs_dir": str(settings.rigs_dir),
                "auth": settings.auth_enabled,
            },
        )
        try:
            yield {SESSIONS_STATE_KEY: app.state.sessions, STOPPING_STATE_KEY: app.state.stopping}
        finally:
            # Normally the runner has already closed sessions with 1001; this catches
            # servers stopped any other way.
            await app.state.sessions.close_all(1001, "server shutting down", timeout=1.0)
            await app.state.channels.close()
            app.state.clone_executor.shutdown(wait=False, cancel_futures=True)
            app.state.fit_executor.shutdown(wait=False, cancel_futures=True)
            app.state.small_fit_executor.shutdown(wait=False, cancel_futures=True)
            app.state.transfer_cancel.set()  # a running transfer stops after its expression
            app.state.transfer_executor.shutdown(wait=False, cancel_futures=True)
            # A job checks the event between expressions and stages: given a moment, it
            # records its end ("interrupted") itself; past it, it is abandoned (its record
            # reads so anyway: the slot is free) and the store closes under it.
            await anyio.to_thread.run_sync(app.state.transfer_executor.idle, TRANSFER_STOP_SECONDS)
            await anyio.to_thread.run_sync(app.state.store.close)
            log.info("server stopped", extra={"event": "server.stop", "pid": os.getpid()})

    app = _FacecastAPI(
        title="facecast",
        version=__version__,
        summary="Real-time example-based facial expression cloning",
        lifespan=lifespan,
        # Served by _add_docs_routes, behind auth when it is on.
        docs_url=None,
        redoc_url=None,
        openapi_url=None,
    )
    app.state.settings = settings
    app.state.store = RigStore(
        settings.rigs_dir,
        cache_size=settings.rig_cache_size,
        max_rig_bytes=settings.max_extracted_bytes,
        max_job_records=settings.max_job_records,
    )
    app.state.metrics = Metrics()
    app.state.sessions = SessionRegistry()
    app.state.channels = ChannelHub(settings, app.state.store, app.state.metrics)
    app.state.pending_fits = 0
    app.state.stopping = asyncio.Event()
    app.state.fits_per_token = Counter()  # principal name -> fit slots held (rest.fit_slot)
    app.state.profiles = profile_store(settings, app.state.store)
    install_error_handlers(app)
    app.include_router(rest_router)
    app.include_router(character_router)
    app.include_router(transfer_router)
    app.include_router(stream_router)
    app.include_router(channel_router)
    app.include_router(performer_router)
    _add_ops_routes(app)
    mount_docs(app)
    mount_landing(app)
    mount_viewer(app, settings)
    mount_perform(app)
    # Added innermost first: transport seam > access log > Host/Origin checks > CORS >
    # routes.
    if settings.allowed_origins:
        # Pages of these origins (a viewer pointed here with server=) may read the API.
        app.add_middleware(
            CORSMiddleware,
            allow_origins=list(settings.allowed_origins),
            allow_methods=["GET", "PUT", "DELETE"],
            allow_headers=["Authorization", "Content-Type"],
            max_age=600,
        )
    app.add_middleware(OriginGuard, settings=settings)
    app.add_middleware(_AccessLog, metrics=app.state.metrics, enabled=settings.access_log)
    # Outermost (inside only Starlette's ServerErrorMiddleware, which hands a WebSocket's
    # send on untouched): it must see uvicorn's own send (server/transport.py).
    app.add_middleware(TransportSeam)
    return app


def abandoned_work(app: FastAPI) -> list[str]:
    """The daemon pools of a stopped app still running work (a parse, a fit, a job).

    Their threads are daemons so that the process need not wait for them; but an
    interpreter that finalises while one runs can fail its own exit (a flush of stdout
    under a running thread exited 120), so ``runner.serve`` ends such a process at once.
    """
    pools = ("fit_executor", "small_fit_executor", "transfer_executor")
    return [name for name in pools if getattr(app.state, name).busy()]


def app_from_env() -> FastAPI:
    """Factory for worker processes: settings arrive serialised in ``FACECAST_SETTINGS_JSON``."""
    text = os.environ.get(SETTINGS_ENV)
    if not text:
        raise RuntimeError(f"{SETTINGS_ENV} is not set; start workers through `facecast serve`")
    return create_app(Settings.from_json(text))


def _add_ops_routes(app: FastAPI) -> None:
    @app.get("/healthz", tags=["ops"], summary="The process is up")
    async def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/readyz", tags=["ops"], summary="The rig store is usable")
    async def readyz(request: Request) -> Response:
        store: RigStore = request.app.state.store
        try:
            await anyio.to_thread.run_sync(store.check_readable)
        except OSError as exc:
            return problem(503, "not_ready", f"rig store: {exc}")
        reason = request.app.state.channels.not_ready_reason()
        if reason is not None:
            return problem(503, "not_ready", reason)
        return Response('{"status":"ready"}', media_type="application/json")

    @app.get("/metrics", tags=["ops"], summary="Prometheus metrics")
    async def metrics(request: Request) -> Response:
        settings: Settings = request.app.state.settings
        if settings.metrics_auth:
            authorize_request(request, ("admin",))
        body = await anyio.to_thread.run_sync(request.app.state.metrics.render)
        return Response(body, media_type=CONTENT_TYPE_LATEST)


class _FacecastAPI(FastAPI):
    """FastAPI whose unexpected failures are logged once (``errors.LogOnce``)."""

    def build_middleware_stack(self) -> ASGIApp:
        # Starlette's own hook (pinned, pyproject): its stack starts with the
        # ServerErrorMiddleware, which LogOnce must wrap.
        return LogOnce(super().build_middleware_stack())


class _AccessLog:
    """Pure-ASGI middleware: one log line and one counter increment per HTTP request.

    Pure ASGI (not BaseHTTPMiddleware) so request bodies stream through untouched.
    """

    def __init__(self, app: ASGIApp, *, metrics: Metrics, enabled: bool) -> None:
        self.app = app
        self.metrics = metrics
        self.enabled = enabled

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def send_wrapper(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            self.metrics.http_requests.labels(scope["method"], template, str(status)).inc()
            if self.enabled:
                client = scope.get("client")
                log.info(
                    "request",
                    extra={
                        "event": "http.request",
                        "method": scope["method"],
                        "path": scope["path"],
                        "status": status,
                        "ms": round((time.perf_counter() - start) * 1000, 2),
                        "client": client[0] if client else None,
                    },
                )
