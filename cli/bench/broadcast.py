"""``facecast bench broadcast``: how many viewers one server process serves at 60 fps.

Starts real ``facecast serve`` processes on 127.0.0.1 (and a redis-server when needed),
publishes the demo performance at 60 fps (weights mode) and ramps viewers held by
separate client processes, so the load generator does not starve the server. It
measures from outside only: it never imports the server. Beside facecast's ramp, in the
same run, stands its floor: a bare ``websockets`` server that broadcasts (``broadcast()``)
a result of the same bytes to the same viewers per published frame. Both hold each
step's viewers and are measured in turn, each with only its own publisher running;
facecast's server CPU per result is reported as a ratio to the floor's at each step.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from facecast.client.channel import FramePublisher, channel_url
from facecast.protocol import Hello, Ready, encode
from facecast.rig import Rig, fit
from facecast.rig.demo import demo_animation, demo_example_set

from .broadcast_viewers import RIGS, Clients
from .harness import (
    RedisServer,
    ServerProcess,
    answers_ok,
    facecast_serve,
    python_server,
    start_redis,
    wait_until,
)
from .measure import cpu_seconds, stage_snapshot

#: Viewer counts tried, in order; the ramp stops at the first step over the goal.
STEPS = (250, 500, 750, 1000, 1250, 1500, 2000)
GOAL_P99_MS = 50.0
GOAL_VIEWERS = 1000
FPS = 60.0
#: A step fails too when viewers get fewer than this share of the frames published.
MIN_DELIVERY = 0.9
#: Goal: facecast's server CPU per delivered result at most this times the floor's.
GOAL_FLOOR_RATIO = 1.2

#: Where a ramp's progress lines go (``print``).
Say = Callable[[str], None]


# -- servers: facecast, its floor and Redis, each a process of its own ---------------------
def _start_floor(rig: Rig) -> tuple[ServerProcess, int]:
    """The floor (``servers.serve_broadcast_floor``), listening; and its port."""
    ready = encode(Ready(session="floor", rig=RIGS[0], names=rig.names,
                         num_points=rig.num_points, num_vertices=rig.num_vertices,
                         output="weights", dtype="f32"))  # fmt: skip
    weights = np.full(rig.num_examples, 1.0 / rig.num_examples, np.float32).tobytes()
    floor = python_server(
        "facecast.cli.bench.servers:serve_broadcast_floor", ready, weights,
        env={"OPENBLAS_NUM_THREADS": "1"}, name="the bare broadcast server",
    ).start()  # fmt: skip
    try:
        floor.wait_listening(timeout=30.0)
    except BaseException:
        floor.stop()
        raise
    return floor, floor.port


def _prepare_rigs(directory: Path) -> tuple[Any, np.ndarray]:
    """The demo rig under three ids (three characters), and the demo performance's points."""
    rig = fit(demo_example_set())
    directory.mkdir(parents=True, exist_ok=True)
    for rig_id in RIGS:
        rig.save(directory / f"{rig_id}.rig")
    return rig, demo_animation(10.0, with_vertices=False).points.astype(np.float32)


def _start_server(
    rigs: Path, redis_url: str | None, *, stage_timing: bool = False
) -> tuple[ServerProcess, int]:
    """A ``facecast serve`` process, started; ``stage_timing`` turns its stage clocks on.

    The clocks (a thread-CPU clock read, a system call, four per key and frame) only
    where the figures are attributed by stage: the judged figures run as deployed.
    """
    env = {"FACECAST_MAX_CONNECTIONS": "5000", "FACECAST_ACCESS_LOG": "false",
           "FACECAST_MAX_CONNECTIONS_PER_ADDRESS": "0",  # every viewer is on 127.0.0.1
           # A paused publisher is silent while the floor beside it is measured (and while
           # viewers join): the idle rule must not close it.
           "FACECAST_IDLE_TIMEOUT": "3600",
           "FACECAST_LOG_LEVEL": "warning", "OPENBLAS_NUM_THREADS": "1",
           "FACECAST_STAGE_TIMING": "true" if stage_timing else "false"}  # fmt: skip
    extra = ["--redis", redis_url] if redis_url else []
    server = facecast_serve(rigs, *extra, env=env).start()
    return server, server.port


def _wait_ready(port: int, timeout: float = 30.0) -> None:
    """Return once the server on ``port`` answers ``GET /readyz``."""
    url = f"http://127.0.0.1:{port}/readyz"
    wait_until(lambda: answers_ok(url), f"the server on port {port} ready", timeout)


def _stop(server: ServerProcess) -> None:
    server.stop()


# -- the scenarios ---------------------------------------------------------------------
async def _publish(
    port: int, frames: np.ndarray, counter: list[int], running: asyncio.Event, stop: asyncio.Event
) -> None:
    """One publisher at 60 fps while ``running`` is set; connected and silent while not.

    Silent, its server does no per-frame work: its viewers then cost nothing while another
    server beside it is measured.
    """
    url = channel_url(f"http://127.0.0.1:{port}", "bench", "publish")
    async with FramePublisher(url, Hello(rig=RIGS[0])) as publisher:
        while not stop.is_set():
            await running.wait()
            # The 60 fps schedule restarts on every resume: no burst to catch up on a pause.
            start, first = time.perf_counter(), counter[0]
            while running.is_set() and not stop.is_set():
                delay = start + (counter[0] - first) / FPS - time.perf_counter()
                if delay > 0:
                    await asyncio.sleep(delay)
                    if not running.is_set():
                        break
                await publisher.send(frames[counter[0] % len(frames)], time.time())
                counter[0] += 1


class _Target:
    """One server (or pair on Redis) under a ramp: its publisher, its client processes (one
    set per group of viewers), its figures step by step; ``close`` gives its results.

    ``facecast`` False: the floor, which has no ``GET /v1/channels/{name}`` to read.
    ``staged``: the servers run with their stage clocks on; each step is attributed.
    ``label`` starts its printed lines (where two targets' lines interleave).
    """

    def __init__(
        self, ports: dict[str, int], pids: list[int], frames: np.ndarray,
        *, facecast: bool = True, staged: bool = False, label: str = "",
    ) -> None:  # fmt: skip
        self.ports, self.pids, self.facecast, self.staged = ports, pids, facecast, staged
        self.label = label
        self.counter, self.running, self.stop = [0], asyncio.Event(), asyncio.Event()
        self.publisher = asyncio.create_task(
            _publish(ports["a"], frames, self.counter, self.running, self.stop)
        )
        self.clients = {group: Clients({group: port}) for group, port in ports.items()}
        self.measured: list[dict[str, Any]] = []
        self.held = 0
        self.total = 0
        self.result: dict[str, Any] | None = None

    async def add(self, target: int) -> int:
        """Viewers up to ``target``, split evenly over the groups; connection failures."""
        failed = 0
        count = target - self.total
        for i, (group, client) in enumerate(self.clients.items()):
            share = count // len(self.clients) + (i < count % len(self.clients))
            failed += await client.add(group, share)
        self.total = target
        return failed

    async def step(self, failed: int, seconds: float, say: Say) -> bool:
        """Measure the viewers held now, with the publisher running; whether the step held.

        A step over the goal is measured once more: one busy moment of a shared machine
        must not end the ramp (both attempts are kept in ``steps``).
        """
        target = self.total
        self.running.set()
        try:
            for attempt in (1, 2):
                await asyncio.sleep(1.0)  # warm-up: let the new viewers' first results settle
                ok = await self._measure(target, attempt, failed, seconds, say)
                if ok:
                    break
        finally:
            self.running.clear()
        if ok:
            self.held = target
        return ok

    async def _measure(
        self, target: int, attempt: int, failed: int, seconds: float, say: Say
    ) -> bool:
        clients = self.clients
        client_pids = [p.pid for c in clients.values() for p in c.processes if p.pid is not None]
        before = await _channel_info(self.ports["a"]) if self.facecast else _NO_INFO
        stages0 = await _snapshots(self.ports) if self.staged else None
        # When the window opened (Unix time): where two targets take turns, their order.
        measured_at = time.time()
        cpu0, wall0 = cpu_seconds(self.pids), time.perf_counter()
        client_cpu0 = cpu_seconds(client_pids)
        figures = await asyncio.gather(
            *(c.measure(seconds, lambda: self.counter[0]) for c in clients.values())
        )
        cpu = cpu_seconds(self.pids) - cpu0
        wall = time.perf_counter() - wall0
        # The load generator shares the machine: its CPU says whether it, not the
        # server, was the limit (each client process can use one core at most).
        client_cores = (cpu_seconds(client_pids) - client_cpu0) / wall
        after = await _channel_info(self.ports["a"]) if self.facecast else _NO_INFO
        stages = None
        if stages0 is not None:
            stages1 = await _snapshots(self.ports)
            stages = _summed_stages(stages0, stages1)
        # Where results went missing: frames the server never cloned (the fan-out
        # of one frame outlasted the next), or results it skipped for a slow viewer.
        uncloned = 1.0 - min(
            1.0,
            (after["frames"] - before["frames"])
            / max(1, sum(f["frames"] for f in figures) / len(figures)),
        ) if self.facecast else 0.0  # fmt: skip
        skipped = after["skipped"] - before["skipped"]
        results = sum(f["results"] for f in figures)
        by_group = dict(zip(clients, figures, strict=True))
        p99 = max(f["p99_ms"] for f in figures)
        expected = sum(f["frames"] for f in figures) / len(figures) * target
        delivered = sum(f["results"] for f in figures) / expected if expected else 0.0
        ok = failed == 0 and p99 < GOAL_P99_MS and delivered >= MIN_DELIVERY
        server_cores = cpu / wall
        us_per_result = cpu / results * 1e6 if results else float("nan")
        self.measured.append({"viewers": target, "attempt": attempt,
                              "measured_at": round(measured_at, 3),
                              "failed_connections": failed, "p99_ms": p99,
                              "delivered": round(delivered, 3), "ok": ok,
                              "server_cpu_cores": round(server_cores, 3),
                              "server_us_per_result": round(us_per_result, 2),
                              "client_cpu_cores": round(client_cores, 3),
                              "frames_not_cloned": round(uncloned, 3), "server_skipped": skipped,
                              "groups": by_group, "stages": stages})  # fmt: skip
        say(f"  {self.label}{target:5d} viewers: p99 {p99:7.2f} ms, delivered {delivered:6.1%}, "
            f"server CPU {server_cores:4.2f} cores ({us_per_result:5.1f} us/result), "
            f"clients {client_cores:4.2f} cores, not cloned {uncloned:5.1%}, "
            f"skipped {skipped}, "
            f"connect failures {failed}  {'ok' if ok else 'OVER'}")  # fmt: skip
        if stages is not None and results:
            per = {k: v / results * 1e6 for k, v in stages.items()}
            say(f"          server us/result by stage: clone and encode {per['weights']:.2f} "
                f"(one per rig and frame, shared by its viewers), fan-out write "
                f"{per['write']:.2f}")  # fmt: skip
        return ok

    async def close(self) -> dict[str, Any]:
        """Stop the publisher and disconnect the viewers (once); the ramp's results."""
        if self.result is None:
            try:
                info = await _channel_info(self.ports["a"]) if self.facecast else {}
            finally:
                self.stop.set()
                self.running.set()  # wakes a paused publisher, which then sees ``stop``
                await asyncio.gather(self.publisher, return_exceptions=True)
                for client in self.clients.values():
                    await client.close()
            self.result = {"held": self.held, "steps": self.measured,
                           "clones_per_frame": info.get("clones_per_frame"),
                           "keys": len(info.get("keys", []))}  # fmt: skip
        return self.result


async def _ramp(
    ports: dict[str, int], pids: list[int], frames: np.ndarray, seconds: float, say: Say,
    *, steps: tuple[int, ...] = STEPS, staged: bool = False,
) -> dict[str, Any]:  # fmt: skip
    """Ramp viewers over ``ports`` (split evenly) until a step fails; figures per step."""
    target = _Target(ports, pids, frames, staged=staged)
    try:
        for viewers in steps:
            if not await target.step(await target.add(viewers), seconds, say):
                break
    finally:
        result = await target.close()
    return result


async def _ramp_beside_floor(
    port: int, pid: int, floor_port: int, floor_pid: int, frames: np.ndarray, seconds: float,
    say: Say, *, steps: tuple[int, ...] = STEPS,
) -> tuple[dict[str, Any], dict[str, Any]]:  # fmt: skip
    """facecast's ramp and its floor's in one: both servers hold each step's viewers, then
    each is measured in turn with only its own publisher running; their results.

    Measured seconds apart, the two stand on the same machine load, so their ratio no
    longer moves with what else the machine did in between. Who goes first alternates
    per step, so a drift of the machine's load over the ramp favours neither. A target
    that fails a step leaves the ramp after it (its viewers disconnected, freeing the
    load generator); the other goes on.
    """
    facecast = _Target({"a": port}, [pid], frames, label="facecast ")
    floor = _Target({"a": floor_port}, [floor_pid], frames, facecast=False, label="floor    ")
    try:
        live = [facecast, floor]
        for index, viewers in enumerate(steps):
            # Both publishers are paused here: the viewers join idle servers.
            failed = await asyncio.gather(*(target.add(viewers) for target in live))
            turns = list(zip(live, failed, strict=True))
            over = []
            for target, target_failed in turns if index % 2 == 0 else turns[::-1]:
                if not await target.step(target_failed, seconds, say):
                    over.append(target)
            # Only now: its viewers leaving (and its publisher's close handshake, slow
            # behind a backlog) would load the machine while the other was measured.
            for target in over:
                await target.close()
                live.remove(target)
                if live:
                    say(f"  {target.label.strip()} held {target.held} viewers: its viewers "
                        "disconnected, the ramp goes on without it")  # fmt: skip
            if not live:
                break
    finally:
        results = (await facecast.close(), await floor.close())
    return results


async def _snapshots(ports: dict[str, int]) -> list[dict[str, Any]]:
    """Every server's stage clocks (read in a thread: the publisher shares this loop)."""
    return [
        await asyncio.to_thread(stage_snapshot, f"http://127.0.0.1:{port}")
        for port in ports.values()
    ]


def _summed_stages(before: list[dict[str, Any]], after: list[dict[str, Any]]) -> dict[str, float]:
    """Seconds per stage spent between two snapshots of every server, summed."""
    return {
        stage: sum(
            a["seconds"][stage] - b["seconds"][stage] for b, a in zip(before, after, strict=True)
        )
        for stage in ("weights", "write")
    }


#: What the floor reports instead of ``GET /v1/channels/{name}``: nothing skipped.
_NO_INFO: dict[str, Any] = {"frames": 0, "skipped": 0}


async def _channel_info(port: int) -> dict[str, Any]:
    """``GET /v1/channels/bench`` of the server on ``port`` (this process's figures)."""
    async with httpx.AsyncClient() as http:
        info: dict[str, Any] = (await http.get(f"http://127.0.0.1:{port}/v1/channels/bench")).json()
        return info


def _start_redis() -> tuple[RedisServer | None, str | None]:
    """A redis-server of this run and its URL; (None, None) if none is installed or starts."""
    try:
        server = start_redis()
    except (RuntimeError, TimeoutError):
        return None, None
    return (server, server.url) if server is not None else (None, None)


def run(args: argparse.Namespace) -> int:
    say = print
    steps = tuple(args.steps) if args.steps else STEPS
    seconds = max(2.0, float(args.duration) / len(STEPS))
    figures: dict[str, Any] = {"fps": FPS, "goal_p99_ms": GOAL_P99_MS, "goal_viewers": GOAL_VIEWERS,
                               "rigs": len(RIGS), "seconds_per_step": seconds,
                               "steps": list(steps),
                               "cpus": os.cpu_count(),
                               "load_average_start": list(os.getloadavg())}  # fmt: skip
    say(
        f"{os.cpu_count()} CPUs, load average {'/'.join(f'{x:.1f}' for x in os.getloadavg())} "
        "(1/5/15 min; other work on the machine disturbs every figure, the ratios least)"
    )
    with tempfile.TemporaryDirectory(prefix="facecast-bench-") as tmp:
        rigs = Path(tmp) / "rigs"
        rig, frames = _prepare_rigs(rigs)
        say(f"one process, {len(RIGS)} rigs, 60 fps weights, beside its floor in the same run "
            "(a bare websockets server broadcasting a result of the same bytes)")  # fmt: skip
        say(f"  both hold each step's viewers; each is measured in turn (who goes first "
            f"alternates) with only its own publisher running; {seconds:.1f} s per step; "
            "stage clocks off (the judged figures: the server as deployed)")  # fmt: skip
        server, port = _start_server(rigs, None)
        floor, floor_port = None, 0
        try:
            _wait_ready(port)
            floor, floor_port = _start_floor(rig)
            ramps = _ramp_beside_floor(
                port, server.pid, floor_port, floor.pid, frames, seconds, say, steps=steps
            )
            figures["one_process"], figures["floor"] = asyncio.run(ramps)
        finally:
            _stop(server)
            if floor is not None:
                _stop(floor)
        figures["floor_ratio"] = _floor_ratios(figures["one_process"], figures["floor"])
        # Where the time goes, from a second server with the stage clocks on: their reads
        # (system calls, four per key and frame) are in its figures, not in the judged ones.
        say("one process again, stage clocks on (attribution only, not judged)")
        server, port = _start_server(rigs, None, stage_timing=True)
        try:
            _wait_ready(port)
            figures["one_process_staged"] = asyncio.run(
                _ramp({"a": port}, [server.pid], frames, seconds, say, steps=steps, staged=True)
            )
        finally:
            _stop(server)
        redis_process, redis_url = (
            (None, None) if args.no_redis else (None, args.redis) if args.redis else _start_redis()
        )
        if args.no_redis:
            say("two processes on Redis: skipped (--no-redis)")
        elif redis_url is None:
            say("two processes on Redis: skipped (no --redis and no redis-server installed)")
        else:
            say(f"two processes on Redis ({redis_url}): publisher on A, viewers split A/B")
            servers = [_start_server(rigs, redis_url) for _ in range(2)]
            try:
                for _, p in servers:
                    _wait_ready(p)
                figures["two_processes_redis"] = asyncio.run(
                    _ramp(
                        {"a": servers[0][1], "b": servers[1][1]},
                        [process.pid for process, _ in servers],
                        frames,
                        seconds,
                        say,
                        steps=steps,
                    )
                )
            finally:
                for process, _ in servers:
                    _stop(process)
                if redis_process is not None:
                    _stop(redis_process)
    figures["load_average_end"] = list(os.getloadavg())
    one = figures["one_process"]
    ratios = figures["floor_ratio"]
    for viewers, ratio in ratios["per_step"].items():
        say(
            f"  {viewers:>5} viewers: server CPU per result {ratio:.2f}x the floor's "
            "(stage clocks off)"
        )
    at, worst = ratios["at_most_held"], ratios["worst_held"]
    say(f"server CPU per result against a bare websockets broadcast, at the most viewers "
        f"both held: {'-' if at is None else f'{at:.2f}'}x (goal <= {GOAL_FLOOR_RATIO}x) "
        f"{'n/a' if at is None else 'PASS' if at <= GOAL_FLOOR_RATIO else 'FAIL'} (worst "
        f"step held by both {'-' if worst is None else f'{worst:.2f}'}x); viewers held: "
        f"facecast {one['held']}, floor {figures['floor']['held']}")  # fmt: skip
    passed = one["held"] >= GOAL_VIEWERS
    clones_ok = one["clones_per_frame"] == float(len(RIGS))
    say(f"viewers held by one process at p99 < {GOAL_P99_MS:g} ms: {one['held']} "
        f"(goal >= {GOAL_VIEWERS}) {'PASS' if passed else 'FAIL'}")  # fmt: skip
    say(f"clones per frame with {len(RIGS)} rigs: {one['clones_per_frame']} (goal {len(RIGS)}) "
        f"{'PASS' if clones_ok else 'FAIL'}")  # fmt: skip
    two = figures.get("two_processes_redis")
    if two:
        added = _added_latency(two)
        figures["redis_added_p50_ms"] = added
        say(f"two processes on Redis: {two['held']} viewers held; viewers on B (frames via "
            f"Redis) p50 {added:+.2f} ms versus viewers on A" if added is not None else
            f"two processes on Redis: {two['held']} viewers held")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2, default=float))
    return 0 if passed and clones_ok else 1


def _floor_ratios(facecast: dict[str, Any], floor: dict[str, Any]) -> dict[str, Any]:
    """facecast's server CPU per result over the floor's, at each viewer count both ran."""
    ours = {step["viewers"]: step for step in facecast["steps"]}
    per_step = {}
    held = []
    for step in floor["steps"]:
        mine = ours.get(step["viewers"])
        if mine is None or not step["server_us_per_result"] > 0:
            continue
        ratio = round(mine["server_us_per_result"] / step["server_us_per_result"], 3)
        per_step[step["viewers"]] = ratio
        if mine["ok"] and step["ok"]:
            held.append(ratio)
    # The verdict: at the most viewers both held (fixed per-frame costs weigh least there,
    # and it is where "viewers held = the floor's x the ratio" is read).
    return {"per_step": per_step, "at_most_held": held[-1] if held else None,
            "worst_held": max(held) if held else None, "goal": GOAL_FLOOR_RATIO}  # fmt: skip


def _added_latency(two: dict[str, Any]) -> float | None:
    """p50 of B's viewers (frames through Redis) minus A's, at the largest step held."""
    held = [step for step in two["steps"] if step["ok"]] or two["steps"][:1]
    if not held:
        return None
    groups = held[-1]["groups"]
    if "a" not in groups or "b" not in groups:
        return None
    return round(float(groups["b"]["p50_ms"]) - float(groups["a"]["p50_ms"]), 3)
