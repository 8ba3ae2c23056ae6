"""``facecast perform``: track a webcam (or a video file) and publish the face to a channel.

Reads frames through OpenCV, tracks them with MediaPipe's FaceMesh (``client.facetrack``,
the ``facecast[perform]`` extra), and publishes the layout's feature points with the
bridges' `FramePublisher`, as the /perform page does; it clones nothing.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from facecast.cli.errors import CommandError, TrackerUnavailable

if TYPE_CHECKING:
    from facecast.cli.commands import Subparsers

#: Frames of the held neutral face whose robust average starts a calibrated performance.
NEUTRAL_FRAMES = 15
#: Frames of each held wink (``--winks``) whose robust average is that eye closed.
WINK_FRAMES = 8
#: Seconds to wait at the end for the server's answers to the frames sent (a lost
#: connection's are not waited for): a performance ends with its last frames seen.
DRAIN_SECONDS = 2.0


def blink_contrast_arg(text: str) -> tuple[float, float]:
    """``--blink-contrast LOW,HIGH``: two numbers, 0 <= LOW < HIGH <= 1 (as the server's
    ``closure.check_contrast`` takes them; checked here so a typo stops before the camera,
    or before a benchmark renders anything)."""
    try:
        low, high = (float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOW,HIGH, got {text!r}") from None
    if not 0.0 <= low < high <= 1.0:  # NaN fails every comparison
        raise argparse.ArgumentTypeError(f"expected 0 <= LOW < HIGH <= 1, got {text!r}")
    return low, high


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "perform",
        help="track your face with a webcam and publish it to a channel",
        description=(
            "Track a face with MediaPipe FaceMesh (pip install 'facecast[perform]') from a "
            "webcam or a video file and publish its feature points to channel --channel on "
            "the server at URL, head pose and distance to the camera removed. Viewers of "
            "the channel see their character move. With a character's own rig (e.g. one "
            "imported with `facecast import ict-facekit`) the performance is calibrated on "
            "your neutral face: keep it neutral for the first half second. A rig fitted on "
            "your own expressions (ID@PERFORMER, see `facecast rigs capture`) needs no "
            "calibration."
        ),
    )
    parser.add_argument("url", metavar="URL", help="server base URL, e.g. http://127.0.0.1:8000")
    parser.add_argument("--channel", required=True, metavar="NAME", help="channel to publish to")
    parser.add_argument("--rig", required=True, metavar="ID", help="the rig the points are for")
    source = parser.add_mutually_exclusive_group()
    source.add_argument(
        "--camera", type=int, default=0, metavar="INDEX", help="camera index (default 0)"
    )
    source.add_argument("--video", metavar="FILE", help="read a video file instead of a camera")
    parser.add_argument(
        "--track-between-frames",
        action="store_true",
        help="let MediaPipe crop each frame from the last one's landmarks instead of "
        "detecting the face in every frame (faster, less steady)",
    )
    calibrate = parser.add_mutually_exclusive_group()
    calibrate.add_argument(
        "--calibrate",
        dest="calibrate",
        action="store_true",
        default=None,
        help="re-base the rig on your neutral face first (default: unless ID has @)",
    )
    calibrate.add_argument("--no-calibrate", dest="calibrate", action="store_false")
    parser.add_argument(
        "--neutral-frames",
        type=int,
        default=NEUTRAL_FRAMES,
        metavar="N",
        help=f"calibration: frames of your neutral face to average (default {NEUTRAL_FRAMES})",
    )
    parser.add_argument(
        "--winks",
        action="store_true",
        help="calibration: after the neutral, wink your left eye, then your right, each "
        "held until captured (prompted): a rig re-based on your neutral then reads your own "
        "closed eyes as closed (as /perform's walk-through does)",
    )
    parser.add_argument(
        "--wink-frames",
        type=int,
        default=WINK_FRAMES,
        metavar="N",
        help=f"calibration: frames of each wink to average (default {WINK_FRAMES})",
    )
    parser.add_argument(
        "--blink-contrast",
        type=blink_contrast_arg,
        default=None,
        metavar="LOW,HIGH",
        help="with --winks: your own blink curve, 0 <= LOW < HIGH <= 1 (a blink read at LOW "
        "or less shows open, at HIGH or more closed; default the server's: 0.4,0.8 for a "
        "character whose eyes follow the gaze shapes, 0.4,0.7 for one without them): raise "
        "LOW if the character half-closes its eyes when you look down, lower HIGH if your "
        "blinks do not close them (PROTOCOL.md §5.1.3 blink_contrast)",
    )
    parser.add_argument(
        "--smoothing",
        choices=("auto", "off"),
        default="auto",
        help="the server's live filter of the published points: auto (default: the Kalman "
        "filter, on the rig's fitted noise or, on a character's own rig, on your neutral's; "
        "PROTOCOL.md §5.1.1) or off (viewers get the tracked points as they are)",
    )
    parser.add_argument(
        "--frames", type=int, default=None, metavar="N", help="stop after N frames read"
    )
    parser.add_argument(
        "--seconds", type=float, default=None, metavar="S", help="stop after S seconds"
    )
    parser.add_argument(
        "--token", help="API token with the publisher role (default: FACECAST_TOKEN)"
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="no messages on stderr")
    parser.set_defaults(func=run)


@dataclass
class PerformStats:
    """What a performance did, printed at the end."""

    read: int = 0
    found: int = 0
    two_faces: int = 0
    published: int = 0
    dropped: int = 0
    track_seconds: list[float] = field(default_factory=list)
    started: float = field(default_factory=time.perf_counter)
    #: The server's filter of the points at the end (``FramePublisher.smoothing``).
    smoothing: str | None = None

    def line(self) -> str:
        elapsed = max(time.perf_counter() - self.started, 1e-9)
        track_ms = 1000.0 * sum(self.track_seconds) / max(len(self.track_seconds), 1)
        filtered = "unfiltered" if self.smoothing is None else f"{self.smoothing}-filtered"
        return (
            f"facecast perform: {self.read} frames read, face found in {self.found}, "
            f"{self.published} published ({self.read / elapsed:.1f} fps, tracking "
            f"{track_ms:.1f} ms a frame), dropped while reconnecting {self.dropped}; "
            f"viewers got the points {filtered}"
        )


class _Say:
    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet

    def __call__(self, message: str) -> None:
        if not self.quiet:
            print(f"facecast perform: {message}", file=sys.stderr, flush=True)


def _calibrates(args: argparse.Namespace) -> bool:
    """Whether the performance starts with a neutral (by default unless the rig is a
    performer's own, ID@PERFORMER)."""
    return ("@" not in args.rig) if args.calibrate is None else bool(args.calibrate)


async def perform(args: argparse.Namespace) -> PerformStats:
    """Track and publish until the video ends, ``--frames``/``--seconds``, or Ctrl-C."""
    import asyncio

    import numpy as np

    from facecast.cli.facetrack import FaceTracker, VideoSource
    from facecast.client.channel import FramePublisher, channel_url
    from facecast.protocol import Hello, Smoothing
    from facecast.rig import estimate_noise
    from facecast.rig.sources.capture import WinkCapture, robust_example
    from facecast.rig.sources.layouts import DEFAULT_LAYOUT, load_layout

    say = _Say(args.quiet)
    layout = load_layout(DEFAULT_LAYOUT)
    calibrate = _calibrates(args)
    url = channel_url(args.url, args.channel, "publish")
    source = VideoSource(args.video if args.video is not None else args.camera)
    tracker = FaceTracker(layout, static=not args.track_between_frames)
    stats = PerformStats()
    # The neutral goes in a calibrate with its measured noise (below), not as the first
    # frame (hello.calibration): a rig not fitted on this face is then re-based
    # noise-aware and bounded, never extrapolating for viewers (PROTOCOL.md §5.1.3).
    # Auto smoothing: the server's Kalman filter on the rig's fitted noise, or from the
    # calibrate on with the neutral's (§5.1.1); the viewers' jitter falls ~3x (README, (a″)).
    smoothing = None if args.smoothing == "off" else Smoothing()
    hello = Hello(rig=args.rig, smoothing=smoothing)
    deadline = None if args.seconds is None else time.monotonic() + args.seconds
    with source, tracker:
        async with FramePublisher(url, hello, token=args.token) as publisher:
            ready = publisher.ready
            assert ready is not None
            if not layout.drives(ready.num_points):
                raise CommandError(
                    f"rig {args.rig!r} has {ready.num_points} feature points but the "
                    f"{layout.name} layout has {layout.num_features}: perform on a rig "
                    "fitted with that layout's points (facecast import ict-facekit)"
                )
            # A rig of the layout's earlier version takes the first k points.
            k = ready.num_points
            neutral: list[np.ndarray] = []
            winks: WinkCapture | None = None
            names = layout.feature_names
            lids = {side: (names.index(f"{side}_upper_lid"), names.index(f"{side}_lower_lid"))
                    for side in ("left", "right")}  # fmt: skip
            if calibrate:
                say(f"calibrating: keep a neutral face for {args.neutral_frames} frames")
            face_was_found = None
            frames = source.frames(args.frames)
            while deadline is None or time.monotonic() < deadline:
                # OpenCV's read and the model block for milliseconds: both in a thread.
                rgb = await asyncio.to_thread(next, frames, None)
                if rgb is None:
                    break
                stats.read += 1
                tracked = await asyncio.to_thread(tracker.track, rgb)
                stats.track_seconds.append(tracked.seconds)
                if tracked.faces > 1:
                    if stats.two_faces == 0:
                        say(f"{tracked.faces} faces in view: tracking the largest")
                    stats.two_faces += 1
                found = tracked.points is not None
                if found != face_was_found:
                    say("face found" if found else "no face in view (viewers see face_lost)")
                    face_was_found = found
                if not found:
                    continue  # no frame: the channel's face_lost path eases to the neutral
                stats.found += 1
                points = tracked.points
                assert points is not None  # found
                points = points[:k]
                if calibrate and len(neutral) < args.neutral_frames:
                    neutral.append(points)
                    if len(neutral) < args.neutral_frames:
                        continue
                    # The held neutral's robust average, re-based on with the landmark
                    # noise of its frames; then it is the first frame published.
                    held = np.stack(neutral)
                    points, spread, _ = robust_example(held)
                    noise = estimate_noise(held)
                    await publisher.calibrate(points, noise)
                    say(f"neutral captured (spread {spread:.3f}, landmark noise {noise:.4f})")
                    if args.winks:
                        rest = (points, noise)
                        winks = WinkCapture(points, lids, frames=args.wink_frames)
                        say("now wink: close your left eye and hold it")
                elif winks is not None and winks.wanted is not None:
                    captured = winks.add(points)
                    if captured is not None and winks.wanted is not None:
                        say(f"{captured} captured; now close your right eye and hold it")
                    elif captured is not None:
                        # The neutral again, with the closed eyes it goes with.
                        await publisher.calibrate(
                            *rest, blinks=winks.closed, blink_contrast=args.blink_contrast
                        )
                        say("both winks captured: your closed eyes now read as closed")
                seq = await publisher.send(points.astype(np.float32), time.time())
                if seq is None:
                    stats.dropped += 1
                else:
                    stats.published += 1
            # The last frames' answers (and a calibrate's, saying the filter) before leaving.
            await publisher.drain(DRAIN_SECONDS)
            stats.smoothing = publisher.smoothing
    return stats


def run(args: argparse.Namespace) -> int:
    import asyncio

    from facecast.client.connection import ConnectionFailed
    from facecast.protocol import ProtocolError
    from facecast.rig.errors import InputError

    if args.neutral_frames < 3:
        raise CommandError("--neutral-frames must be at least 3")
    if args.wink_frames < 3:
        raise CommandError("--wink-frames must be at least 3")
    if args.winks and not _calibrates(args):
        raise CommandError(
            "--winks are captured after the neutral: not without calibrating (--no-calibrate, "
            "or a performer's own rig, ID@PERFORMER)"
        )
    if args.blink_contrast is not None and not args.winks:
        raise CommandError("--blink-contrast shapes the winks' closed eyes: it needs --winks")
    if args.frames is not None and args.frames < 1:
        raise CommandError("--frames must be at least 1")
    if args.seconds is not None and not args.seconds > 0:
        raise CommandError("--seconds must be positive")
    try:
        stats = asyncio.run(perform(args))
    except TrackerUnavailable as exc:
        raise CommandError(str(exc)) from None
    except InputError as exc:
        raise CommandError(exc.message) from None
    except ValueError as exc:  # a malformed URL or channel name
        raise CommandError(str(exc)) from None
    except ConnectionFailed as exc:
        raise CommandError(str(exc)) from None
    except ProtocolError as exc:
        raise CommandError(f"the server refused: {exc}") from None
    except KeyboardInterrupt:
        return 130
    if not args.quiet:
        print(stats.line(), file=sys.stderr)
    return 0
