"""``facecast record``: save what a broadcast channel carries (points, timestamps) as a take.

Watches with ``output=points`` (PROTOCOL.md §2.4) and writes the ``.npz`` that
``load_source_animation`` reads, so ``facecast publish --realtime`` replays it as performed;
it clones nothing and keeps at most ``--frames`` frames in memory.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from facecast.cli.errors import CommandError

if TYPE_CHECKING:  # numpy loads when the command runs, not for --help
    import numpy as np

    from facecast.cli.commands import Subparsers

#: Most frames one take holds (1 hour at 60 fps): bounds the recorder's memory.
MAX_FRAMES = 216_000
#: After the publisher leaves, results still in flight arrive within this long.
_LINGER = 0.5


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "record",
        help="save a broadcast channel's performance (points and timestamps) as a take",
        description=(
            "Record the frames channel CHANNEL carries, as its publisher sent them (feature "
            "points before any smoothing, with their seq and timestamps), into TAKE.npz: "
            "points (F, K, 3), timestamps (F,) in seconds from the first frame, fps (from "
            "the median step), seq (F,). `facecast publish URL CHANNEL TAKE.npz --realtime` "
            "replays it with its original timing. Stops after --frames frames, --seconds "
            "seconds, when the publisher leaves, when no frame came for --idle-timeout "
            "seconds, or on Ctrl-C, and writes what it has. A recorder that cannot keep up "
            "skips frames (the channel sends only the newest); it reports how many."
        ),
    )
    parser.add_argument("url", metavar="URL", help="server base URL, e.g. http://127.0.0.1:8000")
    parser.add_argument("channel", metavar="CHANNEL", help="channel name (1-256 characters)")
    parser.add_argument("-o", "--out", required=True, metavar="TAKE", help="output .npz file")
    parser.add_argument(
        "--rig", default="demo", metavar="NAME",
        help="layout rig the channel's points follow (gives K; default demo)",
    )  # fmt: skip
    parser.add_argument(
        "--frames", type=int, metavar="N",
        help=f"stop after N frames (at most {MAX_FRAMES}, also the default limit)",
    )  # fmt: skip
    parser.add_argument("--seconds", type=float, metavar="S", help="stop after S seconds")
    parser.add_argument(
        "--idle-timeout", type=float, default=10.0, metavar="S",
        help="stop when no frame came for S seconds (default 10)",
    )  # fmt: skip
    parser.add_argument(
        "--dtype", choices=("f32", "f64"), default="f32",
        help="precision of the recorded points (default f32)",
    )  # fmt: skip
    parser.add_argument("--token", help="API token with the viewer role (default: FACECAST_TOKEN)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no summary on stderr")
    parser.set_defaults(func=run)


@dataclass
class Take:
    """Frames recorded so far; filled while recording, so an interrupt keeps them."""

    points: list[Any] = field(default_factory=list)
    timestamps: list[float] = field(default_factory=list)
    seq: list[int] = field(default_factory=list)
    rig: str = ""
    ended: str = ""

    @property
    def missed(self) -> int:
        """Frames the channel carried between the first and last recorded that are not here."""
        return sum(max(0, b - a - 1) for a, b in zip(self.seq, self.seq[1:], strict=False))

    def add(self, seq: int, ts: float, points: Any) -> str | None:
        """Keep one frame; why the take must end instead (the clock went back), or None."""
        if self.seq:
            if seq == self.seq[-1] and ts == self.timestamps[-1]:
                return None  # the same frame twice (a late joiner's catch-up)
            if seq < self.seq[-1] or ts < self.timestamps[-1]:
                return "a new performance started (seq or ts went back)"
        self.points.append(points)
        self.timestamps.append(ts)
        self.seq.append(seq)
        return None

    def arrays(self) -> dict[str, np.ndarray]:
        """The ``.npz`` arrays ``load_source_animation`` reads (plus ``seq`` and ``rig``)."""
        import numpy as np

        stamps = np.asarray(self.timestamps, dtype=np.float64)
        stamps -= stamps[0]
        steps = np.diff(stamps)
        steps = steps[steps > 0]
        fps = float(1.0 / np.median(steps)) if steps.size else 60.0
        return {
            "points": np.stack(self.points),
            "timestamps": stamps,
            "fps": np.asarray(fps, dtype=np.float64),
            "seq": np.asarray(self.seq, dtype=np.int64),
            "rig": np.asarray(self.rig),
        }


def _fail_on(message: Any, args: argparse.Namespace) -> None:
    """Raise the CommandError an ``error`` from the server calls for (None if it is benign)."""
    from facecast.protocol import ErrorCode

    if message.fatal:
        raise CommandError(f"the server refused: {message.message} ({message.code.name})")
    if message.code == ErrorCode.WRONG_POINT_COUNT:
        raise CommandError(
            f"channel {args.channel!r} carries frames that do not fit rig {args.rig!r} "
            f"({message.message}); pass --rig with the publisher's layout rig"
        )
    print(f"facecast record: server: {message.message}", file=sys.stderr)


async def record(args: argparse.Namespace, take: Take) -> None:
    """Fill ``take`` from the channel until a stop condition (see ``register``)."""
    import asyncio

    import numpy as np
    from websockets.exceptions import ConnectionClosed

    from facecast.client.channel import channel_url
    from facecast.client.errors import ConnectionFailed
    from facecast.client.handshake import open_websocket
    from facecast.client.reconnect import OPEN_ERRORS, describe
    from facecast.client.urls import auth_headers, resolve_token
    from facecast.protocol import (
        ChannelIdle,
        ChannelLive,
        Error,
        Limits,
        ProtocolError,
        Ready,
        Result,
        decode_server,
    )

    limits = Limits()
    limit = args.frames or MAX_FRAMES
    query = {"rig": args.rig, "output": "points", "dtype": args.dtype}
    url = channel_url(args.url, args.channel, "watch", query)
    loop = asyncio.get_running_loop()
    try:
        ws = await open_websocket(url, auth_headers(resolve_token(args.token)), limits, 10.0)
    except OPEN_ERRORS as exc:
        raise ConnectionFailed(f"cannot watch {url}: {describe(exc)}") from None
    ready: Ready | None = None
    live = False
    started = loop.time()
    stop_at = started + args.seconds if args.seconds else float("inf")
    last_frame_at = started
    try:
        while True:
            now = loop.time()
            if now >= stop_at:
                take.ended = take.ended or f"{args.seconds:g} s elapsed"
                return
            if now - last_frame_at >= args.idle_timeout:
                take.ended = take.ended or f"no frame for {args.idle_timeout:g} s"
                return
            try:
                async with asyncio.timeout(min(stop_at, last_frame_at + args.idle_timeout) - now):
                    data = await ws.recv()
            except TimeoutError:
                continue
            if isinstance(data, str):
                continue
            try:
                message = decode_server(data, limits)
            except ProtocolError as exc:
                print(f"facecast record: undecodable message skipped: {exc}", file=sys.stderr)
                continue
            if isinstance(message, Error):
                _fail_on(message, args)
            elif isinstance(message, Ready):
                if message.output != "points":
                    raise CommandError("the server does not serve output=points watchers")
                ready, take.rig = message, message.rig
            elif isinstance(message, ChannelLive):
                live = True
            elif isinstance(message, ChannelIdle) and live:
                live = False
                if take.seq:
                    # The publisher left; its last results may still be on their way.
                    take.ended = "the publisher left"
                    stop_at = min(stop_at, loop.time() + _LINGER)
            elif isinstance(message, Result) and ready is not None:
                if not take.seq and not live:
                    continue  # the newest frame of an idle channel: a past performance
                if message.output != "points" or message.values.shape != (ready.num_points, 3):
                    raise CommandError(
                        f"the server sent {message.output} {message.values.shape}, not "
                        f"({ready.num_points}, 3) points"
                    )
                ended = take.add(message.seq, message.ts, np.array(message.values))
                if ended:
                    take.ended = ended
                    return
                last_frame_at = loop.time()
                if len(take.seq) >= limit:
                    take.ended = (
                        f"{limit} frames" if args.frames else f"the limit of {MAX_FRAMES} frames"
                    )
                    return
    except ConnectionClosed:
        take.ended = take.ended or "the server closed the connection"
    finally:
        await ws.close()


def run(args: argparse.Namespace) -> int:
    import asyncio

    import numpy as np

    from facecast.client.connection import ConnectionFailed

    out = Path(args.out)
    if out.suffix.lower() != ".npz":
        raise CommandError(f"{out}: a take is written as .npz")
    if not out.parent.exists():
        raise CommandError(f"{out.parent}: no such folder for {out.name}")
    if args.frames is not None and not 1 <= args.frames <= MAX_FRAMES:
        raise CommandError(f"--frames must be in 1..{MAX_FRAMES}, got {args.frames}")
    for name in ("seconds", "idle_timeout"):
        value = getattr(args, name)
        if value is not None and not value > 0:
            raise CommandError(f"--{name.replace('_', '-')} must be > 0, got {value}")
    take = Take()
    try:
        asyncio.run(record(args, take))
    except KeyboardInterrupt:
        take.ended = "interrupted"  # Ctrl-C is how a take is ended by hand
    except (ValueError, ConnectionFailed) as exc:  # a malformed URL or channel name
        raise CommandError(str(exc)) from None
    if not take.seq:
        raise CommandError(
            f"no frames from channel {args.channel!r} ({take.ended or 'stopped'}): "
            "is a publisher live?"
        )
    arrays = take.arrays()
    np.savez(out, allow_pickle=False, **arrays)  # no record is an object array
    if not args.quiet:
        seq = arrays["seq"]
        print(
            f"facecast record: {len(seq)} frames, {arrays['timestamps'][-1]:.3f} s "
            f"(seq {seq[0]}..{seq[-1]}), missed {take.missed} -> {out} ({take.ended})",
            file=sys.stderr,
        )
    return 0
