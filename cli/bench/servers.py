"""The servers the benchmarks start in subprocesses: bare floors, and facecast set up to bench.

Each ``serve_…`` function is a subprocess's whole life (``harness.python_server`` runs it):
it serves on 127.0.0.1:``port`` until killed. The floors are the least a server can do for
the same bytes (echo them, answer each frame with a result of the same size, broadcast one
result to every viewer), measured in the same run as facecast. Nothing here measures.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path

import msgpack
import numpy as np
import uvicorn
import uvloop

# At module level: FastAPI resolves the echo endpoint's (string) annotations here.
from fastapi import FastAPI, WebSocket, WebSocketDisconnect
from websockets.asyncio.server import ServerConnection, broadcast, serve
from websockets.typing import Subprotocol

from facecast.protocol import SUBPROTOCOL, Result, encode, encode_result

__all__ = [
    "BENCH_MAX_FPS",
    "serve_broadcast_floor",
    "serve_facecast",
    "serve_fastapi_echo",
    "serve_relay_floor",
    "serve_vertices_floor",
    "serve_websockets_echo",
]

#: Facecast's rate limit in the benchmark: far above any rate reached here, so the
#: pipelined phase measures the path, not the limit (``max_fps`` defaults to 240).
BENCH_MAX_FPS = 1e6
#: The largest message any of these servers reads (a whole ICT mesh is ~160 kB).
_MAX_SIZE = 1 << 24


def serve_websockets_echo(port: int) -> None:
    """A bare ``websockets`` echo server on uvloop."""

    async def echo(ws: ServerConnection) -> None:
        async for message in ws:
            await ws.send(message)

    async def main() -> None:
        async with serve(echo, "127.0.0.1", port, compression=None, max_size=_MAX_SIZE):
            await asyncio.Future()

    uvloop.run(main())


def serve_relay_floor(port: int) -> None:
    """A bare ``websockets`` relay: each message from one connection goes to every other,
    as it comes (the least a server between a publisher page and a viewer page can do)."""
    members: set[ServerConnection] = set()

    async def relay(ws: ServerConnection) -> None:
        members.add(ws)
        try:
            async for message in ws:
                broadcast([m for m in members if m is not ws], message)
        finally:
            members.discard(ws)

    async def main() -> None:
        async with serve(relay, "127.0.0.1", port, compression=None, max_size=1 << 20,
                         ping_interval=None):  # fmt: skip
            await asyncio.Future()

    uvloop.run(main())


def serve_fastapi_echo(port: int) -> None:
    """A bare FastAPI/uvicorn WebSocket echo endpoint, ``/echo``."""
    app = FastAPI()

    @app.websocket("/echo")
    async def echo_endpoint(websocket: WebSocket) -> None:
        await websocket.accept()
        with contextlib.suppress(WebSocketDisconnect):
            while True:
                await websocket.send_bytes(await websocket.receive_bytes())

    uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning", loop="uvloop")


def serve_vertices_floor(port: int, rigs_dir: str) -> None:
    """The floor of a vertex stream: each frame answered with a result of facecast's bytes.

    Reads ``bare.npz`` in ``rigs_dir`` (the ``ready`` and the f16 vertices a bounded
    session gets, for output ``moving`` and for the whole mesh); no rig, no session.
    """
    with np.load(Path(rigs_dir) / "bare.npz") as data:
        answers = {
            output: (bytes(data[f"ready_{output}"]), np.ascontiguousarray(data[output]))
            for output in ("moving", "vertices")
        }

    async def answer(ws: ServerConnection) -> None:
        # Read each frame's seq and ts, send a result of the same bytes facecast sends
        # (the moving or the whole mesh, as hello asks); nothing else.
        hello = msgpack.unpackb(await ws.recv())
        ready, values = answers["vertices" if hello.get("output") == "vertices" else "moving"]
        await ws.send(ready)
        async for message in ws:
            frame = msgpack.unpackb(message)
            await ws.send(encode_result(frame["seq"], frame["ts"], "vertices", values, 0, 0))

    async def main() -> None:
        async with serve(answer, "127.0.0.1", port, compression=None, max_size=_MAX_SIZE,
                         subprotocols=[Subprotocol(SUBPROTOCOL)]):  # fmt: skip
            await asyncio.Future()

    uvloop.run(main())


def serve_broadcast_floor(port: int, ready: bytes, weights: bytes) -> None:
    """A bare ``websockets`` broadcast: viewers connect on any ``.../watch`` path; each
    frame the publisher sends is answered by one ``broadcast()`` of a result to each
    rig's viewers."""
    values = np.frombuffer(weights, dtype=np.float32)
    groups: dict[str, set[ServerConnection]] = {}

    async def handler(ws: ServerConnection) -> None:
        assert ws.request is not None  # the handshake is done when the handler runs
        path = ws.request.path
        if "/publish" in path:
            await ws.recv()  # hello
            await ws.send(ready)
            async for message in ws:
                frame = msgpack.unpackb(message)
                for members in groups.values():
                    # What facecast sends a watcher: the rig's result, encoded once.
                    data = encode(Result(seq=frame["seq"], ts=frame["ts"], weights=values,
                                         server_ts=time.time()))  # fmt: skip
                    broadcast(members, data)
            return
        rig = path.split("rig=", 1)[-1].split("&", 1)[0]
        members = groups.setdefault(rig, set())
        members.add(ws)
        try:
            await ws.wait_closed()
        finally:
            members.discard(ws)

    async def main() -> None:
        async with serve(handler, "127.0.0.1", port, compression=None, max_size=1 << 20,
                         subprotocols=[Subprotocol(SUBPROTOCOL)], ping_interval=None):  # fmt: skip
            await asyncio.Future()

    uvloop.run(main())


def serve_facecast(port: int, rigs_dir: str, stage_timing: bool) -> None:
    """``facecast serve``'s server (``runner.serve``) with its rate limit out of the way."""
    from facecast.server.runner import serve as serve_facecast_settings
    from facecast.server.settings import Settings

    settings = Settings(
        host="127.0.0.1",
        port=port,
        rigs_dir=Path(rigs_dir),
        # A benchmark measures the path, not the per-client rate limit.
        max_fps=BENCH_MAX_FPS,
        rate_burst=1_000_000,
        log_level="warning",
        access_log=False,
        # The stage clocks (a thread-CPU clock read, a system call, ~8 a frame) only
        # where the figures are attributed; the judged figures run as deployed.
        stage_timing=stage_timing,
    )
    serve_facecast_settings(settings)
