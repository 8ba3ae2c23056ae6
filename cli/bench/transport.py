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

The servers are compared with the same bare client: pre-encoded messages, each facecast
reply's ``dropped`` read off its last bytes (to count results and drops), nothing else. All three run at
once and are measured in alternating rounds from one client process, so a busy moment
of the machine weighs on the baselines and facecast alike. The facecast
client library's own round trip (encode, full decode and validation, its reader task)
is measured too and printed apart, as client cost, not server cost.

Every phase reports the server's and the load generator's CPU, and facecast's server
time per result in each stage (decode, weights, blend, cast, encode, write, read off
its ``/metrics``). Vertex streams (ICT with bounded weights, as tracked input is fitted)
run beside their floors, measured in the same run: (d) a bare ``websockets`` server
answering each frame with a result of the same bytes, driven by the same load
generator, and a bare batched blend ``weights @ basis`` of the same rig. Both ramp the
number of 60 fps streams to the most each holds.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from facecast.protocol import Frame, Ready, encode
from facecast.rig import Rig, fit
from facecast.rig.demo import demo_example_set
from facecast.rig.sources.ict import ict_example_set, locate_ict

from .harness import python_server
from .measure import cpu_seconds, stage_delta, stage_snapshot
from .servers import BENCH_MAX_FPS
from .transport_client import ROUNDS, measure
from .transport_report import (
    BASELINES,
    FPS_SLACK,
    GOAL_P99_MS,
    TARGET_FPS,
    format_report,
    load_line,
    moving_figures,
    summarize,
)

__all__ = ["run"]

#: Streams tried after ``--clients`` when ramping, in order, up to ``--max-streams``.
RAMP_STEPS = (30, 40, 60, 80, 100, 140, 200)
#: Seconds per ramp step (at most ``--duration``).
RAMP_SECONDS = 5.0
#: Seconds of unmeasured vertex streams that warm a fresh server up for each rig.
WARMUP_SECONDS = 2.0
_SERVER_START_TIMEOUT = 60.0
#: Each server kind's entry point in ``servers`` (its arguments after the port).
_SERVERS = {
    "websockets": "serve_websockets_echo",
    "fastapi": "serve_fastapi_echo",
    "bare-vertices": "serve_vertices_floor",
    "facecast": "serve_facecast",
    "facecast-staged": "serve_facecast",
}


@contextlib.contextmanager
def _server(kind: str, rigs_dir: Path, log_dir: Path) -> Iterator[tuple[int, int]]:
    """Start server ``kind`` in a subprocess; yield (port, pid) once it accepts connections."""
    args: tuple[object, ...] = ()
    if kind == "bare-vertices":
        args = (str(rigs_dir),)
    elif kind.startswith("facecast"):
        args = (str(rigs_dir), kind == "facecast-staged")
    server = python_server(
        f"facecast.cli.bench.servers:{_SERVERS[kind]}", *args,
        log_path=log_dir / f"{kind}.log", cwd=log_dir, name=f"{kind} server",
    )  # fmt: skip
    with server:
        server.wait_listening(_SERVER_START_TIMEOUT)
        yield server.port, server.pid


def _rigs(rigs_dir: Path) -> dict[str, Any]:
    """Fit and store the demo rig, and the vertices rigs (ICT's when its data is there).

    The vertices rigs: ``exact`` (the thesis's fit, dense weights) and ``bounded``
    (``noise`` 0.1 mm, ``clamp`` nonneg: how tracked input is fitted; its weights are
    mostly 0). Without ICT both are the demo rig's. Also writes ``bare.npz`` for the
    bare vertices server: the ``ready`` and the f16 vertices a bounded session gets, for
    output ``moving`` and for the whole mesh.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fitted on purpose as they are: no advice wanted
        demo_set = demo_example_set()
        demo = fit(demo_set)
        example_set, name = demo_set, "demo"
        archive = locate_ict()
        if archive is not None:
            example_set, name = ict_example_set(archive), "ict"
        exact = demo if archive is None else fit(example_set)
        # 0.1 mm of landmark noise on ICT (cm); the demo's units are of the same size.
        bounded = fit(example_set, noise=0.01, clamp="nonneg")
    demo.save(rigs_dir / "demo.rig")
    exact.save(rigs_dir / f"{name}.rig")
    bounded.save(rigs_dir / f"{name}-bounded.rig")
    bare: dict[str, np.ndarray] = {}
    for output, moving in (("moving", bounded.moving_vertices), ("vertices", None)):
        ready = Ready(session="bare", rig=f"{name}-bounded", names=bounded.names,
                      num_points=bounded.num_points, num_vertices=bounded.num_vertices,
                      output=output, dtype="f16", moving=moving)  # fmt: skip
        first = np.eye(1, bounded.num_examples)[0]
        bare[output] = bounded.blend(first, moving=moving is not None).astype(np.float16)
        bare[f"ready_{output}"] = np.frombuffer(encode(ready), np.uint8)
    np.savez(rigs_dir / "bare.npz", allow_pickle=False, **bare)  # no record is an object array
    return {
        "demo_neutral": np.asarray(demo.source_neutral, dtype=np.float32),
        "name": name,
        "exact": exact,
        "bounded": bounded,
    }


class _Run:
    """One benchmark run's servers and the way to load them (shared by the phases)."""

    def __init__(self, say: Callable[[str], None], timeout: float) -> None:
        self.say = say
        self.timeout = timeout

    def load(
        self, url: str, pids: list[int], rig: Rig, rig_id: str, clients: int, seconds: float,
        output: str, stages: bool,
    ) -> dict[str, Any]:  # fmt: skip
        """One load-generator run of ``clients`` f16 streams at 60 fps, with CPU and stages."""
        before = stage_snapshot(url) if stages else None
        cpu0, wall0 = cpu_seconds(pids), time.perf_counter()
        load = measure(
            {
                "kind": "load", "url": url, "rig": rig_id, "clients": clients, "fps": TARGET_FPS,
                "seconds": seconds, "neutral": np.asarray(rig.source_neutral).tolist(),
                "output": output, "dtype": "f16",
            },
            self.timeout,
        )  # fmt: skip
        wall = time.perf_counter() - wall0
        cpu = cpu_seconds(pids) - cpu0
        received = max(1, load["received"])
        floor_fps = TARGET_FPS * (1 - FPS_SLACK)
        p99 = load["latency_ms"]["p99_ms"]
        held = (
            bool(load["per_client_fps"])
            and min(load["per_client_fps"]) >= floor_fps
            and p99 is not None
            and p99 < GOAL_P99_MS
            and not load["errors"]
        )
        figures = {
            "clients": clients,
            "output": output,
            "min_client_fps": load["min_client_fps"],
            "mb_per_s": load["payload_mb_per_s"],
            "latency_ms": load["latency_ms"],
            "received": load["received"],
            "sent": load["sent"],
            "dropped": load["dropped"],
            "errors": load["errors"],
            "held": held,
            "server_cpu_cores": cpu / wall,
            "server_cpu_us_per_result": cpu / received * 1e6,
            "client_cpu_cores": load["client_cpu_seconds"] / wall,
            "client_cpu_us_per_result": load["client_cpu_seconds"] / received * 1e6,
        }
        if before is not None:
            figures["stages"] = stage_delta(before, stage_snapshot(url), load["received"])
        return figures

    def ramp(
        self, url: str, pids: list[int], rig: Rig, rig_id: str, steps: list[int], seconds: float,
        label: str, stages: bool,
    ) -> dict[str, Any]:  # fmt: skip
        """Streams at 60 fps, more at each step, until a step does not hold."""
        held = 0
        runs = []
        for clients in steps:
            # A step that does not hold is measured once more: one busy moment of a
            # shared machine must not end the ramp (both runs are kept in ``steps``).
            for attempt in (1, 2):
                figures = self.load(url, pids, rig, rig_id, clients, seconds, "moving", stages)
                figures["attempt"] = attempt
                runs.append(figures)
                self.say("  " + load_line(label, figures))
                if figures["held"]:
                    break
            if not figures["held"]:
                break
            held = clients
        return {"held": held, "steps": runs}


def run(args: argparse.Namespace) -> int:
    """Run the benchmark (``args.duration`` s per phase, ``args.clients`` vertices clients)."""
    duration = float(getattr(args, "duration", None) or 10.0)
    clients = int(getattr(args, "clients", None) or 20)
    max_streams = int(getattr(args, "max_streams", None) or RAMP_STEPS[-1])
    # Not a flag: the test's smoke run shortens it (the figures of a short run mean nothing).
    warmup = float(getattr(args, "warmup_seconds", None) or WARMUP_SECONDS)
    if not 0 < duration <= 3600:
        raise ValueError(f"--duration must be in (0, 3600] s, got {duration}")
    if not 1 <= clients <= 1000:
        raise ValueError(f"--clients must be in 1..1000, got {clients}")
    if not clients <= max_streams <= 1000:
        raise ValueError(f"--max-streams must be in {clients}..1000, got {max_streams}")
    timeout = 4 * duration + 120.0

    def say(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    step_seconds = min(duration, RAMP_SECONDS)
    steps = [clients, *(n for n in RAMP_STEPS if clients < n <= max_streams)]
    if steps[-1] < max_streams and max_streams not in steps:
        steps.append(max_streams)
    bench = _Run(say, timeout)
    load_start = list(os.getloadavg())

    with tempfile.TemporaryDirectory(prefix="facecast-bench-") as tmp:
        tmp_path = Path(tmp)
        rigs_dir = tmp_path / "rigs"
        rigs_dir.mkdir()
        say("bench transport: fitting rigs ...")
        rigs = _rigs(rigs_dir)
        name = rigs["name"]
        neutral = rigs["demo_neutral"]
        message = encode(Frame(seq=1, ts=0.0, points=neutral))
        blend_floor = measure(
            {"kind": "blend-floor", "rig_path": str(rigs_dir / f"{name}-bounded.rig")}, timeout
        )
        blend_floor.pop("client_cpu_seconds", None)
        with contextlib.ExitStack() as servers:
            started = {
                kind: servers.enter_context(_server(kind, rigs_dir, tmp_path)) for kind in BASELINES
            }
            ports = {kind: port for kind, (port, _) in started.items()}
            port, pid = servers.enter_context(_server("facecast", rigs_dir, tmp_path))
            pids = {kind: p for kind, (_, p) in started.items()} | {"facecast": pid}
            base = f"http://127.0.0.1:{port}"
            say(
                f"bench transport: {', '.join(BASELINES)} echo and facecast weights "
                f"({duration:g} s each, in {ROUNDS} alternating rounds; facecast's max_fps "
                f"raised to {BENCH_MAX_FPS:g}) ..."
            )
            spec = {"url": base, "rig": "demo", "points": neutral.tolist(), "seconds": duration}
            echo_urls = {
                kind: f"ws://127.0.0.1:{ports[kind]}{'/echo' if kind == 'fastapi' else '/'}"
                for kind in BASELINES
            }
            cpu0 = {kind: cpu_seconds([p]) for kind, p in pids.items()}
            wall0 = time.perf_counter()
            results = measure(
                {**spec, "kind": "interleaved", "message": message.hex(), "echo_urls": echo_urls},
                timeout * (len(BASELINES) + 1),
            )
            wall = time.perf_counter() - wall0
            client_cpu = results.pop("client_cpu_seconds")
            for kind, p in pids.items():
                cpu = cpu_seconds([p]) - cpu0[kind]
                results[kind]["server_cpu_cores"] = cpu / wall
                results[kind]["server_cpu_us_per_message"] = (
                    cpu / results[kind]["messages"] * 1e6 if results[kind]["messages"] else None
                )
            say(f"bench transport: facecast weights, library client ({duration:g} s) ...")
            library = measure({**spec, "kind": "facecast-library"}, timeout)
            library.pop("client_cpu_seconds", None)
            # The rest is attributed by stage: a server with the stage clocks on (their
            # cost is in its figures, not in the judged ones above).
            port, pid = servers.enter_context(_server("facecast-staged", rigs_dir, tmp_path))
            base = f"http://127.0.0.1:{port}"
            say(
                f"bench transport: facecast weights by stage, stage clocks on "
                f"({duration / 2:g} s) ..."
            )
            before = stage_snapshot(base)
            staged = measure(
                {**spec, "url": base, "seconds": duration / 2, "kind": "interleaved",
                 "message": message.hex(), "echo_urls": {}},
                timeout,
            )  # fmt: skip
            after = stage_snapshot(base)
            weights_stages = stage_delta(
                before, after, int(after["items"]["encode"] - before["items"]["encode"])
            )
            weights_stages["rtt_p50_ms"] = staged["facecast"]["rtt_ms"]["p50_ms"]
            weights_stages["throughput_msgs_per_s"] = staged["facecast"]["throughput_msgs_per_s"]
            say(
                f"bench transport: facecast vertices f16, {name} rigs, {clients} clients x "
                f"{TARGET_FPS:g} fps ({duration:g} s each): exact and bounded weights, "
                "whole mesh ..."
            )
            # A fresh server's first seconds of vertex streams cost it about twice what
            # later ones do (rig loads, first touches of the bases and of every session's
            # buffers): each rig is warmed up once, unmeasured, before its figures.
            for kind, rig_id, output in (("exact", name, "vertices"),
                                         ("bounded", f"{name}-bounded", "moving")):  # fmt: skip
                bench.load(base, [pid], rigs[kind], rig_id, clients, warmup, output,
                           False)  # fmt: skip
            full = {}
            for kind, rig_id in (("exact", name), ("bounded", f"{name}-bounded")):
                full[kind] = bench.load(base, [pid], rigs[kind], rig_id, clients, duration,
                                        "vertices", True)  # fmt: skip
                say("  " + load_line(kind, full[kind]))
            say(
                f"bench transport: moving vertices f16, {name}-bounded rig: facecast and the "
                f"bare floor, streams ramped {steps} ({step_seconds:g} s a step) ..."
            )
            ramp = bench.ramp(base, [pid], rigs["bounded"], f"{name}-bounded", steps,
                              step_seconds, "facecast", True)  # fmt: skip
        with _server("bare-vertices", rigs_dir, tmp_path) as (bare_port, bare_pid):
            bench.load(f"http://127.0.0.1:{bare_port}", [bare_pid], rigs["bounded"],
                       f"{name}-bounded", clients, warmup, "moving", False)  # fmt: skip
            floor = bench.ramp(f"http://127.0.0.1:{bare_port}", [bare_pid], rigs["bounded"],
                               f"{name}-bounded", steps, step_seconds, "floor", False)  # fmt: skip
            say(f"bench transport: the whole mesh's floor, {clients} clients ({duration:g} s) ...")
            whole_floor = bench.load(f"http://127.0.0.1:{bare_port}", [bare_pid],
                                     rigs["bounded"], f"{name}-bounded", clients, duration,
                                     "vertices", False)  # fmt: skip
            say("  " + load_line("floor", whole_floor))

    figures = summarize(results, full["exact"], duration, clients, len(message), name)
    figures["machine"] = {"cpus": os.cpu_count(), "load_average_start": load_start,
                          "load_average_end": list(os.getloadavg())}  # fmt: skip
    figures["library_client"] = library
    figures["load_generator_cpu_cores"] = client_cpu / wall
    figures["weights_stages"] = weights_stages
    figures["whole_mesh"] = full
    figures["whole_mesh_floor"] = whole_floor
    figures["moving"] = moving_figures(ramp, floor, blend_floor, rigs["bounded"], clients)
    print(format_report(figures))
    if getattr(args, "json", None):
        Path(args.json).write_text(json.dumps(figures, indent=2), encoding="utf-8")
    return 0
