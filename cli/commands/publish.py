"""``facecast publish``: stream an animation file to a broadcast channel as its publisher.

Maps flags onto the bridges' `FramePublisher` (PROTOCOL.md §2.1 ``.../publish``); it
writes nothing and clones nothing: viewers (``facecast watch``, the web viewer) do.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from typing import TYPE_CHECKING

from facecast.cli.commands._animation import add_source_arguments, load_animation
from facecast.cli.errors import CommandError

if TYPE_CHECKING:  # numpy loads when the command runs, not for --help
    import numpy as np

    from facecast.cli.commands import Subparsers
    from facecast.client.channel import PublisherStats
    from facecast.rig.sources.animation import SourceAnimation


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "publish",
        help="stream an animation to a broadcast channel (one performer, many viewers)",
        description=(
            "Send every frame of SOURCE to channel CHANNEL on the server at URL. Viewers "
            "of the channel receive it cloned onto the character they watch. --rig names "
            "the rig whose feature-point layout SOURCE follows (the publisher's own "
            "results come back on it). Without --realtime frames go as fast as the "
            "server's announced max_fps allows. A source with timestamps (a take written "
            "by `facecast record`) is sent with its own timestamps as the frames' ts, and "
            "--realtime replays it with its original timing."
        ),
    )
    parser.add_argument("url", metavar="URL", help="server base URL, e.g. http://127.0.0.1:8000")
    parser.add_argument("channel", metavar="CHANNEL", help="channel name (1-256 characters)")
    add_source_arguments(
        parser,
        source_help="source animation as 'facecast clone' reads it (.npz/.npy, OBJ folder, "
        "Live Link .csv with --source-rig, MediaPipe .ndjson) or 'demo'",
    )
    parser.add_argument(
        "--rig", default="demo", metavar="NAME", help="layout rig id on the server (default demo)"
    )
    parser.add_argument(
        "--realtime",
        action="store_true",
        help="pace frames at the source's timestamps (else its fps), as performed",
    )
    parser.add_argument("--loop", action="store_true", help="start over at the end, until Ctrl-C")
    parser.add_argument("--seconds", type=float, default=12.0, help="length of 'demo' (default 12)")
    parser.add_argument(
        "--token", help="API token with the publisher role (default: FACECAST_TOKEN)"
    )
    parser.add_argument(
        "--drain-timeout",
        type=float,
        default=5.0,
        metavar="SECONDS",
        help="at the end, wait at most this long for the last frame's result (default 5)",
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="no summary on stderr")
    parser.set_defaults(func=run)


def _animation(args: argparse.Namespace, num_points: int) -> SourceAnimation:
    """The source animation, checked against the channel rig's K."""

    def feature_indices() -> np.ndarray | None:

        from facecast.client.fetch import ServerRequestError, fetch_rig

        # Mesh sources need the rig's feature indices; a publisher-only token cannot
        # read rigs, and point sources do not need them.
        with contextlib.suppress(ServerRequestError):
            return fetch_rig(args.url, args.rig, token=args.token).feature_indices
        return None

    return load_animation(
        args.source,
        num_points=num_points,
        feature_indices=feature_indices,
        source_rig=args.source_rig,
        seconds=args.seconds,
        expected_by=f"rig {args.rig!r} needs",
    )


def _schedule(animation: SourceAnimation) -> tuple[np.ndarray, np.ndarray | None, float]:
    """When each frame plays and what ``ts`` it carries, for one pass over ``animation``.

    Returns
    -------
    offsets : (F,) float64
        Seconds after the pass starts: ``timestamps - timestamps[0]``, else ``i / fps``.
    stamps : (F,) float64 or None
        The source's own timestamps, sent as the frames' ``ts`` so watchers see the
        performance's clock; None when it has none (``ts`` is then the wall clock).
    period : float
        Seconds from one pass's start to the next (``--loop``): the take's length plus
        one frame, so timestamps keep increasing across passes.
    """
    stamps = animation.timestamps
    offsets = animation.times - animation.times[0]
    return offsets, stamps, float(offsets[-1]) + 1.0 / animation.fps


async def publish(args: argparse.Namespace) -> tuple[int, PublisherStats, bool, int]:
    """Publish until the animation ends (or forever with ``--loop``).

    Returns (frames sent, the publisher's stats, whether the last frame was answered
    within ``--drain-timeout``, frames neither a result nor a counted drop or refusal).
    """
    import asyncio

    from facecast.client.channel import FramePublisher, channel_url
    from facecast.protocol import Hello

    url = channel_url(args.url, args.channel, "publish")
    async with FramePublisher(url, Hello(rig=args.rig), token=args.token) as publisher:
        ready = publisher.ready
        assert ready is not None
        animation = _animation(args, ready.num_points)
        offsets, stamps, period = _schedule(animation)
        # Not realtime: as fast as the server takes frames, a margin under its max_fps.
        rate = 0.9 * float(ready.limits.get("max_fps", 60.0))
        start = time.perf_counter()
        sent = 0
        passes = 0
        while True:
            for i, points in enumerate(animation.points):
                due = passes * period + offsets[i] if args.realtime else sent / rate
                delay = start + due - time.perf_counter()
                if delay > 0:
                    await asyncio.sleep(delay)
                ts = time.time() if stamps is None else passes * period + stamps[i]
                await publisher.send(points, ts)
                sent += 1
            passes += 1
            if not args.loop:
                break
        # Leave only once the last frame is answered, or the summary misses its result.
        drained = await publisher.drain(args.drain_timeout)
        return sent, publisher.stats, drained, publisher.unaccounted


def run(args: argparse.Namespace) -> int:
    import asyncio

    from facecast.client.connection import ConnectionFailed

    if not 0 <= args.drain_timeout <= 600:  # also refuses NaN
        raise CommandError(f"--drain-timeout must be in [0, 600] seconds, got {args.drain_timeout}")
    try:
        sent, stats, drained, unaccounted = asyncio.run(publish(args))
    except ValueError as exc:  # a malformed URL or channel name
        raise CommandError(str(exc)) from None
    except ConnectionFailed as exc:
        raise CommandError(str(exc)) from None
    if not args.quiet:
        print(
            f"facecast publish: {sent} frames to {args.channel!r} (results back {stats.results}, "
            f"dropped by the server {stats.server_dropped}, refused {stats.refused}, "
            f"dropped while reconnecting {stats.dropped}, reconnects {stats.reconnects}"
            + (f", unaccounted {unaccounted}" if unaccounted else "")
            + ")",
            file=sys.stderr,
        )
        if not drained:
            print(
                f"facecast publish: the last frame's result did not arrive within "
                f"{args.drain_timeout:g} s",
                file=sys.stderr,
            )
    return 0
