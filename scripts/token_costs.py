#!/usr/bin/env python3
"""Measures what a client holding a token costs a real `facecast serve` on 127.0.0.1 (SERVER.md).

For each role at its bounds, against one server process (auth on, defaults otherwise,
the ICT rig fitted from ../shared/data/ict-facekit or $FACECAST_ICT): server CPU seconds
per second of wall time (utime + stime from /proc, all threads), RSS, connections. A
`stream` token flooding frames (weights, vertices) on 1 and 10 connections and
calibrates on 4; held idle sessions; a `publisher` flooding frames with a `viewer`'s
watchers on 1 and 9 keys; a viewer fetching the mesh (model.glb) in a loop; a
`performer` refitting its capture in a loop. Each scenario is bounded in time
(``--seconds``, default 8). Loopback only. Run from the repository:
`.venv/bin/python scripts/token_costs.py`. The client runs on the same machine and
takes CPU of its own: the figures are what the server spent while one client pushed.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import platform
import sys
import tempfile
import time
import warnings
from collections.abc import AsyncIterator
from pathlib import Path

import httpx
import numpy as np
import websockets

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from hostile_costs import rss_mb, start, stop

from facecast.client.channel import channel_url
from facecast.protocol import (
    SUBPROTOCOL,
    Calibrate,
    ClientProtocol,
    Frame,
    Hello,
    Ready,
    encode,
)
from facecast.rig import Rig, fit
from facecast.rig.sources.ict import ict_example_set

TOKENS = "admin-t:admin,stream-t:stream,publisher-t:publisher,viewer-t:viewer,performer-t:performer"
ICT = Path(
    os.environ.get("FACECAST_ICT", Path(__file__).resolve().parents[2] / "shared/data/ict-facekit")
)


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Server:
    """``hostile_costs.start``'s server (auth on, one worker), with this script's tokens."""

    def __init__(self, rigs: Path) -> None:
        self.process, self.port = start("websockets-sansio", rigs, f"FACECAST_TOKENS={TOKENS}")
        self.base = f"http://127.0.0.1:{self.port}"
        self.ws = f"ws://127.0.0.1:{self.port}"

    def stop(self) -> None:
        stop(self.process)


class Meter:
    """Server CPU s/s and RSS over one scenario (RSS sampled every 0.2 s for the peak)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid

    async def __aenter__(self) -> Meter:
        self.rss0 = self.peak = rss_mb(self.pid)
        self.cpu0, self.t0 = cpu_seconds(self.pid), time.monotonic()
        self._sampler = asyncio.create_task(self._sample())
        return self

    async def _sample(self) -> None:
        while True:
            self.peak = max(self.peak, rss_mb(self.pid))
            await asyncio.sleep(0.2)

    async def __aexit__(self, *exc: object) -> None:
        self._sampler.cancel()
        self.seconds = time.monotonic() - self.t0
        self.cpu = cpu_seconds(self.pid) - self.cpu0
        self.rss1 = rss_mb(self.pid)

    def line(self, what: str, extra: str = "") -> str:
        return (f"{what:58s} CPU {self.cpu / self.seconds:5.2f} s/s ({self.cpu:5.1f} s in "
                f"{self.seconds:4.1f} s); RSS {self.rss0:6.1f} -> peak {self.peak:6.1f} -> "
                f"{self.rss1:6.1f} MB{extra}")  # fmt: skip


@contextlib.asynccontextmanager
async def session(url: str, hello: Hello, token: str) -> AsyncIterator[websockets.ClientConnection]:
    sep = "&" if "?" in url else "?"
    ws = await websockets.connect(f"{url}{sep}token={token}", subprotocols=[SUBPROTOCOL],
                                  compression=None, max_size=None, max_queue=4,
                                  close_timeout=2)  # fmt: skip
    try:
        protocol = ClientProtocol()
        if hello is not None:
            await ws.send(protocol.send(hello))
            ready = protocol.receive(await asyncio.wait_for(ws.recv(), 30))
            assert isinstance(ready, Ready), ready
        yield ws
    finally:
        await ws.close()


async def drain(ws) -> int:
    count = 0
    with contextlib.suppress(websockets.ConnectionClosed):
        async for _ in ws:
            count += 1
    return count


async def flood(ws, messages: list[bytes], seconds: float, per_second: float) -> tuple[int, int]:
    """``messages`` in turn at ``per_second`` for ``seconds``, answers read aside; then close.

    (sent, answers read): the server's work for a stream is bounded by what its client
    reads too (results not read are superseded, not computed).
    """
    reader = asyncio.create_task(drain(ws))
    start = time.monotonic()
    sent = 0
    while time.monotonic() - start < seconds:
        for _ in range(10):
            await ws.send(messages[sent % len(messages)])
            sent += 1
        await asyncio.sleep(max(0.0, start + sent / per_second - time.monotonic()))
    await ws.close()
    return sent, await reader


def frames(points: np.ndarray) -> list[bytes]:
    return [encode(Frame(seq=i, ts=i / 240, points=points)) for i in range(1000)]


async def streams(stack, server: Server, hello: Hello, count: int) -> list:
    url = f"{server.ws}/v1/stream"
    return [await stack.enter_async_context(session(url, hello, "stream-t")) for _ in range(count)]


async def frames_scenario(server: Server, points, seconds, output: str, connections: int) -> str:
    # 1000 frames/s per connection: over max_fps (240), as a hostile client sends them.
    async with contextlib.AsyncExitStack() as stack:
        sockets = await streams(stack, server, Hello(rig="ict", output=output), connections)
        async with Meter(server.process.pid) as meter:
            sent = await asyncio.gather(
                *(flood(ws, frames(points), seconds, 1000.0) for ws in sockets)
            )
    return meter.line(f"stream token: {connections:3d} conn flooding frames, {output}",
                      f"; {sum(s for s, _ in sent)} frames sent, "
                      f"{sum(r for _, r in sent)} answers read")  # fmt: skip


async def calibrate_scenario(server: Server, points, seconds, connections: int) -> str:
    message = [encode(Calibrate(points=points))]
    async with contextlib.AsyncExitStack() as stack:
        sockets = await streams(stack, server, Hello(rig="ict"), connections)
        async with Meter(server.process.pid) as meter:
            sent = await asyncio.gather(*(flood(ws, message, seconds, 4000.0) for ws in sockets))
    return meter.line(f"stream token: {connections:3d} conn flooding calibrates",
                      f"; {sum(s for s, _ in sent)} calibrates sent, "
                      f"{sum(r for _, r in sent)} answers read")  # fmt: skip


async def idle_sessions(server: Server, count: int) -> str:
    pid = server.process.pid
    before = rss_mb(pid)
    async with contextlib.AsyncExitStack() as stack:
        for _ in range(count):
            await stack.enter_async_context(
                session(f"{server.ws}/v1/stream", Hello(rig="ict"), "stream-t")
            )
        held = rss_mb(pid)
        cpu0, t0 = cpu_seconds(pid), time.monotonic()
        await asyncio.sleep(3.0)
        idle_cpu = (cpu_seconds(pid) - cpu0) / (time.monotonic() - t0)
    return (
        f"stream token: {count} idle sessions held (the token's quota): RSS {before:.1f} -> "
        f"{held:.1f} MB ({(held - before) * 1024 / count:.0f} kB each); CPU {idle_cpu:.3f} s/s"
    )


async def channel_scenario(
    server: Server, points, seconds, keys: list[tuple[str, str]], *, calibrates: bool = False
) -> str:
    url = channel_url(server.ws, "stage", "publish")
    watch = channel_url(server.ws, "stage", "watch")
    async with contextlib.AsyncExitStack() as stack:
        watchers = []
        for output, dtype in keys:
            query = f"?rig=ict&output={output}&dtype={dtype}"
            ws = await stack.enter_async_context(session(watch + query, None, "viewer-t"))
            watchers.append(asyncio.create_task(drain(ws)))
        hello = Hello(rig="ict", output="weights")
        ws = await stack.enter_async_context(session(url, hello, "publisher-t"))
        messages = frames(points)
        if calibrates:  # a frame, then calibrates between frames: each refit re-bases every key
            messages = [messages[0], *[encode(Calibrate(points=points))] * 3]
        async with Meter(server.process.pid) as meter:
            sent, _ = await flood(ws, messages, seconds, 1000.0)
    results = await asyncio.gather(*watchers)
    what = "calibrates and frames" if calibrates else "frames"
    return meter.line(f"publisher token flooding {what}, viewer on {len(keys)} key(s)",
                      f"; {sent} messages sent, {sum(results)} results watched")  # fmt: skip


async def watchers_scenario(server: Server, count: int) -> str:
    pid = server.process.pid
    before = rss_mb(pid)
    watch = channel_url(server.ws, "stage", "watch") + "?rig=ict&output=vertices&dtype=f32"
    async with contextlib.AsyncExitStack() as stack:
        for _ in range(count):
            await stack.enter_async_context(session(watch, None, "viewer-t"))
        held = rss_mb(pid)
    return (
        f"viewer token: {count} watchers held (the token's quota): RSS {before:.1f} -> "
        f"{held:.1f} MB ({(held - before) * 1024 / count:.0f} kB each)"
    )


async def glb_scenario(server: Server, seconds: float, concurrency: int = 4) -> str:
    headers = {"Authorization": "Bearer viewer-t"}
    done = 0
    size = 0

    async def loop(client: httpx.AsyncClient, end: float) -> None:
        nonlocal done, size
        while time.monotonic() < end:
            response = await client.get("/v1/rigs/ict/model.glb", headers=headers)
            response.raise_for_status()
            done += 1
            size = len(response.content)

    async with httpx.AsyncClient(base_url=server.base, timeout=60) as client:
        async with Meter(server.process.pid) as first:  # the first request builds it
            await client.get("/v1/rigs/ict/model.glb", headers=headers)
        print(first.line("viewer token: the first GET model.glb (builds and caches it)"))
        async with Meter(server.process.pid) as meter:
            end = time.monotonic() + seconds
            await asyncio.gather(*(loop(client, end) for _ in range(concurrency)))
    return meter.line(f"viewer token: GET model.glb x {concurrency} concurrent",
                      f"; {done} answered ({size / 1e6:.1f} MB each)")  # fmt: skip


async def performer_scenario(
    server: Server, capture: dict, seconds: float, concurrency: int
) -> str:
    headers = {"Authorization": "Bearer performer-t"}
    statuses: dict[int, int] = {}

    async def loop(client: httpx.AsyncClient, end: float, i: int) -> None:
        while time.monotonic() < end:
            response = await client.put(f"/v1/rigs/ict/performer/p{i}", json=capture,
                                        headers=headers)  # fmt: skip
            statuses[response.status_code] = statuses.get(response.status_code, 0) + 1

    async with (
        httpx.AsyncClient(base_url=server.base, timeout=300) as client,
        Meter(server.process.pid) as meter,
    ):
        end = time.monotonic() + seconds
        await asyncio.gather(*(loop(client, end, i) for i in range(concurrency)))
    return meter.line(f"performer token: captures refitted, {concurrency} at once",
                      f"; answers {dict(sorted(statuses.items()))}")  # fmt: skip


def ict_rig(directory: Path) -> tuple[Rig, np.ndarray, dict]:
    example_set = ict_example_set(ICT)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # exact interpolation: the engine's own benchmarks
        rig = fit(example_set)
    rig.save(directory / "ict.rig")
    rng = np.random.default_rng(0)
    points = rig.source_neutral + rng.normal(scale=0.02, size=rig.source_neutral.shape)
    # A performer capture in ICT's own points (its feature points are the layout's 20).
    capture = {"layout": "mediapipe_face_mesh", "points": {
        ("neutral" if i == 0 else name): example_set.source_points[i].tolist()
        for i, name in enumerate(example_set.names)}}  # fmt: skip
    return rig, points.astype(np.float32), capture


async def run(args: argparse.Namespace, rigs: Path, points, capture) -> None:
    seconds = args.seconds
    server = Server(rigs)
    try:
        async with Meter(server.process.pid) as floor:  # the same run's floor
            await asyncio.sleep(seconds)
        print(floor.line("floor: the server idle, nothing connected"), flush=True)
        print(await frames_scenario(server, points, seconds, "weights", 1), flush=True)
        print(await frames_scenario(server, points, seconds, "vertices", 1), flush=True)
        print(await frames_scenario(server, points, seconds, "weights", 10), flush=True)
        print(await frames_scenario(server, points, seconds, "vertices", 10), flush=True)
        print(await calibrate_scenario(server, points, seconds, 4), flush=True)
        print(await idle_sessions(server, 100), flush=True)
        print(await channel_scenario(server, points, seconds, [("weights", "f32")]), flush=True)
        keys = [(o, d) for o in ("weights", "vertices", "points") for d in ("f16", "f32", "f64")
                if not (o == "points" and d == "f16")]  # fmt: skip
        print(await channel_scenario(server, points, seconds, keys), flush=True)
        print(await channel_scenario(server, points, seconds, keys, calibrates=True), flush=True)
        print(await watchers_scenario(server, 100), flush=True)
        print(await glb_scenario(server, seconds), flush=True)
        print(await performer_scenario(server, capture, seconds * 2, 1), flush=True)
        print(await performer_scenario(server, capture, seconds * 2, 6), flush=True)
    finally:
        server.stop()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=8.0)
    args = parser.parse_args(argv)
    print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.node()}, "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="facecast-token-costs-") as tmp:
        rigs = Path(tmp)
        rig, points, capture = ict_rig(rigs)
        print(f"rig: ICT, K = {rig.num_points}, M = {rig.num_examples}, V = {rig.num_vertices}")
        asyncio.run(run(args, rigs, points, capture))


if __name__ == "__main__":
    main()
