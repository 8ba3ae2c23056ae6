"""``facecast bench transport``'s client process: the bare clients and their measurements.

Runs in a process of its own (``measure`` starts one per task: a JSON task on stdin, its
JSON figures on stdout), never in a server's, so the load generator and the servers do
not share an interpreter. Measures and returns figures; it judges nothing. The rig
engine (~1.3 s to import) loads only for the blend floor: every process's start-up lies
within the wall time its servers' CPU is divided by.
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time
from typing import Any, Protocol

import msgpack
import numpy as np
import uvloop
from websockets.asyncio.client import ClientConnection, connect
from websockets.typing import Subprotocol

from facecast.cli.loadgen import run_load
from facecast.client.connection import connect as connect_session
from facecast.client.latency import latency_stats
from facecast.client.urls import stream_url
from facecast.protocol import SUBPROTOCOL, Frame, Hello, Ready, Result, decode_server, encode

__all__ = ["FLOOR_BATCH", "PIPELINE_WINDOW", "ROUNDS", "WARMUP", "measure"]

#: Messages in flight in the pipelined throughput test.
PIPELINE_WINDOW = 32
#: Distinct pre-encoded frames the bare facecast client cycles through (seq 0..N-1).
_FRAME_CYCLE = 1024
#: Slices each server's measurement is cut into, taken in turn (``_interleaved_figures``).
ROUNDS = 10
#: Messages sent and discarded before timing (connection and JIT-less warm-up).
WARMUP = 50
#: Frames per bare blend batch (the batcher's batches under load are of this order).
FLOOR_BATCH = 16


class _Target(Protocol):
    """A server driven by the bare client: opened once, then round trips and pipelining."""

    dropped: int

    async def open(self, stack: contextlib.AsyncExitStack) -> None: ...
    async def rtt(self) -> float: ...
    async def pipelined(self, seconds: float) -> tuple[int, float]: ...


class _Echo:
    """A bare client of an echo server: sends pre-encoded messages, reads the replies."""

    ws: ClientConnection

    def __init__(self, url: str, message: bytes) -> None:
        self.url, self.message = url, message
        self.dropped = 0  # an echo answers every message

    async def open(self, stack: contextlib.AsyncExitStack) -> None:
        self.ws = await stack.enter_async_context(
            connect(self.url, compression=None, max_size=1 << 24)
        )
        for _ in range(WARMUP):
            await self.rtt()

    async def rtt(self) -> float:
        start = time.perf_counter()
        await self.ws.send(self.message)
        await self.ws.recv()
        return time.perf_counter() - start

    async def pipelined(self, seconds: float) -> tuple[int, float]:
        """Results received in ``seconds`` with PIPELINE_WINDOW in flight, and the time."""
        ws, message = self.ws, self.message
        for _ in range(PIPELINE_WINDOW):
            await ws.send(message)
        count = 0
        start = time.perf_counter()
        end = start + seconds
        while time.perf_counter() < end:
            await ws.recv()  # echo keeps order: one reply frees one slot
            count += 1
            await ws.send(message)
        elapsed = time.perf_counter() - start
        for _ in range(PIPELINE_WINDOW):
            await ws.recv()
        return count, elapsed


#: A result's first bytes and its last key, as the server lays them out (§5.2.2).
_RESULT_START = b"\x87\xa1v\x01\xa4type\xa6result"
_DROPPED_KEY = b"\xa7dropped"


def _dropped(reply: bytes) -> int:
    """A result's ``dropped``, read off its last bytes; RuntimeError unless a result.

    The load generator shares the machine with the server: a full msgpack decode of each
    reply would cost it more than the echo clients pay for theirs (nothing). Anything
    not laid out as the server lays results out is decoded in full.
    """
    at = reply.rfind(_DROPPED_KEY)
    if reply.startswith(_RESULT_START) and at > 0:
        tail = reply[at + len(_DROPPED_KEY) :]
        if len(tail) == 1 and tail[0] < 0x80:
            return tail[0]
        if len(tail) > 1 and tail[0] in _UINTS and len(tail) == 1 + _UINTS[tail[0]]:
            return int.from_bytes(tail[1:], "big")
    message = decode_server(reply)
    if not isinstance(message, Result):
        raise RuntimeError(f"facecast answered a frame with {message!r}")
    return int(msgpack.unpackb(reply)["dropped"])


_UINTS = {0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8}


class _Facecast:
    """Facecast's path driven like the echo servers: bare websockets, pre-encoded frames.

    Each reply's ``dropped`` is read off its last bytes (`_dropped`: results are counted,
    ``dropped`` frees the window slots of superseded frames); the first and last results
    are decoded and validated in full.
    """

    ws: ClientConnection
    reply: bytes

    def __init__(self, url: str, rig: str, points: np.ndarray) -> None:
        self.url, self.rig = url, rig
        self.frames = [encode(Frame(seq=i, ts=i / 60, points=points)) for i in range(_FRAME_CYCLE)]
        self.i = 0
        self.dropped = 0  # superseded in the pipelined phases (newest-only, not answered)

    async def open(self, stack: contextlib.AsyncExitStack) -> None:
        self.ws = await stack.enter_async_context(
            connect(stream_url(self.url), subprotocols=[Subprotocol(SUBPROTOCOL)], compression=None,
                    max_size=1 << 24)
        )  # fmt: skip
        await self.ws.send(encode(Hello(rig=self.rig)))
        while not isinstance(decode_server(await self.ws.recv(decode=False)), Ready):
            pass
        for _ in range(WARMUP):
            await self.rtt()
        self._result(self.reply)

    def _result(self, reply: bytes) -> Result:
        """The reply decoded and validated in full; RuntimeError unless it is a result."""
        message = decode_server(reply)
        if not isinstance(message, Result):
            raise RuntimeError(f"facecast answered a frame with {message!r}")
        return message

    def _next(self) -> bytes:
        frame = self.frames[self.i % _FRAME_CYCLE]
        self.i += 1
        return frame

    async def rtt(self) -> float:
        start = time.perf_counter()
        await self.ws.send(self._next())
        self.reply = await self.ws.recv(decode=False)
        elapsed = time.perf_counter() - start
        _dropped(self.reply)  # raises unless a result
        return elapsed

    async def pipelined(self, seconds: float) -> tuple[int, float]:
        """Results received in ``seconds`` with PIPELINE_WINDOW frames in flight.

        A result frees its own slot and those of the frames it reports as dropped.
        """
        ws = self.ws
        reply = self.reply
        dropped_before = dropped = _dropped(reply)
        sent = results = 0
        start = time.perf_counter()
        end = start + seconds
        while time.perf_counter() < end:
            while sent - results - (dropped - dropped_before) < PIPELINE_WINDOW:
                await ws.send(self._next())
                sent += 1
            reply = await ws.recv(decode=False)
            results += 1
            dropped = _dropped(reply)
        elapsed = time.perf_counter() - start
        count = results
        # Drain what is still in flight so the next round starts from an idle session.
        while sent - results - (dropped - dropped_before) > 0:
            reply = await ws.recv(decode=False)
            results += 1
            dropped = _dropped(reply)
        self.reply = reply
        self.dropped += dropped - dropped_before
        last = self._result(reply)
        if last.weights is None:
            raise RuntimeError(f"facecast's last reply is not a weights result: {last!r}")
        return count, elapsed


async def _interleaved_figures(targets: dict[str, _Target], seconds: float) -> dict[str, Any]:
    """Each target's RTTs and pipelined rate, measured in alternating short rounds.

    Every target gets ``seconds / 2`` of round trips and as much of pipelining, cut into
    ``ROUNDS`` slices taken in turn, so that whatever else the machine does meanwhile
    weighs on baselines and facecast alike (one long block each would not).
    """
    rtts: dict[str, list[float]] = {name: [] for name in targets}
    counts = dict.fromkeys(targets, 0)
    times = dict.fromkeys(targets, 0.0)
    piece = seconds / 2 / ROUNDS
    async with contextlib.AsyncExitStack() as stack:
        for target in targets.values():
            await target.open(stack)
        for _ in range(ROUNDS):
            for name, target in targets.items():
                end = time.perf_counter() + piece
                while time.perf_counter() < end:
                    rtts[name].append(await target.rtt())
            for name, target in targets.items():
                count, elapsed = await target.pipelined(piece)
                counts[name] += count
                times[name] += elapsed
    return {
        name: {
            "rtt_ms": latency_stats(rtts[name]).to_dict(),
            "throughput_msgs_per_s": counts[name] / times[name],
            "pipelined_dropped": targets[name].dropped,
            "messages": len(rtts[name]) + counts[name],
        }
        for name in targets
    }


async def _facecast_figures(
    url: str, rig: str, points: np.ndarray, seconds: float
) -> dict[str, Any]:
    async with connect_session(url, rig) as session:
        for _ in range(WARMUP):
            await session.clone(points)
        rtts: list[float] = []
        end = time.perf_counter() + seconds / 2
        while time.perf_counter() < end:
            start = time.perf_counter()
            await session.clone(points)
            rtts.append(time.perf_counter() - start)
        # Pipelined: the server keeps only the newest pending frame, so a deep window
        # measures how many results per second it can produce; superseded frames are
        # counted, not waited for (the latency tracker forgets them when a later
        # result arrives).
        dropped_before = session.dropped
        for _ in range(PIPELINE_WINDOW):
            await session.send(points)
        count = 0
        start = time.perf_counter()
        end = start + seconds / 2
        while time.perf_counter() < end:
            try:
                item = await session.receive(errors="return", timeout=1.0)
            except TimeoutError:
                session.latency.forget()
                item = None
            if isinstance(item, Result):
                count += 1
            while session.latency.in_flight < PIPELINE_WINDOW:
                await session.send(points)
        elapsed = time.perf_counter() - start
        dropped = session.dropped - dropped_before
    return {
        "rtt_ms": latency_stats(rtts).to_dict(),
        "throughput_msgs_per_s": count / elapsed,
        "pipelined_dropped": dropped,
    }


async def _client_task(spec: dict[str, Any]) -> dict[str, Any]:
    kind = spec["kind"]
    if kind == "interleaved":
        message = bytes.fromhex(spec["message"])
        targets: dict[str, _Target] = {
            name: _Echo(url, message) for name, url in spec["echo_urls"].items()
        }
        points = np.asarray(spec["points"], dtype=np.float32)
        targets["facecast"] = _Facecast(spec["url"], spec["rig"], points)
        return await _interleaved_figures(targets, spec["seconds"])
    if kind == "blend-floor":
        return _blend_floor(spec["rig_path"])
    if kind == "facecast-library":
        points = np.asarray(spec["points"], dtype=np.float32)
        return await _facecast_figures(spec["url"], spec["rig"], points, spec["seconds"])
    if kind == "load":
        report = await run_load(
            spec["url"],
            spec["rig"],
            clients=spec["clients"],
            fps=spec["fps"],
            duration=spec["seconds"],
            neutral=np.asarray(spec["neutral"], dtype=np.float64),
            output=spec["output"],
            dtype=spec["dtype"],
        )
        return report.to_dict()
    raise ValueError(f"unknown client task {kind!r}")


def _client_main() -> None:
    """Client subprocess entry point: a JSON task on stdin, its JSON figures on stdout."""
    spec = json.loads(sys.stdin.read())
    started = time.process_time()
    figures = uvloop.run(_client_task(spec))
    figures["client_cpu_seconds"] = time.process_time() - started
    sys.stdout.write(json.dumps(figures) + "\n")


def measure(spec: dict[str, Any], timeout: float) -> dict[str, Any]:
    """Run one client task in a fresh process (never in the servers' processes)."""
    code = "from facecast.cli.bench.transport_client import _client_main; _client_main()"
    done = subprocess.run(
        [sys.executable, "-c", code],
        input=json.dumps(spec),
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"client process failed ({done.returncode}):\n{done.stderr[-2000:]}")
    figures: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return figures


def _blend_floor(rig_path: str) -> dict[str, float]:
    """Per-frame µs of a bare dense blend ``weights @ basis`` of a rig: alone and batched.

    Runs in a client process, whose BLAS has the one thread the servers' have (``facecast``
    limits it in the environment, too late for a process that imported numpy already).
    """
    from facecast.rig import load_rig  # start-up time: see the module's docstring
    from facecast.rig.evaluation.evaluate import median_call_seconds

    rig = load_rig(rig_path)
    basis = np.ascontiguousarray(rig.blend_basis)
    rng = np.random.default_rng(0)
    one = rng.random((1, rig.num_examples)).astype(np.float32)
    batch = rng.random((FLOOR_BATCH, rig.num_examples)).astype(np.float32)
    out_one = np.empty((1, basis.shape[1]), np.float32)
    out_batch = np.empty((FLOOR_BATCH, basis.shape[1]), np.float32)
    single = median_call_seconds(lambda: np.matmul(one, basis, out=out_one), repeat=5)
    batched = median_call_seconds(lambda: np.matmul(batch, basis, out=out_batch), repeat=5)
    return {"single_us": single * 1e6, f"batch{FLOOR_BATCH}_us": batched / FLOOR_BATCH * 1e6}
