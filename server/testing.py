"""Test helpers: a real uvicorn serving ``create_app(settings)`` on 127.0.0.1, in a thread.

For tests and benchmarks of any package (``from facecast.server.testing import
run_server``); production code never imports this module. Servers in processes of their
own (``facecast serve``, redis-server, the benchmarks' floors) are started, waited for and
stopped by ``facecast.cli.bench.harness``, which never imports the server.
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any

from fastapi import FastAPI

from .app import create_app
from .runner import WS_IMPLEMENTATIONS, FacecastServer, ThreadedServer, uvicorn_config
from .settings import Settings

__all__ = ["WS_IMPLEMENTATIONS", "RunningServer", "free_port", "run_server"]


@dataclass
class RunningServer:
    """A started server: where it listens and its app (to inspect ``app.state``)."""

    app: FastAPI
    settings: Settings
    server: FacecastServer
    host: str
    port: int

    @property
    def base_url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://{self.host}:{self.port}"


def free_port(host: str = "127.0.0.1") -> int:
    """A port free right now (for subprocess servers that must bind it themselves)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        port: int = sock.getsockname()[1]
        return port


@asynccontextmanager
async def run_server(
    settings: Settings | None = None,
    *,
    ws: str = "websockets-sansio",
    startup_timeout: float = 10.0,
    app: Any = None,
    **config: Any,
) -> AsyncIterator[RunningServer]:
    """Serve ``create_app(settings)`` with a real uvicorn on 127.0.0.1 until the block exits.

    The server runs its own event loop in a thread, so the test's loop (and any
    blocking call in the test) cannot stall it. The listening socket is bound here, on a
    free port, before uvicorn starts: no race for the port. ``ws`` picks uvicorn's
    WebSocket implementation (see ``WS_IMPLEMENTATIONS``); ``app`` serves another ASGI
    app than ``create_app(settings)`` (e.g. one wrapped in a middleware of the test's);
    extra keywords go to ``uvicorn.Config``.
    """
    settings = settings or Settings()
    if app is None:
        app = create_app(settings)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    uv_config = uvicorn_config(settings, app, ws=ws, host="127.0.0.1", port=port, **config)
    threaded = ThreadedServer(uv_config, sock, startup_timeout=startup_timeout)
    while not threaded.started():
        await asyncio.sleep(0.01)
    try:
        yield RunningServer(app, settings, threaded.server, "127.0.0.1", port)
    finally:
        await asyncio.get_running_loop().run_in_executor(None, threaded.stop)
