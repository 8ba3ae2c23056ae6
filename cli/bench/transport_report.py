"""``facecast bench transport``'s verdicts and its printed report, from measured figures.

Judges figures against the goals and formats them; it starts and measures nothing.
"""

from __future__ import annotations

from typing import Any

from facecast.rig import Rig

from .servers import BENCH_MAX_FPS
from .transport_client import FLOOR_BATCH, PIPELINE_WINDOW

__all__ = [
    "BASELINES",
    "FPS_SLACK",
    "GOAL_P99_MS",
    "TARGET_FPS",
    "format_report",
    "load_line",
    "moving_figures",
    "summarize",
]

#: Goals (issue 12, "Per-frame overhead", tightening the first round's 1.5x and 0.5x):
#: facecast weights RTT p50 within 1.2x of the faster bare echo, pipelined throughput at
#: least 0.8x of it, and every vertices-mode connection sustaining the target rate (1% slack).
GOAL_RTT_RATIO = 1.2
GOAL_THROUGHPUT_RATIO = 0.8
TARGET_FPS = 60.0
FPS_SLACK = 0.01
#: A stream "holds" when every client gets >= 99 % of 60 fps at p99 below this.
GOAL_P99_MS = 50.0
#: The bare echo servers facecast's weights path is compared with.
BASELINES = ("websockets", "fastapi")


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else a / b


def _status(ok: bool | None) -> str:
    return "n/a" if ok is None else ("PASS" if ok else "FAIL")


def load_line(label: str, f: dict[str, Any]) -> str:
    lat = f["latency_ms"]
    p99 = "-" if lat["p99_ms"] is None else f"{lat['p99_ms']:.1f}"
    errors = f", errors {f['errors']}" if f["errors"] else ""
    text = (
        f"{label:<9}{f['clients']:>4} x 60 fps {f['output']:<8} min {f['min_client_fps']:5.1f} fps, "
        f"p99 {p99:>6} ms, dropped {f['dropped']:>5}, server {f['server_cpu_cores']:.2f} cores "
        f"({f['server_cpu_us_per_result']:.0f} us/result), load generator "
        f"{f['client_cpu_cores']:.2f} cores ({f['client_cpu_us_per_result']:.0f} us/result)"
        f"{errors}  "
        f"{'held' if f['held'] else 'NOT held'}"
    )
    stages = f.get("stages")
    if stages:
        parts = ", ".join(
            f"{k} {v:.0f}" for k, v in stages["per_result_us"].items() if v is not None
        )
        batch = stages["mean_batch_frames"]
        blends = (
            f"blend batches of {batch} frames on average"
            if batch is not None
            else f"no blends ({f['output']} output: nothing blended on the server)"
        )
        text += f"\n{'':13}server us/result by stage: {parts}; {blends}"
    return text


def _first_step(ramp: dict[str, Any]) -> dict[str, Any]:
    """The ramp's run at its first stream count that held, else its last attempt there."""
    runs = [r for r in ramp["steps"] if r["clients"] == ramp["steps"][0]["clients"]]
    return next((r for r in runs if r["held"]), runs[-1])


def moving_figures(
    ramp: dict[str, Any],
    floor: dict[str, Any],
    blend_floor: dict[str, float],
    rig: Rig,
    clients: int,
) -> dict[str, Any]:
    first = _first_step(ramp)
    floor_first = _first_step(floor)
    blend = (first.get("stages") or {}).get("per_item_us", {}).get("blend")
    return {
        "num_vertices": int(rig.num_vertices),
        "moving_vertices": int(rig.moving_vertices.size),
        "ramp": ramp,
        "floor": floor,
        "streams_held": ramp["held"],
        "floor_streams_held": floor["held"],
        "held_ratio": _ratio(ramp["held"], floor["held"]),
        "server_cpu_ratio_at_first_step": _ratio(
            first["server_cpu_us_per_result"], floor_first["server_cpu_us_per_result"]
        ),
        "blend_floor_us": blend_floor,
        "blend_us_per_frame": blend,
        "blend_ratio_to_batched_floor": _ratio(blend, blend_floor[f"batch{FLOOR_BATCH}_us"]),
        "goal": {
            "clients": clients,
            "fps_min": TARGET_FPS * (1 - FPS_SLACK),
            "p99_ms_max": GOAL_P99_MS,
            "pass": first["held"],
        },
    }


def summarize(
    results: dict[str, dict[str, Any]],
    load: dict[str, Any],
    duration: float,
    clients: int,
    frame_bytes: int,
    vertices_id: str,
) -> dict[str, Any]:
    p50 = {name: r["rtt_ms"]["p50_ms"] for name, r in results.items()}
    tput = {name: r["throughput_msgs_per_s"] for name, r in results.items()}
    rtt_base = min(BASELINES, key=lambda n: p50[n] if p50[n] is not None else float("inf"))
    tput_base = max(BASELINES, key=lambda n: tput[n])
    rtt_ratio = _ratio(p50["facecast"], p50[rtt_base])
    tput_ratio = _ratio(tput["facecast"], tput[tput_base])
    floor = TARGET_FPS * (1 - FPS_SLACK)
    per_client_min = load["min_client_fps"]
    vertices_pass = load["held"]
    cpu_base = min(
        BASELINES, key=lambda n: results[n].get("server_cpu_us_per_message") or float("inf")
    )
    return {
        "duration": duration,
        "clients": clients,
        "frame_bytes": frame_bytes,
        "pipeline_window": PIPELINE_WINDOW,
        "servers": results,
        "rtt_p50_ms": p50,
        "throughput_msgs_per_s": tput,
        "baseline": {"rtt": rtt_base, "throughput": tput_base, "cpu": cpu_base},
        "ratios": {
            "rtt_p50": rtt_ratio,
            "throughput": tput_ratio,
            "server_cpu_per_message": _ratio(
                results["facecast"].get("server_cpu_us_per_message"),
                results[cpu_base].get("server_cpu_us_per_message"),
            ),
        },
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
            "min_client_fps": per_client_min,
            "mb_per_s": load["mb_per_s"],
            "latency_ms": load["latency_ms"],
            "received": load["received"],
            "sent": load["sent"],
            "dropped": load["dropped"],
            "errors": load["errors"],
            "pass": vertices_pass,
        },
    }


def format_report(f: dict[str, Any]) -> str:
    def num(value: float | None, fmt: str) -> str:
        return "-" if value is None else format(value, fmt)

    machine = f.get("machine") or {}
    loads = [machine.get("load_average_start"), machine.get("load_average_end")]
    load_text = " -> ".join("/".join(f"{x:.1f}" for x in v) for v in loads if v)
    lines = [
        f"transport benchmark: frame of {f['frame_bytes']} bytes, "
        f"{f['duration']:g} s per phase, window {f['pipeline_window']}; "
        f"{machine.get('cpus', '?')} CPUs, load average {load_text or '?'} (1/5/15 min: "
        "other work on the machine disturbs every figure, the ratios least)",
        f"  {'server':<12}{'RTT p50 (ms)':>14}{'pipelined (msg/s)':>20}{'server CPU (us/msg)':>22}",
    ]
    for name in (*BASELINES, "facecast"):
        lines.append(
            f"  {name:<12}{num(f['rtt_p50_ms'][name], '.3f'):>14}"
            f"{num(f['throughput_msgs_per_s'][name], '.0f'):>20}"
            f"{num(f['servers'][name].get('server_cpu_us_per_message'), '.1f'):>22}"
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
        f"superseded (newest-only, not answered): {dropped}; load generator "
        f"{num(f.get('load_generator_cpu_cores'), '.2f')} cores"
    )
    stages = f.get("weights_stages")
    if stages:
        parts = ", ".join(
            f"{k} {v:.1f}" for k, v in stages["per_result_us"].items() if v is not None
        )
        lines.append(
            f"  facecast weights, server us/result by stage: {parts} (a second server with "
            f"the stage clocks on: RTT p50 {num(stages.get('rtt_p50_ms'), '.3f')} ms, "
            f"{num(stages.get('throughput_msgs_per_s'), '.0f')} msg/s)"
        )
    goals, ratios, base = f["goals"], f["ratios"], f["baseline"]
    lines += [
        f"  RTT p50: facecast / {base['rtt']} = {num(ratios['rtt_p50'], '.2f')}x "
        f"(goal <= {goals['rtt_p50_ratio_max']}x)  {_status(goals['rtt_pass'])}",
        f"  throughput: facecast / {base['throughput']} = {num(ratios['throughput'], '.2f')}x "
        f"(goal >= {goals['throughput_ratio_min']}x)  {_status(goals['throughput_pass'])}",
        f"  server CPU per message: facecast / {base['cpu']} = "
        f"{num(ratios['server_cpu_per_message'], '.2f')}x",
    ]
    for kind, figures in (f.get("whole_mesh") or {}).items():
        lines.append("  " + load_line(kind, figures))
    whole_floor = f.get("whole_mesh_floor")
    if whole_floor:
        lines.append("  " + load_line("floor", whole_floor))
        bounded = (f.get("whole_mesh") or {}).get("bounded")
        ratio = _ratio(
            bounded and bounded["server_cpu_us_per_result"],
            whole_floor["server_cpu_us_per_result"],
        )
        lines.append(
            f"  whole mesh f16: server CPU per result, facecast (bounded) / its floor (bare "
            f"websockets, same bytes) = {num(ratio, '.2f')}x"
        )
    v = f["vertices"]
    lat = v["latency_ms"]
    lines.append(
        f"  vertices f16, {v['rig']} rig (exact), {f['clients']} clients x "
        f"{v['target_fps']:g} fps: min {v['min_client_fps']:.1f} fps/client, "
        f"{v['mb_per_s']:.1f} MB/s, p50 {num(lat['p50_ms'], '.2f')} ms p99 "
        f"{num(lat['p99_ms'], '.2f')} ms, dropped {v['dropped']}, errors "
        f"{v['errors'] or 'none'}  {_status(goals['vertices_pass'])} "
        f"(goal >= {goals['vertices_fps_min']:.1f} fps each, p99 < {GOAL_P99_MS:g} ms)"
    )
    moving = f.get("moving")
    if moving:
        ramp, floor = moving["ramp"], moving["floor"]
        lines.append(
            f"  moving vertices: {moving['moving_vertices']} of {moving['num_vertices']}; "
            "each step, facecast then its floor (bare websockets, same bytes):"
        )
        for step in ramp["steps"]:
            lines.append("    " + load_line("facecast", step).replace("\n", "\n    "))
        for step in floor["steps"]:
            lines.append("    " + load_line("floor", step))
        b = moving["blend_floor_us"]
        lines += [
            f"  streams held at 60 fps (p99 < {GOAL_P99_MS:g} ms): facecast {ramp['held']}, "
            f"floor {floor['held']} ({num(moving['held_ratio'], '.2f')}x); server CPU per "
            f"result at {moving['goal']['clients']} streams: "
            f"{num(moving['server_cpu_ratio_at_first_step'], '.2f')}x the floor's",
            f"  blend: facecast {num(moving['blend_us_per_frame'], '.0f')} us/frame (moving "
            f"columns, non-zero rows) against a bare dense blend of the same rig, "
            f"{b['single_us']:.0f} us alone, {b[f'batch{FLOOR_BATCH}_us']:.0f} us/frame in "
            f"batches of {FLOOR_BATCH}: {num(moving['blend_ratio_to_batched_floor'], '.2f')}x",
            f"  goal: {moving['goal']['clients']} moving f16 streams at >= "
            f"{moving['goal']['fps_min']:.1f} fps each, p99 < {GOAL_P99_MS:g} ms  "
            f"{_status(moving['goal']['pass'])}",
        ]
    return "\n".join(lines)
