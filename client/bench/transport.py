"""``facecast bench transport``: facecast's WebSocket path beside bare echo servers, in one run.

Every server runs in its own subprocess on a free 127.0.0.1 port and is driven from a
separate client process, so the load generator never starves a server; it measures and
prints figures with their goals, it asserts nothing.

Servers: (a) a bare ``websockets`` echo server on uvloop, (b) a bare FastAPI/uvicorn
WebSocket echo endpoint, (c) facecast itself (``facecast.server.runner.serve``, what
``facecast serve`` runs, with its per-connection rate limit raised out of the way) with
the demo rig for weights and the ICT rig (if the data is present, else the demo rig)
for vertices. Echo messages are the bytes of a real facecast ``frame`` of the demo rig,
so every path carries messages of the same size.

The servers are compared with the same bare client: pre-encoded messages, one msgpack
unpack per facecast reply (to count results and drops), nothing else. All three run at
once and are measured in alternating rounds from one client process, so a busy moment
of the machine weighs on the baselines and facecast alike. The facecast
client library's own round trip (encode, full decode and validation, its reader task)
is measured too and printed apart, as client cost, not server cost.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

# At module level: FastAPI resolves the echo endpoint's (string) annotations here.
from fastapi import WebSocket, WebSocketDisconnect

__all__ = ["run"]

#: Goals (issue "Streaming service"): facecast weights RTT p50 within 1.5x of the faster
#: bare echo, pipelined throughput at least half of it, and every vertices-mode
#: connection sustaining the target rate (1% slack).
GOAL_RTT_RATIO = 1.5
GOAL_THROUGHPUT_RATIO = 0.5
TARGET_FPS = 60.0
FPS_SLACK = 0.01
#: Messages in flight in the pipelined throughput test.
PIPELINE_WINDOW = 32
#: Facecast's rate limit in the benchmark: far above any rate reached here, so the
#: pipelined phase measures the path, not the limit (``max_fps`` defaults to 240).
BENCH_MAX_FPS = 1e6
#: Distinct pre-encoded frames the bare facecast client cycles through (seq 0..N-1).
_FRAME_CYCLE = 1024
#: Slices each server's measurement is cut into, taken in turn (``_interleaved_figures``).
ROUNDS = 10
#: Messages sent and discarded before timing (connection and JIT-less warm-up).
WARMUP = 50
_SERVER_START_TIMEOUT = 60.0
_BASELINES = ("websockets", "fastapi")


# -- servers (each runs in its own subprocess) -------------------------------------------


def _serve(kind: str, port: int, rigs_dir: str | None = None) -> None:
    """Subprocess entry point: serve ``kind`` on 127.0.0.1:``port`` until killed."""
    if kind == "websockets":
        import uvloop
        from websockets.asyncio.server import serve

        async def echo(ws) -> None:
            async for message in ws:
                await ws.send(message)

        async def main() -> None:
            async with serve(echo, "127.0.0.1", port, compression=None, max_size=1 << 24):
                await asyncio.Future()

        uvloop.run(main())
    elif kind == "fastapi":
        import uvicorn
        from fastapi import FastAPI

        app = FastAPI()

        @app.websocket("/echo")
        async def echo_endpoint(websocket: WebSocket) -> None:
            await websocket.accept()
            with contextlib.suppress(WebSocketDisconnect):
                while True:
                    await websocket.send_bytes(await websocket.receive_bytes())

        uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning", loop="uvloop")
    elif kind == "facecast":
        from facecast.server.runner import serve as serve_facecast
        from facecast.server.settings import Settings

        settings = Settings(
            host="127.0.0.1",
            port=port,
            rigs_dir=Path(rigs_dir or "."),
            # A benchmark measures the path, not the per-client rate limit.
            max_fps=BENCH_MAX_FPS,
            rate_burst=1_000_000,
            log_level="warning",
            access_log=False,
        )
        serve_facecast(settings)
    else:  # pragma: no cover - internal
        raise SystemExit(f"unknown server kind {kind!r}")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextlib.contextmanager
def _server(kind: str, rigs_dir: Path | None, log_dir: Path) -> Iterator[int]:
    """Start server ``kind`` in a subprocess; yield its port once it accepts connections."""
    port = _free_port()
    log = (log_dir / f"{kind}.log").open("wb")
    code = (
        "from facecast.client.bench.transport import _serve; "
        f"_serve({kind!r}, {port}, {str(rigs_dir) if rigs_dir else None!r})"
    )
    process = subprocess.Popen(
        [sys.executable, "-c", code], stdout=log, stderr=subprocess.STDOUT, cwd=log_dir
    )
    try:
        deadline = time.monotonic() + _SERVER_START_TIMEOUT
        while True:
            if process.poll() is not None:
                log.flush()
                tail = (log_dir / f"{kind}.log").read_text(errors="replace")[-2000:]
                raise RuntimeError(f"{kind} server exited with {process.returncode}:\n{tail}")
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                    break
            except OSError:
                if time.monotonic() > deadline:
                    raise TimeoutError(
                        f"{kind} server did not listen within {_SERVER_START_TIMEOUT:g} s"
                    ) from None
                time.sleep(0.05)
        yield port
    finally:
        process.terminate()
        try:
            process.wait(10.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        log.close()


# -- client measurements (run in the client subprocess) ----------------------------------


class _Echo:
    """A bare client of an echo server: sends pre-encoded messages, reads the replies."""

    def __init__(self, url: str, message: bytes) -> None:
        self.url, self.message = url, message
        self.dropped = 0  # an echo answers every message

    async def open(self, stack: contextlib.AsyncExitStack) -> None:
        from websockets.asyncio.client import connect

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


class _Facecast:
    """Facecast's path driven like the echo servers: bare websockets, pre-encoded frames.

    Each reply is msgpack-unpacked once (results are counted, ``dropped`` read to free
    the window slots of superseded frames); the first and last results are decoded and
    validated in full.
    """

    def __init__(self, url: str, rig: str, points: np.ndarray) -> None:
        from facecast.protocol import Frame, encode

        self.url, self.rig = url, rig
        self.frames = [encode(Frame(seq=i, ts=i / 60, points=points)) for i in range(_FRAME_CYCLE)]
        self.i = 0
        self.dropped = 0  # superseded in the pipelined phases (newest-only, not answered)

    async def open(self, stack: contextlib.AsyncExitStack) -> None:
        from websockets.asyncio.client import connect

        from facecast.client.urls import stream_url
        from facecast.protocol import SUBPROTOCOL, Hello, Ready, decode_server, encode

        self.ws = await stack.enter_async_context(
            connect(stream_url(self.url), subprotocols=[SUBPROTOCOL], compression=None,
                    max_size=1 << 24)
        )  # fmt: skip
        await self.ws.send(encode(Hello(rig=self.rig)))
        while not isinstance(decode_server(await self.ws.recv()), Ready):
            pass
        for _ in range(WARMUP):
            await self.rtt()
        self._result(self.reply)

    def _result(self, reply: bytes) -> Any:
        """The reply decoded and validated in full; RuntimeError unless it is a result."""
        from facecast.protocol import Result, decode_server

        message = decode_server(reply)
        if not isinstance(message, Result):
            raise RuntimeError(f"facecast answered a frame with {message!r}")
        return message

    def _next(self) -> bytes:
        frame = self.frames[self.i % _FRAME_CYCLE]
        self.i += 1
        return frame

    async def rtt(self) -> float:
        import msgpack

        start = time.perf_counter()
        await self.ws.send(self._next())
        self.reply = await self.ws.recv()
        elapsed = time.perf_counter() - start
        if msgpack.unpackb(self.reply)["type"] != "result":
            self._result(self.reply)
        return elapsed

    async def pipelined(self, seconds: float) -> tuple[int, float]:
        """Results received in ``seconds`` with PIPELINE_WINDOW frames in flight.

        A result frees its own slot and those of the frames it reports as dropped.
        """
        import msgpack

        ws = self.ws
        reply = self.reply
        dropped_before = dropped = msgpack.unpackb(reply)["dropped"]
        sent = results = 0
        start = time.perf_counter()
        end = start + seconds
        while time.perf_counter() < end:
            while sent - results - (dropped - dropped_before) < PIPELINE_WINDOW:
                await ws.send(self._next())
                sent += 1
            reply = await ws.recv()
            message = msgpack.unpackb(reply)
            if message["type"] != "result":
                self._result(reply)
            results += 1
            dropped = message["dropped"]
        elapsed = time.perf_counter() - start
        count = results
        # Drain what is still in flight so the next round starts from an idle session.
        while sent - results - (dropped - dropped_before) > 0:
            reply = await ws.recv()
            results += 1
            dropped = msgpack.unpackb(reply)["dropped"]
        self.reply = reply
        self.dropped += dropped - dropped_before
        last = self._result(reply)
        if last.weights is None:
            raise RuntimeError(f"facecast's last reply is not a weights result: {last!r}")
        return count, elapsed


async def _interleaved_figures(targets: dict[str, Any], seconds: float) -> dict[str, Any]:
    """Each target's RTTs and pipelined rate, measured in alternating short rounds.

    Every target gets ``seconds / 2`` of round trips and as much of pipelining, cut into
    ``ROUNDS`` slices taken in turn, so that whatever else the machine does meanwhile
    weighs on baselines and facecast alike (one long block each would not).
    """
    from facecast.client.latency import latency_stats

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
        }
        for name in targets
    }


async def _facecast_figures(
    url: str, rig: str, points: np.ndarray, seconds: float
) -> dict[str, Any]:
    from facecast.client.connection import connect
    from facecast.client.latency import latency_stats
    from facecast.protocol import Result

    async with connect(url, rig) as session:
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
        targets: dict[str, Any] = {
            name: _Echo(url, message) for name, url in spec["echo_urls"].items()
        }
        points = np.asarray(spec["points"], dtype=np.float32)
        targets["facecast"] = _Facecast(spec["url"], spec["rig"], points)
        return await _interleaved_figures(targets, spec["seconds"])
    if kind == "facecast-library":
        points = np.asarray(spec["points"], dtype=np.float32)
        return await _facecast_figures(spec["url"], spec["rig"], points, spec["seconds"])
    if kind == "load":
        from facecast.client.loadgen import run_load

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
    import uvloop

    spec = json.loads(sys.stdin.read())
    figures = uvloop.run(_client_task(spec))
    sys.stdout.write(json.dumps(figures) + "\n")


def _measure(spec: dict[str, Any], timeout: float) -> dict[str, Any]:
    """Run one client task in a fresh process (never in the servers' processes)."""
    code = "from facecast.client.bench.transport import _client_main; _client_main()"
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
    return json.loads(done.stdout.strip().splitlines()[-1])


# -- the run -------------------------------------------------------------------------------


def _rigs(rigs_dir: Path) -> tuple[np.ndarray, np.ndarray, str]:
    """Fit and store the demo rig (and ICT's, when its data is there).

    Returns the demo rig's source neutral (K, 3), the vertices rig's neutral, and the
    vertices rig's id.
    """
    from facecast.rig import fit
    from facecast.rig.demo import demo_example_set

    demo = fit(demo_example_set())
    demo.save(rigs_dir / "demo.rig")
    vertices_rig, vertices_id = demo, "demo"
    try:
        from facecast.rig.sources.ict import ict_example_set, locate_ict

        archive = locate_ict()
    except ImportError:
        archive = None
    if archive is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the exact rig: its noise gain is beside the point
            vertices_rig, vertices_id = fit(ict_example_set(archive)), "ict"
        vertices_rig.save(rigs_dir / "ict.rig")
    return (
        np.asarray(demo.source_neutral, dtype=np.float32),
        np.asarray(vertices_rig.source_neutral, dtype=np.float64),
        vertices_id,
    )


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else a / b


def _status(ok: bool | None) -> str:
    return "n/a" if ok is None else ("PASS" if ok else "FAIL")


def run(args: argparse.Namespace) -> int:
    """Run the benchmark (``args.duration`` s per phase, ``args.clients`` vertices clients)."""
    from facecast.protocol import Frame, encode

    duration = float(getattr(args, "duration", None) or 10.0)
    clients = int(getattr(args, "clients", None) or 20)
    if not 0 < duration <= 3600:
        raise ValueError(f"--duration must be in (0, 3600] s, got {duration}")
    if not 1 <= clients <= 1000:
        raise ValueError(f"--clients must be in 1..1000, got {clients}")
    timeout = 4 * duration + 120.0
    say = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731

    with tempfile.TemporaryDirectory(prefix="facecast-bench-") as tmp:
        tmp_path = Path(tmp)
        rigs_dir = tmp_path / "rigs"
        rigs_dir.mkdir()
        say("bench transport: fitting rigs ...")
        neutral, vertices_neutral, vertices_id = _rigs(rigs_dir)
        message = encode(Frame(seq=1, ts=0.0, points=neutral))
        with contextlib.ExitStack() as servers:
            ports = {
                kind: servers.enter_context(_server(kind, None, tmp_path)) for kind in _BASELINES
            }
            port = servers.enter_context(_server("facecast", rigs_dir, tmp_path))
            base = f"http://127.0.0.1:{port}"
            say(
                f"bench transport: {', '.join(_BASELINES)} echo and facecast weights "
                f"({duration:g} s each, in {ROUNDS} alternating rounds; facecast's max_fps "
                f"raised to {BENCH_MAX_FPS:g}) ..."
            )
            spec = {"url": base, "rig": "demo", "points": neutral.tolist(), "seconds": duration}
            echo_urls = {
                kind: f"ws://127.0.0.1:{ports[kind]}{'/echo' if kind == 'fastapi' else '/'}"
                for kind in _BASELINES
            }
            results = _measure(
                {**spec, "kind": "interleaved", "message": message.hex(), "echo_urls": echo_urls},
                timeout * (len(_BASELINES) + 1),
            )
            say(f"bench transport: facecast weights, library client ({duration:g} s) ...")
            library = _measure({**spec, "kind": "facecast-library"}, timeout)
            say(
                f"bench transport: facecast vertices, {vertices_id} rig, {clients} clients x "
                f"{TARGET_FPS:g} fps f16 ({duration:g} s) ..."
            )
            load = _measure(
                {
                    "kind": "load",
                    "url": base,
                    "rig": vertices_id,
                    "clients": clients,
                    "fps": TARGET_FPS,
                    "seconds": duration,
                    "neutral": vertices_neutral.tolist(),
                    "output": "vertices",
                    "dtype": "f16",
                },
                timeout,
            )

    figures = _figures(results, load, duration, clients, len(message), vertices_id)
    figures["library_client"] = library
    print(_format(figures))
    if getattr(args, "json", None):
        Path(args.json).write_text(json.dumps(figures, indent=2), encoding="utf-8")
    return 0


def _figures(
    results: dict[str, dict[str, Any]],
    load: dict[str, Any],
    duration: float,
    clients: int,
    frame_bytes: int,
    vertices_id: str,
) -> dict[str, Any]:
    p50 = {name: r["rtt_ms"]["p50_ms"] for name, r in results.items()}
    tput = {name: r["throughput_msgs_per_s"] for name, r in results.items()}
    rtt_base = min(_BASELINES, key=lambda n: p50[n] if p50[n] is not None else float("inf"))
    tput_base = max(_BASELINES, key=lambda n: tput[n])
    rtt_ratio = _ratio(p50["facecast"], p50[rtt_base])
    tput_ratio = _ratio(tput["facecast"], tput[tput_base])
    floor = TARGET_FPS * (1 - FPS_SLACK)
    per_client = load["per_client_fps"]
    vertices_pass = bool(per_client) and min(per_client) >= floor and not load["errors"]
    return {
        "duration": duration,
        "clients": clients,
        "frame_bytes": frame_bytes,
        "pipeline_window": PIPELINE_WINDOW,
        "servers": results,
        "rtt_p50_ms": p50,
        "throughput_msgs_per_s": tput,
        "baseline": {"rtt": rtt_base, "throughput": tput_base},
        "ratios": {"rtt_p50": rtt_ratio, "throughput": tput_ratio},
        "goals": {
            "rtt_p50_ratio_max": GOAL_RTT_RATIO,
            "throughput_ratio_min": GOAL_THROUGHPUT_RATIO,
            "rtt_pass": None if rtt_ratio is None else rtt_ratio <= GOAL_RTT_RATIO,
            "throughput_pass": None if tput_ratio is None else tput_ratio >= GOAL_THROUGHPUT_RATIO,
            "vertices_fps_min": floor,
            "vertices_pass": vertices_pass,
        },
        "vertices": {
            "rig": vertices_id,
            "target_fps": TARGET_FPS,
            "min_client_fps": load["min_client_fps"],
            "per_client_fps": per_client,
            "mb_per_s": load["payload_mb_per_s"],
            "latency_ms": load["latency_ms"],
            "received": load["received"],
            "sent": load["sent"],
            "dropped": load["dropped"],
            "errors": load["errors"],
            "pass": vertices_pass,
        },
    }


def _format(f: dict[str, Any]) -> str:
    def num(value: float | None, fmt: str) -> str:
        return "-" if value is None else format(value, fmt)

    lines = [
        f"transport benchmark: frame of {f['frame_bytes']} bytes, "
        f"{f['duration']:g} s per phase, window {f['pipeline_window']}",
        f"  {'server':<12}{'RTT p50 (ms)':>14}{'pipelined (msg/s)':>20}",
    ]
    for name in (*_BASELINES, "facecast"):
        lines.append(
            f"  {name:<12}{num(f['rtt_p50_ms'][name], '.3f'):>14}"
            f"{num(f['throughput_msgs_per_s'][name], '.0f'):>20}"
        )
    library = f.get("library_client")
    if library is not None:
        lines.append(
            f"  {'(library)':<12}{num(library['rtt_ms']['p50_ms'], '.3f'):>14}"
            f"{num(library['throughput_msgs_per_s'], '.0f'):>20}"
            "   facecast through facecast.client (client cost included; not compared)"
        )
    dropped = f["servers"]["facecast"].get("pipelined_dropped", 0)
    lines.append(
        f"  facecast: rate limit raised to {BENCH_MAX_FPS:g} fps; pipelined frames "
        f"superseded (newest-only, not answered): {dropped}"
    )
    goals, ratios, base = f["goals"], f["ratios"], f["baseline"]
    lines += [
        f"  RTT p50: facecast / {base['rtt']} = {num(ratios['rtt_p50'], '.2f')}x "
        f"(goal <= {goals['rtt_p50_ratio_max']}x)  {_status(goals['rtt_pass'])}",
        f"  throughput: facecast / {base['throughput']} = {num(ratios['throughput'], '.2f')}x "
        f"(goal >= {goals['throughput_ratio_min']}x)  {_status(goals['throughput_pass'])}",
    ]
    v = f["vertices"]
    lat = v["latency_ms"]
    lines.append(
        f"  vertices f16, {v['rig']} rig, {f['clients']} clients x {v['target_fps']:g} fps: "
        f"min {v['min_client_fps']:.1f} fps/client, {v['mb_per_s']:.1f} MB/s, "
        f"p50 {num(lat['p50_ms'], '.2f')} ms p99 {num(lat['p99_ms'], '.2f')} ms, "
        f"dropped {v['dropped']}, errors {v['errors'] or 'none'}  "
        f"{_status(goals['vertices_pass'])} (goal >= {goals['vertices_fps_min']:.1f} fps each)"
    )
    return "\n".join(lines)
