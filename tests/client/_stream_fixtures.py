"""Fixtures for the streaming-client tests: the fitted demo rig and a real server on a port.

``LiveServer`` runs facecast's app under a real uvicorn in a thread on a fixed 127.0.0.1
port, so a test can stop it and start it again on the same port (reconnection tests).
"""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import pytest

from facecast.rig import Rig, fit
from facecast.rig.demo import demo_example_set
from facecast.server.app import create_app
from facecast.server.runner import FacecastServer, uvicorn_config
from facecast.server.settings import Settings
from facecast.server.testing import WS_IMPLEMENTATIONS, free_port

RIG_ID = "demo"


class LiveServer:
    """facecast on 127.0.0.1:``port``; `start` and `stop` may alternate."""

    def __init__(
        self, settings: Settings, port: int | None = None, ws: str = "websockets-sansio"
    ) -> None:
        self.settings = settings
        self.ws = ws
        self.port = port or free_port()
        self._server: FacecastServer | None = None
        self._thread: threading.Thread | None = None

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout: float = 10.0) -> LiveServer:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", self.port))
        config = uvicorn_config(
            self.settings,
            create_app(self.settings),
            ws=self.ws,
            host="127.0.0.1",
            port=self.port,
        )
        server = FacecastServer(config)
        thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
        thread.start()
        deadline = time.monotonic() + timeout
        # uvicorn has no start-up callback: poll its ``started`` flag against a deadline.
        while not server.started:
            if not thread.is_alive() or time.monotonic() > deadline:
                server.should_exit = True
                raise RuntimeError(f"server on port {self.port} did not start")
            time.sleep(0.01)
        self._server, self._thread, self._sock = server, thread, sock
        return self

    def stop(self) -> None:
        if self._server is None:
            return
        self._server.should_exit = True
        assert self._thread is not None
        self._thread.join(30.0)
        self._sock.close()
        self._server = None


def server_settings(rigs_dir: Path, **changes) -> Settings:
    values = dict(
        rigs_dir=rigs_dir,
        log_level="warning",
        access_log=False,
        max_fps=2000.0,
        rate_burst=200,
        shutdown_timeout=0.5,
    )
    values.update(changes)
    return Settings(**values)


@pytest.fixture(scope="session")
def demo_rig() -> Rig:
    return fit(demo_example_set())


@pytest.fixture(scope="session")
def rigs_dir(tmp_path_factory, demo_rig) -> Path:
    folder = tmp_path_factory.mktemp("rigs")
    demo_rig.save(folder / f"{RIG_ID}.rig")
    return folder


@pytest.fixture(scope="module", params=WS_IMPLEMENTATIONS)
def live_server(request, rigs_dir):
    """A server per module and uvicorn WebSocket implementation (the client works on both)."""
    server = LiveServer(server_settings(rigs_dir), ws=request.param).start()
    yield server
    server.stop()
