"""``facecast bench broadcast``'s viewers: client processes holding thousands of raw viewers.

Each process (``Clients`` starts them, spawned) runs minimal RFC 6455 viewers on uvloop and
answers commands over a pipe: add viewers, measure, collect, quit. Cheap per message on
purpose: thousands share one process; they count results and read latencies, nothing else.
"""

from __future__ import annotations

import asyncio
import base64
import multiprocessing
import os
import struct
import time
from array import array
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any, cast

import msgpack
import numpy as np
import uvloop

__all__ = ["CLIENT_PROCESSES", "RIGS", "Clients"]

#: The rigs (characters) of the benchmark's channel; viewers are spread over them.
RIGS = ("bench-a", "bench-b", "bench-c")
CLIENT_PROCESSES = 2

_RESULT_TYPE = b"\xa4type\xa6result"
_TS_KEY = b"\xa2ts\xcb"
_F64 = struct.Struct(">d")


class _Viewer(asyncio.Protocol):
    """A minimal RFC 6455 client: handshake, unmasked server frames, pongs; no library.

    Cheap per message on purpose: thousands of these share one client process.
    """

    def __init__(self, path: str, stats: dict[str, Any]) -> None:
        self.path = path
        self.stats = stats
        self.buffer = bytearray()
        self.open = False
        self.ready = asyncio.get_running_loop().create_future()
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # A stream connection's transport (asyncio types the callback for every protocol).
        self.transport = cast(asyncio.Transport, transport)
        key = base64.b64encode(os.urandom(16)).decode()
        self.transport.write(
            (
                f"GET {self.path} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                "Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: facecast.v1\r\n\r\n"
            ).encode()
        )

    def connection_lost(self, exc: Exception | None) -> None:
        self.stats["lost"] += 1
        if not self.ready.done():
            self.ready.set_result(False)

    def data_received(self, data: bytes) -> None:
        # Fast path (nearly every call): exactly one whole unfragmented frame, no copy.
        if self.open and not self.buffer and len(data) >= 2:
            length, offset = data[1] & 0x7F, 2
            if length == 126 and len(data) >= 4:
                length, offset = int.from_bytes(data[2:4], "big"), 4
            if length < 127 and len(data) == offset + length:
                self._message(data[0] & 0x0F, data, offset)
                return
        buf = self.buffer
        buf += data
        if not self.open:
            end = buf.find(b"\r\n\r\n")
            if end < 0:
                return
            ok = buf.startswith(b"HTTP/1.1 101")
            del buf[: end + 4]
            self.open = True
            if not self.ready.done():
                self.ready.set_result(ok)
        while len(buf) >= 2:
            length, offset = buf[1] & 0x7F, 2
            if length == 126:
                if len(buf) < 4:
                    return
                length, offset = int.from_bytes(buf[2:4], "big"), 4
            elif length == 127:
                if len(buf) < 10:
                    return
                length, offset = int.from_bytes(buf[2:10], "big"), 10
            if len(buf) < offset + length:
                return
            frame = bytes(buf[: offset + length])
            del buf[: offset + length]
            self._message(frame[0] & 0x0F, frame, offset)

    def _message(self, opcode: int, frame: bytes, offset: int) -> None:
        if opcode == 2:
            # The server's result maps start {v, type, seq, ts, ...}: read ts in place
            # (a full msgpack decode costs the client more than the server's send).
            if frame.find(_RESULT_TYPE, offset, offset + 24) < 0:
                return
            self.stats["results"] += 1
            if self.stats["measuring"]:
                at = frame.find(_TS_KEY, offset)
                if at >= 0:
                    ts = _F64.unpack_from(frame, at + len(_TS_KEY))[0]
                else:  # pragma: no cover - another encoder's key order
                    ts = msgpack.unpackb(frame[offset:])["ts"]
                self.stats["latency"].append(time.time() - ts)
        elif opcode == 9 and self.transport is not None:  # ping: answer with a masked pong
            payload = frame[offset:]
            mask = os.urandom(4)
            body = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
            self.transport.write(bytes([0x8A, 0x80 | len(payload)]) + mask + body)


def _client_main(conn: Connection, port_by_group: dict[str, int]) -> None:
    """A client process: obeys ("add", group, rig, n), ("measure", on), ("collect",), ("quit",)."""

    async def main() -> None:
        loop = asyncio.get_running_loop()
        stats: dict[str, Any] = {"results": 0, "lost": 0, "measuring": False,
                                 "latency": array("d")}  # fmt: skip
        viewers: list[_Viewer] = []
        while True:
            command = await loop.run_in_executor(None, conn.recv)
            if command[0] == "add":
                _, group, rig, count = command
                path = f"/v1/channels/bench/watch?rig={rig}&output=weights&dtype=f32"
                port = port_by_group[group]

                async def join(viewer: _Viewer, port: int = port) -> bool:
                    try:
                        await loop.create_connection(lambda: viewer, "127.0.0.1", port)
                        return bool(await asyncio.wait_for(viewer.ready, 10))
                    except (OSError, TimeoutError):
                        return False

                failed = 0
                # Batches of 50 at once: quick, without a connect storm; 10 s per batch
                # at most, so an overloaded server bounds the ramp's time.
                for start in range(0, count, 50):
                    batch = [_Viewer(path, stats) for _ in range(min(50, count - start))]
                    viewers.extend(batch)
                    joined = await asyncio.gather(*(join(v) for v in batch))
                    failed += joined.count(False)
                conn.send(("added", failed))
            elif command[0] == "measure":
                stats["measuring"] = command[1]
                if command[1]:
                    stats["latency"] = array("d")
                    stats["results"] = 0
                conn.send(("ok",))
            elif command[0] == "collect":
                conn.send(("stats", stats["latency"].tobytes(), stats["results"], stats["lost"]))
            else:
                for viewer in viewers:
                    if viewer.transport is not None:
                        viewer.transport.close()
                conn.send(("bye",))
                return

    uvloop.run(main())  # less client CPU per message than asyncio's own loop


class Clients:
    """The client processes and the commands sent to all of them."""

    def __init__(self, ports: dict[str, int]) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.pipes: list[Connection] = []
        self.processes: list[BaseProcess] = []
        for _ in range(CLIENT_PROCESSES):
            here, there = ctx.Pipe()
            process = ctx.Process(target=_client_main, args=(there, ports), daemon=True)
            process.start()
            self.pipes.append(here)
            self.processes.append(process)

    async def ask(
        self, command: tuple[Any, ...], pipes: list[Connection] | None = None
    ) -> list[tuple[Any, ...]]:
        pipes = pipes or self.pipes
        for pipe in pipes:
            pipe.send(command)
        return [await asyncio.to_thread(pipe.recv) for pipe in pipes]

    async def add(self, group: str, count: int) -> int:
        """``count`` more viewers on ``group``, rigs round-robin; connection failures."""
        failed = 0
        share = [
            count // len(self.pipes) + (i < count % len(self.pipes)) for i in range(len(self.pipes))
        ]
        for pipe, n in zip(self.pipes, share, strict=True):
            for r, rig in enumerate(RIGS):
                k = n // len(RIGS) + (r < n % len(RIGS))
                if k:
                    failed += (await self.ask(("add", group, rig, k), [pipe]))[0][1]
        return failed

    async def measure(self, seconds: float, published: Callable[[], int]) -> dict[str, float]:
        await self.ask(("measure", True))
        frames0 = published()
        await asyncio.sleep(seconds)
        frames = published() - frames0
        await self.ask(("measure", False))
        replies = await self.ask(("collect",))
        latency = np.concatenate([np.frombuffer(r[1]) for r in replies]) * 1000.0
        results = sum(r[2] for r in replies)
        lost = sum(r[3] for r in replies)
        return {
            "p50_ms": float(np.percentile(latency, 50)) if latency.size else float("nan"),
            "p99_ms": float(np.percentile(latency, 99)) if latency.size else float("nan"),
            "results": results,
            "frames": frames,
            "lost": lost,
        }

    async def close(self) -> None:
        await self.ask(("quit",))
        for process in self.processes:
            process.join(5)
