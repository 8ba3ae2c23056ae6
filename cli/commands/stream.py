"""``facecast stream``: clone an animation file through a running server, like ``facecast clone``.

Maps flags onto the client library (connection, streaming, fetch) and writes the result
with ``write_clone_output``; no protocol or numeric code of its own.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from facecast.cli.commands._animation import add_source_arguments, load_animation, write_results
from facecast.cli.errors import CommandError

if TYPE_CHECKING:  # the client library loads when the command runs, not for --help
    from typing import TextIO

    from facecast.cli.commands import Subparsers
    from facecast.client.streaming import Progress, StreamOutcome

#: Largest (frames x vertices) result kept in memory for --output vertices, bytes.
MAX_VERTEX_BYTES = 2 << 30


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "stream",
        help="stream an animation through a server and write the cloned result",
        description=(
            "Send every frame of SOURCE to the server at URL over WebSocket and write the "
            "results like `facecast clone`. Frames go as fast as a small window of frames "
            "in flight allows (none dropped), or at the animation's own frame rate with "
            "--realtime. Progress, fps and latency are shown on stderr."
        ),
    )
    parser.add_argument("url", metavar="URL", help="server base URL, e.g. http://127.0.0.1:8000")
    add_source_arguments(
        parser,
        source_help="source animation as 'facecast clone' reads it (.npz/.npy, folder of OBJ "
        "frames, Live Link .csv with --source-rig, MediaPipe .ndjson) or 'demo'",
    )
    parser.add_argument("--rig", required=True, metavar="NAME", help="rig id on the server")
    parser.add_argument(
        "-o", "--out", required=True, metavar="OUT", help="output .npz, .glb or OBJ folder"
    )
    parser.add_argument(
        "--output",
        choices=("weights", "vertices", "moving"),
        default="weights",
        help="moving: receive only the vertices the rig's examples move (fewer bytes), "
        "written out as the whole mesh",
    )
    parser.add_argument("--dtype", choices=("f32", "f16"), default="f32")
    parser.add_argument(
        "--realtime", action="store_true", help="pace frames at the animation's fps"
    )
    parser.add_argument("--align", action="store_true", help="remove head pose on the server")
    parser.add_argument("--token", help="API token (default: FACECAST_TOKEN)")
    parser.add_argument(
        "--window",
        type=int,
        default=2,
        help="frames in flight when not --realtime (default 2)",
    )
    parser.add_argument(
        "--reconnect",
        type=int,
        default=5,
        metavar="N",
        help="reconnection attempts before giving up (default 5)",
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    parser.set_defaults(func=run)


class _ProgressLine:
    """One self-overwriting status line on a terminal; a line a second otherwise."""

    def __init__(self, stream: TextIO, quiet: bool) -> None:
        self.stream = stream
        self.quiet = quiet
        self.tty = stream.isatty()
        self.last = -1.0

    def __call__(self, p: Progress) -> None:
        if self.quiet:
            return
        if not self.tty and p.elapsed - self.last < 1.0 and p.done < p.total:
            return
        self.last = p.elapsed
        lat = p.latency
        text = (
            f"{p.done}/{p.total} frames  {p.fps:7.1f} fps  "
            f"p50 {lat.p50_ms:6.2f} ms  p99 {lat.p99_ms:6.2f} ms  dropped {p.dropped}"
            + (f"  reconnects {p.reconnects}" if p.reconnects else "")
        )
        if self.tty:
            self.stream.write("\r" + text.ljust(100))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def finish(self) -> None:
        if self.tty and not self.quiet:
            self.stream.write("\n")


def run(args: argparse.Namespace) -> int:
    import asyncio

    from facecast.client.connection import connect
    from facecast.client.fetch import fetch_rig
    from facecast.client.streaming import stream_frames

    if not Path(args.out).absolute().parent.is_dir():
        raise CommandError(f"{Path(args.out).parent}: no such folder for {Path(args.out).name}")
    if args.window < 1:
        raise CommandError(f"--window must be >= 1, got {args.window}")
    if args.reconnect < 0:
        raise CommandError(f"--reconnect must be >= 0, got {args.reconnect}")
    try:
        rig = fetch_rig(args.url, args.rig, token=args.token)
    except ValueError as exc:  # a malformed URL
        raise CommandError(str(exc)) from None
    animation = load_animation(
        args.source,
        num_points=rig.num_points,
        feature_indices=lambda: rig.feature_indices,
        source_rig=args.source_rig,
    )
    if args.output != "weights":
        size = animation.num_frames * rig.num_vertices * 3 * 4
        if size > MAX_VERTEX_BYTES:
            raise CommandError(
                f"{animation.num_frames} frames of {rig.num_vertices} vertices need "
                f"{size / 2**30:.1f} GiB in memory (limit {MAX_VERTEX_BYTES / 2**30:.0f} GiB); "
                "stream --output weights instead"
            )
    line = _ProgressLine(sys.stderr, args.quiet)

    async def main() -> StreamOutcome:
        async with connect(
            args.url,
            args.rig,
            output=args.output,
            dtype=args.dtype,
            token=args.token,
            align=args.align,
            reconnect=args.reconnect,
        ) as session:
            outcome = await stream_frames(
                session,
                animation.points,
                fps=animation.fps,
                realtime=args.realtime,
                window=args.window,
                progress=line,
            )
            if args.output == "moving":
                outcome.values = session.full_vertices(outcome.values, rig.target_neutral)
            return outcome

    try:
        outcome = asyncio.run(main())
    finally:
        line.finish()
    output = "weights" if args.output == "weights" else "vertices"
    path = write_results(args.out, rig, output, outcome.values, animation.fps)
    errors = ", ".join(f"{k} x{v}" for k, v in sorted(outcome.errors.items())) or "none"
    print(
        f"facecast stream: {animation.num_frames} frames -> {path}  "
        f"({outcome.fps:.1f} fps live, latency {outcome.latency}; dropped by server "
        f"{outcome.dropped}, re-requested {outcome.rerequested}; errors {errors})",
        file=sys.stderr,
    )
    return 0
