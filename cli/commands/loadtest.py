"""``facecast loadtest``: N WebSocket clients at F fps for S seconds against one server.

Maps flags onto ``facecast.cli.loadgen`` and prints / writes its report; bounded in
clients, rate and time, and only ever connects to the URL given.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING, Any

from facecast.cli.errors import CommandError

if TYPE_CHECKING:  # numpy loads when the command runs, not for --help
    import numpy as np

    from facecast.cli.commands import Subparsers


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "loadtest",
        help="measure a server under N concurrent streaming clients",
        description=(
            "Open --clients WebSocket sessions to URL, each sending --fps frames per "
            "second for --duration seconds (small motion around the rig's neutral), then "
            "report latency percentiles, throughput, results, server-reported drops and "
            "errors by code. Stops by itself."
        ),
    )
    parser.add_argument("url", metavar="URL", help="server base URL, e.g. http://127.0.0.1:8000")
    parser.add_argument("--rig", required=True, metavar="NAME", help="rig id on the server")
    parser.add_argument("--clients", type=int, default=10, help="concurrent sessions (default 10)")
    parser.add_argument("--fps", type=float, default=60.0, help="frames/s per client (default 60)")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds (default 10)")
    parser.add_argument("--output", choices=("weights", "vertices", "moving"), default="weights")
    parser.add_argument("--dtype", choices=("f32", "f16"), default="f32")
    parser.add_argument("--token", help="API token (default: FACECAST_TOKEN)")
    parser.add_argument("--json", metavar="FILE", help="write the report as JSON")
    parser.add_argument("--png", metavar="FILE", help="write a latency histogram (PNG)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no live progress")
    parser.set_defaults(func=run)


def _neutral(url: str, rig: str, token: str | None) -> np.ndarray:
    """The rig's source neutral (K, 3) if the rig file can be fetched, else zeros (K, 3)."""
    import numpy as np

    from facecast.client.fetch import ServerRequestError, fetch_rig, fetch_summary

    summary = fetch_summary(url, rig, token=token)
    neutral = summary.get("source_neutral")
    if neutral is not None:
        return np.asarray(neutral, dtype=np.float64)
    try:
        return np.asarray(fetch_rig(url, rig, token=token).source_neutral, dtype=np.float64)
    except ServerRequestError:
        # Not allowed to download the rig: motion around zero loads the server the same.
        return np.zeros((int(summary["num_points"]), 3))


def format_report(report: dict[str, Any]) -> str:
    """The human-readable summary of ``LoadReport.to_dict()``."""
    lat = report["latency_ms"]

    def ms(key: str) -> str:
        return "-" if lat[key] is None else f"{lat[key]:.2f}"

    errors = ", ".join(f"{k} x{v}" for k, v in report["errors"].items()) or "none"
    return "\n".join(
        [
            f"loadtest {report['url']} rig {report['rig']}: {report['clients']} clients x "
            f"{report['fps']:g} fps x {report['duration']:g} s ({report['output']} "
            f"{report['dtype']})",
            f"  latency   p50 {ms('p50_ms')} ms  p95 {ms('p95_ms')} ms  p99 {ms('p99_ms')} ms  "
            f"max {ms('max_ms')} ms",
            f"  results   {report['received']} of {report['sent']} frames sent  "
            f"({report['throughput_fps']:.1f} results/s, "
            f"{report['payload_mb_per_s']:.2f} MB/s payload)",
            f"  per client  min {report['min_client_fps']:.1f} fps",
            f"  dropped by server {report['dropped']}  reconnects {report['reconnects']}",
            f"  errors    {errors}",
        ]
    )


def run(args: argparse.Namespace) -> int:
    import asyncio

    from facecast.cli.loadgen import (
        MAX_CLIENTS,
        MAX_DURATION,
        MAX_FPS,
        run_load,
        write_histogram,
    )

    if not 1 <= args.clients <= MAX_CLIENTS:
        raise CommandError(f"--clients must be in 1..{MAX_CLIENTS}, got {args.clients}")
    if not 0 < args.fps <= MAX_FPS:
        raise CommandError(f"--fps must be in (0, {MAX_FPS:g}], got {args.fps}")
    if not 0 < args.duration <= MAX_DURATION:
        raise CommandError(f"--duration must be in (0, {MAX_DURATION:g}], got {args.duration}")
    try:
        neutral = _neutral(args.url, args.rig, args.token)
    except ValueError as exc:  # a malformed URL
        raise CommandError(str(exc)) from None

    def progress(p: dict[str, Any]) -> None:
        if not args.quiet:
            print(
                f"  {p['elapsed']:5.1f} s  sent {p['sent']}  received {p['received']}  "
                f"errors {p['errors']}",
                file=sys.stderr,
                flush=True,
            )

    report = asyncio.run(
        run_load(
            args.url,
            args.rig,
            clients=args.clients,
            fps=args.fps,
            duration=args.duration,
            neutral=neutral,
            output=args.output,
            dtype=args.dtype,
            token=args.token,
            progress=progress,
        )
    )
    figures = report.to_dict()
    print(format_report(figures))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(figures, fh, indent=2)
    if args.png:
        write_histogram(
            args.png,
            report.rtts,
            title=f"{args.clients} clients x {args.fps:g} fps, {args.output} {args.dtype}",
        )
    return 0
