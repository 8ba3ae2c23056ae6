"""``facecast demo``: the main job on the embedded default, end to end on one machine.

Fits the procedural demo rig, serves it from a local server (with the web viewer), streams
the demo performance through the real WebSocket protocol, checks the results against
offline cloning and prints the viewer's URL. It needs nothing but this package.
"""

from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from facecast.cli.errors import CommandError

if TYPE_CHECKING:  # the rig and the client load when the command runs, not for --help
    from facecast.cli.commands import Subparsers
    from facecast.client.streaming import Progress, StreamOutcome
    from facecast.rig.sources.animation import SourceAnimation


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="fit the demo rig, serve it locally, stream the demo performance, show the viewer URL",
        description=(
            "Runs facecast's main job on its built-in procedural example set: fits the demo "
            "rig, starts a local server on 127.0.0.1, streams the demo performance over "
            "WebSocket, compares every result with offline cloning, prints fps and latency, "
            "then keeps serving the web viewer until Ctrl-C (or exits with --exit)."
        ),
    )
    parser.add_argument(
        "--port", type=int, default=8000, help="port on 127.0.0.1 (default 8000; 0 = any free)"
    )
    parser.add_argument(
        "--rigs",
        metavar="DIR",
        help="rig directory to serve (default: a temporary one, removed at exit)",
    )
    parser.add_argument(
        "--seconds", type=float, default=12.0, help="length of the performance (default 12)"
    )
    parser.add_argument("--output", choices=("weights", "vertices"), default="weights")
    parser.add_argument("--dtype", choices=("f32", "f16"), default="f32")
    parser.add_argument(
        "--realtime", action="store_true", help="send at the performance's 60 fps (default: fast)"
    )
    parser.add_argument(
        "--exit", action="store_true", help="stop the server after streaming instead of serving on"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not 0 <= args.port <= 65535:
        raise CommandError(f"--port must be in 0..65535, got {args.port}")
    if not 0 < args.seconds <= 600:
        raise CommandError(f"--seconds must be in (0, 600], got {args.seconds}")

    # SIGTERM (a service manager, `kill`) stops it as Ctrl-C does, so the temporary rig
    # folder is removed either way (the default action would leave it behind).
    if threading.current_thread() is not threading.main_thread():
        return _run(args)  # only the main thread may set a signal handler
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        return _run(args)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def _run(args: argparse.Namespace) -> int:
    import asyncio

    import numpy as np

    from facecast.cli.snapshot import DEMO_RIG_ID, serving, write_demo_rig
    from facecast.rig import load_rig
    from facecast.rig.demo import demo_animation
    from facecast.server.settings import Settings

    with tempfile.TemporaryDirectory(prefix="facecast-demo-") as scratch:
        rigs_dir = Path(args.rigs) if args.rigs else Path(scratch)
        rig_path = write_demo_rig(rigs_dir)
        rig = load_rig(rig_path)
        animation = demo_animation(args.seconds, with_vertices=False)
        print(
            f"demo rig: M={rig.num_examples} examples ({', '.join(rig.names)}), "
            f"K={rig.num_points} feature points, V={rig.num_vertices} target vertices"
        )
        settings = Settings(
            host="127.0.0.1", port=args.port, rigs_dir=rigs_dir, log_level="warning"
        )
        try:
            context = serving(settings, port=args.port)
            url = context.__enter__()
        except OSError as exc:
            raise CommandError(
                f"cannot listen on 127.0.0.1:{args.port} ({exc.strerror or exc}); "
                "try --port 0 for any free port"
            ) from None
        try:
            print(f"server: {url}  (rigs in {rigs_dir})")
            outcome = asyncio.run(_stream(url, DEMO_RIG_ID, animation, args))
            # The server clones one frame at a time; BLAS accumulates a single frame (gemv)
            # and a batch (gemm) in different orders, so the bit-exact reference is the
            # engine's single-frame path, cast to the negotiated dtype.
            single = [rig.weights(frame) for frame in animation.points]
            offline = np.stack(
                single if args.output == "weights" else [rig.blend(w) for w in single]
            ).astype(np.float32 if args.dtype == "f32" else np.float16)
            difference = float(
                np.abs(outcome.values.astype(np.float64) - offline.astype(np.float64)).max()
            )
            _report(outcome, animation, difference, args)
            viewer = f"{url}/viewer?rig={DEMO_RIG_ID}"
            print(f"\nviewer: {viewer}")
            print(f"overlay (OBS browser source): {url}/overlay?rig={DEMO_RIG_ID}")
            print(f"every rig and live channel, the API docs: {url}/")
            if not args.exit:
                try:
                    print("serving; press Ctrl-C to stop", flush=True)
                    threading.Event().wait()
                except KeyboardInterrupt:
                    print("stopping")
        finally:
            context.__exit__(None, None, None)
    return 0


async def _stream(
    url: str, rig_id: str, animation: SourceAnimation, args: argparse.Namespace
) -> StreamOutcome:

    from facecast.client.connection import connect
    from facecast.client.streaming import stream_frames

    def progress(p: Progress) -> None:
        print(
            f"\r  streamed {p.done}/{p.total} frames  {p.fps:6.1f} fps  "
            f"latency p50 {p.latency.p50_ms:5.2f} ms",
            end="",
            file=sys.stderr,
            flush=True,
        )

    async with connect(url, rig_id, output=args.output, dtype=args.dtype) as session:
        outcome = await stream_frames(
            session,
            animation.points,
            fps=animation.fps,
            realtime=args.realtime,
            progress=progress,
        )
    print(file=sys.stderr)
    return outcome


def _report(
    outcome: StreamOutcome, animation: SourceAnimation, difference: float, args: argparse.Namespace
) -> None:
    latency = outcome.latency
    verdict = "exactly equal" if difference == 0.0 else "DIFFERENT"
    print(
        f"streamed {animation.num_frames} frames ({animation.num_frames / animation.fps:.1f} s "
        f"at {animation.fps:g} fps) as {args.output}/{args.dtype}: {outcome.fps:.0f} fps, "
        f"latency p50 {latency.p50_ms:.2f} ms, p99 {latency.p99_ms:.2f} ms, "
        f"{outcome.dropped} dropped, {outcome.rerequested} re-requested"
    )
    print(f"results vs offline cloning: max difference {difference:.3g} ({verdict})")
