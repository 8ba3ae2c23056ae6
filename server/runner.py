"""Running the app under uvicorn: one process, or N worker processes sharing one socket.

Adds what plain uvicorn lacks for us: on SIGTERM, stop accepting, then close open
stream sessions with 1001 (uvicorn would send 1012) before its own shutdown.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import uvicorn
from fastapi import FastAPI
from prometheus_client.multiprocess import mark_process_dead

from .app import SESSIONS_STATE_KEY, SETTINGS_ENV, STOPPING_STATE_KEY, abandoned_work, create_app
from .logs import uvicorn_log_config
from .serving.http_guard import HTTP_IMPLEMENTATIONS, PendingConnections, guarded_http_protocol
from .serving.ws_guard import guarded_ws_protocol
from .settings import Settings, SettingsError

__all__ = [
    "WS_IMPLEMENTATIONS",
    "FacecastServer",
    "ThreadedServer",
    "serve",
    "sweep_metrics_dirs",
    "uvicorn_config",
]

log = logging.getLogger("facecast.server")

#: Incoming WebSocket messages up to this multiple of ``max_message_bytes`` reach the
#: protocol decoder (which answers MESSAGE_TOO_LARGE and keeps the session); larger
#: ones are cut by uvicorn with close code 1009 before they are buffered.
_WS_SIZE_FACTOR = 2
#: uvicorn's WebSocket implementations the server supports ("auto" is the first). Not
#: wsproto: it is not a dependency, and its pongs are not bounded (SERVER.md).
WS_IMPLEMENTATIONS = ("websockets-sansio", "websockets")
#: HTTP requests and WebSocket connections beyond ``max_connections`` (+ publisher
#: slots) before uvicorn answers 503 itself; sessions have their own, lower, limit.
_HTTP_HEADROOM = 64
#: Messages uvicorn's legacy ``websockets`` implementation reads ahead of the app per
#: connection (its default, 32, let one tokenless connection make the server buffer
#: 32 x ws_max_size = 66 MB while it was being refused); ``websockets-sansio`` holds one.
_WS_MAX_QUEUE = 2


def _ws_protocol(settings: Settings, ws: str) -> type:
    if ws == "auto":
        ws = WS_IMPLEMENTATIONS[0]
    if ws not in WS_IMPLEMENTATIONS:
        raise SettingsError(f"ws: {ws!r} is not supported; choose one of {WS_IMPLEMENTATIONS}")
    return guarded_ws_protocol(
        ws, max_pong_backlog=settings.max_pong_backlog, close_timeout=settings.ws_close_timeout
    )


def uvicorn_config(
    settings: Settings,
    app: FastAPI | str,
    *,
    ws: str = "auto",
    http: str = "auto",
    **overrides: Any,
) -> uvicorn.Config:
    """The ``uvicorn.Config`` for ``settings`` (``app`` an ASGI app or an import string).

    ``http``: uvicorn's HTTP implementation, a key of ``http_guard.HTTP_IMPLEMENTATIONS``.
    """
    if http not in HTTP_IMPLEMENTATIONS:
        raise SettingsError(f"http: {http!r} is not one of {sorted(HTTP_IMPLEMENTATIONS)}")
    kwargs: dict[str, Any] = dict(
        host=settings.host,
        port=settings.port,
        lifespan="on",
        ws=_ws_protocol(settings, ws),
        ws_max_size=_WS_SIZE_FACTOR * settings.max_message_bytes + 64 * 1024,
        ws_max_queue=_WS_MAX_QUEUE,
        ws_ping_interval=settings.ping_interval or None,
        ws_ping_timeout=settings.ping_timeout or None,
        timeout_graceful_shutdown=max(settings.shutdown_timeout, 0.1),
        log_config=uvicorn_log_config(settings.log_level),
        access_log=False,
        server_header=False,
        # X-Forwarded-For names the client only when a trusted proxy sent it (the per-
        # address quota counts that address); uvicorn alone would believe 127.0.0.1.
        proxy_headers=bool(settings.trusted_proxies),
        forwarded_allow_ips=list(settings.trusted_proxies) or None,
        # Results are float arrays that deflate barely shrinks, and per-connection
        # compression would cost every viewer its own pass over each result.
        ws_per_message_deflate=False,
        # Connections that have not sent a complete request are bounded apart (deadlines
        # and max_pending_connections, http_guard), so they cannot fill this one.
        http=guarded_http_protocol(
            PendingConnections(
                idle_timeout=settings.request_idle_timeout,
                head_timeout=settings.request_head_timeout,
                max_pending=settings.max_pending_connections,
            ),
            http,
        ),
        timeout_keep_alive=settings.request_idle_timeout,
        # uvicorn counts every open connection, pending ones too: they get room of their own.
        limit_concurrency=settings.max_connections
        + settings.publisher_slots
        + _HTTP_HEADROOM
        + settings.max_pending_connections,
    )
    kwargs.update(overrides)
    return uvicorn.Config(app, **kwargs)


class FacecastServer(uvicorn.Server):
    """uvicorn's server, closing stream sessions with 1001 ("going away") on shutdown.

    Requests still reading a body or waiting for a fit are told to stop at once (the app's
    ``stopping`` event: they answer 503 ``shutting_down``), rather than be cancelled by
    uvicorn when its graceful wait runs out (a 500 and a traceback).
    """

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        for server in getattr(self, "servers", []):
            server.close()  # stop accepting before anything else
        stopping = self.lifespan.state.get(STOPPING_STATE_KEY)
        if stopping is not None:
            stopping.set()
        sessions = self.lifespan.state.get(SESSIONS_STATE_KEY)
        if sessions is not None:
            timeout = getattr(self.config, "timeout_graceful_shutdown", None) or 5.0
            await sessions.close_all(1001, "server shutting down", timeout=timeout)
        await super().shutdown(sockets=sockets)


class ThreadedServer:
    """A `FacecastServer` running its own event loop in a thread, on a socket bound by the caller.

    For the demo and for tests: the caller's loop (or blocking calls) cannot stall it.
    uvicorn has no start-up callback, so callers poll `started()` between short waits of
    their own (``time.sleep`` or ``asyncio.sleep``).
    """

    def __init__(self, config: uvicorn.Config, sock: socket.socket, *, startup_timeout: float):
        self.server = FacecastServer(config)
        self.sock = sock
        self._failure: list[BaseException] = []
        self._deadline = time.monotonic() + startup_timeout
        self._startup_timeout = startup_timeout
        self.thread = threading.Thread(
            target=self._run, name=f"facecast-{sock.getsockname()[1]}", daemon=True
        )
        self.thread.start()

    def _run(self) -> None:
        try:
            self.server.run(sockets=[self.sock])
        except BaseException as exc:  # SystemExit on a failed start-up, too
            self._failure.append(exc)

    def started(self) -> bool:
        """Whether it serves yet; raises if it failed or missed its start-up deadline."""
        if self.server.started:
            return True
        if self._failure or not self.thread.is_alive():
            self.sock.close()
            raise RuntimeError(f"server failed to start: {self._failure[:1]}")
        if time.monotonic() > self._deadline:
            self.server.should_exit = True
            raise TimeoutError(f"server did not start within {self._startup_timeout} s")
        return False

    def stop(self, timeout: float = 30.0) -> None:
        """Ask it to exit, wait for the thread, close the socket (blocking)."""
        self.server.should_exit = True
        self.thread.join(timeout)
        self.sock.close()


def serve(settings: Settings, *, ws: str = "auto") -> int:
    """Run the server in the foreground until SIGINT/SIGTERM; returns an exit status."""
    settings.check_startable()
    if settings.workers == 1:
        app = create_app(settings)
        server = FacecastServer(uvicorn_config(settings, app, ws=ws))
        with _signals_end_in_status():
            server.run()
        status = 0 if server.started else 1
        if server.started and (busy := abandoned_work(app)):
            _exit_abandoning(status, busy)
        return status
    return _serve_workers(settings, ws)


def _exit_abandoning(status: int, busy: list[str]) -> None:
    """End the process now, its logs flushed: work still runs in ``busy`` daemon pools,
    and finalising the interpreter under them is not safe (``app.abandoned_work``)."""
    log.info("exiting with work abandoned", extra={"event": "server.abandon", "pools": busy})
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(status)


@contextlib.contextmanager
def _signals_end_in_status() -> Iterator[None]:
    """Let SIGTERM/SIGINT end ``serve`` with its return value, as with ``--workers N``.

    After a graceful shutdown uvicorn re-raises the signal it caught, with the handlers
    found at start restored: those are these no-ops, so the process is not killed by it
    (exit status -15) and ``serve`` returns.
    """
    previous = {s: signal.signal(s, _ignore) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _ignore(signum: int, frame: FrameType | None) -> None:
    """A handler that only marks the signal as handled (uvicorn's own runs meanwhile)."""


def _worker(settings_json: str, ws: str, sock: socket.socket) -> None:
    os.environ[SETTINGS_ENV] = settings_json
    settings = Settings.from_json(settings_json)
    config = uvicorn_config(
        settings, "facecast.server.app:app_from_env", ws=ws, factory=True, workers=1
    )
    config.configure_logging()
    FacecastServer(config).run(sockets=[sock])


#: The prefix of a supervisor's metrics directory, followed by its pid and a dash.
_METRICS_PREFIX = "facecast-metrics-"


def sweep_metrics_dirs(parent: Path) -> list[Path]:
    """Remove the metrics directories in ``parent`` of supervisors no longer running.

    A supervisor killed with SIGKILL leaves its ``facecast-metrics-<pid>-*`` directory
    (the workers' metric files) behind; one whose pid is gone is removed. Only this
    user's, and only directories named so. Returns those removed.
    """
    removed = []
    for path in parent.glob(f"{_METRICS_PREFIX}*-*"):
        pid_text = path.name[len(_METRICS_PREFIX) :].split("-", 1)[0]
        if not pid_text.isdigit() or not path.is_dir() or path.stat().st_uid != os.getuid():
            continue
        try:
            os.kill(int(pid_text), 0)
        except ProcessLookupError:
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
        except (PermissionError, OverflowError):
            continue  # alive (someone else's), or not a pid
    return removed


def _serve_workers(settings: Settings, ws: str) -> int:
    """N spawned worker processes serving one listening socket bound here.

    All share the rig directory (the store re-stats, so uploads through one worker are
    seen by all); metrics are summed through prometheus multiprocess mode.
    """
    config = uvicorn_config(settings, "facecast.server.app:app_from_env", ws=ws, factory=True)
    config.configure_logging()
    sock = config.bind_socket()
    sweep_metrics_dirs(Path(tempfile.gettempdir()))
    # Named after this process, so a later supervisor can tell it is gone (kill -9
    # skips the clean-up) and remove it.
    metrics_dir = tempfile.TemporaryDirectory(prefix=f"{_METRICS_PREFIX}{os.getpid()}-")
    # Read by prometheus_client in the workers (spawned processes inherit the env).
    os.environ["PROMETHEUS_MULTIPROC_DIR"] = metrics_dir.name
    ctx = multiprocessing.get_context("spawn")
    text = settings.to_json()

    def start() -> multiprocessing.process.BaseProcess:
        process = ctx.Process(target=_worker, args=(text, ws, sock), daemon=False)
        process.start()
        return process

    stopping = False

    def on_signal(signum: int, frame: FrameType | None) -> None:
        nonlocal stopping
        stopping = True

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    processes = [start() for _ in range(settings.workers)]
    log.info(
        "workers started",
        extra={"event": "server.workers", "workers": settings.workers, "pid": os.getpid()},
    )
    try:
        while not stopping:
            for i, process in enumerate(processes):
                if not process.is_alive() and not stopping:
                    log.warning(
                        "worker died; restarting",
                        extra={"event": "server.worker_died", "exitcode": process.exitcode},
                    )
                    # Its live gauges (open connections) would otherwise count for ever.
                    if process.pid is not None:
                        # prometheus_client leaves this function unannotated.
                        mark_process_dead(process.pid, metrics_dir.name)  # type: ignore[no-untyped-call]
                    processes[i] = start()
            time.sleep(0.2)
    finally:
        for process in processes:
            if process.is_alive() and process.pid is not None:
                os.kill(process.pid, signal.SIGTERM)
        deadline = time.monotonic() + settings.shutdown_timeout + 5.0
        for process in processes:
            process.join(max(deadline - time.monotonic(), 0.1))
            if process.is_alive():
                process.kill()
                process.join()
        sock.close()
        metrics_dir.cleanup()
        for s, handler in previous.items():
            signal.signal(s, handler)
    return 0
