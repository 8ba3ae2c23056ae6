"""Helpers of the channel tests: tiny rigs, raw watcher and publisher clients.

A real redis-server is the benchmarks' and the tests' one: ``facecast.cli.bench.harness``.

The clients speak facecast.protocol over plain websockets so the tests see exactly what a
third-party client would; nothing here fakes a server component.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path
from typing import Any

import numpy as np
import websockets

from facecast.client.channel import channel_url
from facecast.protocol import (
    SUBPROTOCOL,
    ClientProtocol,
    Error,
    Frame,
    Hello,
    Ready,
    Result,
)
from facecast.rig import ExampleSet, fit

NAMES = ("neutral", "smile", "frown", "jaw")
K = 5
RIG_IDS = ("alpha", "beta", "gamma")


def tiny_examples(
    seed: int,
    num_vertices: int = 12,
    k: int = K,
    target_scale: float = 1.0,
    names: tuple[str, ...] = NAMES,
) -> ExampleSet:
    """4 examples, ``k`` feature points, a small target (times ``target_scale``)."""
    rng = np.random.default_rng(seed)
    m = len(names)
    source = np.repeat(rng.normal(size=(1, k, 3)), m, axis=0)
    source[1:] += rng.normal(scale=0.3, size=(m - 1, k, 3))
    target = np.repeat(rng.normal(size=(1, num_vertices, 3)), m, axis=0)
    target[1:] += rng.normal(scale=0.3, size=(m - 1, num_vertices, 3))
    faces = np.array([[i, i + 1, i + 2] for i in range(num_vertices - 2)])
    return ExampleSet(names, source, target * target_scale, faces)


def tiny_rig(
    seed: int, num_vertices: int = 12, k: int = K, target_scale: float = 1.0, noise: float = 0.0
):
    """``tiny_examples`` fitted with landmark ``noise``."""
    return fit(tiny_examples(seed, num_vertices, k, target_scale), noise=noise)


def write_rigs(directory: Path, rigs: dict[str, Any]) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    for rig_id, rig in rigs.items():
        rig.save(directory / f"{rig_id}.rig")


def points(rig, seed: int) -> np.ndarray:
    """(K, 3) float32 near the rig's source neutral, different per ``seed``."""
    rng = np.random.default_rng(10_000 + seed)
    return (rig.source_neutral + rng.normal(scale=0.1, size=rig.source_neutral.shape)).astype(
        np.float32
    )


async def wait_for(predicate, timeout: float = 10.0, what: str = "condition") -> None:
    """Poll a cheap condition (an HTTP status, a counter) until true or fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        result = predicate()
        if asyncio.iscoroutine(result):
            result = await result
        if result:
            return
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        await asyncio.sleep(0.05)


async def _connect(url: str, token: str | None):
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return await websockets.connect(
        url, subprotocols=[SUBPROTOCOL], additional_headers=headers, compression=None,
        max_size=2**26, open_timeout=5,
    )  # fmt: skip


class Watcher:
    """A channel watcher: every server message goes into ``queue`` (consumed by ``next``)
    and, in arrival order and never consumed, into ``messages``."""

    def __init__(self, ws, protocol: ClientProtocol) -> None:
        self.ws = ws
        self.protocol = protocol
        self.queue: asyncio.Queue[Any] = asyncio.Queue()
        self.messages: list[Any] = []
        self.results: list[Result] = []
        self.arrivals: list[float] = []
        self.closed = asyncio.Event()
        self.close_code: int | None = None
        self._task = asyncio.create_task(self._read())

    @classmethod
    async def open(cls, base: str, channel: str, rig: str, *, output: str = "weights",
                   dtype: str = "f32", token: str | None = None) -> Watcher:  # fmt: skip
        url = channel_url(base, channel, "watch", {"rig": rig, "output": output, "dtype": dtype})
        return cls(await _connect(url, token), ClientProtocol(watching=True))

    async def _read(self) -> None:
        try:
            async for data in self.ws:
                message = self.protocol.receive(data)
                self.messages.append(message)
                if isinstance(message, Result):
                    self.results.append(message)
                    self.arrivals.append(time.time())
                self.queue.put_nowait(message)
        except websockets.ConnectionClosed:
            pass
        finally:
            self.close_code = self.ws.close_code
            self.closed.set()

    async def next(self, *types: type, timeout: float = 5.0) -> Any:
        """The next message of one of ``types`` (others are skipped)."""
        async with asyncio.timeout(timeout):
            while True:
                message = await self.queue.get()
                if not types or isinstance(message, types):
                    return message

    async def result_with_seq(self, seq: int, timeout: float = 5.0) -> Result:
        async with asyncio.timeout(timeout):
            while True:
                message = await self.next(Result, timeout=timeout)
                if message.seq >= seq:
                    return message

    async def close(self) -> None:
        await self.ws.close()
        with contextlib.suppress(Exception):
            await self._task


class Publisher:
    """A channel publisher: ``hello``, then frames; server messages go into ``queue``."""

    def __init__(self, ws, protocol: ClientProtocol, ready: Ready) -> None:
        self.ws = ws
        self.protocol = protocol
        self.ready = ready
        self.queue: asyncio.Queue[Any] = asyncio.Queue()
        self._task = asyncio.create_task(self._read())

    @classmethod
    async def open(cls, base: str, channel: str, rig: str, *, token: str | None = None,
                   **hello: Any) -> Publisher:  # fmt: skip
        ws = await _connect(channel_url(base, channel, "publish"), token)
        protocol = ClientProtocol()
        await ws.send(protocol.send(Hello(rig=rig, **hello)))
        message = protocol.receive(await asyncio.wait_for(ws.recv(), 5))
        if isinstance(message, Error):
            await ws.close()
            raise message.to_exception()
        assert isinstance(message, Ready)
        return cls(ws, protocol, message)

    async def _read(self) -> None:
        with contextlib.suppress(websockets.ConnectionClosed):
            async for data in self.ws:
                self.queue.put_nowait(self.protocol.receive(data))

    async def send(self, seq: int, pts: np.ndarray, ts: float | None = None) -> None:
        ts = time.time() if ts is None else ts
        await self.ws.send(self.protocol.send(Frame(seq=seq, ts=ts, points=pts)))

    async def close(self) -> None:
        await self.ws.close()
        with contextlib.suppress(Exception):
            await self._task


async def refused(
    url: str, *, token: str | None = None, hello: Hello | None = None, timeout: float = 5.0
) -> tuple[Error, int]:
    """Connect, (send ``hello``), and return the server's fatal error and close code
    (each awaited at most ``timeout``)."""
    ws = await _connect(url, token)
    protocol = ClientProtocol(watching=hello is None)
    if hello is not None:
        await ws.send(protocol.send(hello))
    try:
        while True:
            message = protocol.receive(await asyncio.wait_for(ws.recv(), timeout))
            if isinstance(message, Error):
                await asyncio.wait_for(ws.wait_closed(), timeout)
                return message, ws.close_code
    finally:
        await ws.close()
