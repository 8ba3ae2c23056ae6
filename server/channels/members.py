"""The two kinds of channel connection: a watcher, and the channel's one publisher.

Each is a `Member` (``outbox``): the driver's read loop feeds its core (the protocol
rules), and it writes through a bounded outbox where the newest result replaces an
unsent one, so a slow client only ever slows itself. They do no cloning and no fan-out:
frames go to the `Channel`, results come back from it as shared bytes.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections.abc import Awaitable
from concurrent.futures import Executor
from typing import Protocol

import numpy as np
from starlette.websockets import WebSocket

from facecast.protocol import (
    ErrorCode,
    Frame,
    Hello,
    Limits,
    ProtocolError,
    Ready,
    ServerProtocol,
)
from facecast.rig import Rig
from facecast.rig.errors import InputError
from facecast.rig.filters import KalmanFilter

from ..compute.cloning import Smoother, frame_error
from ..connection.core import PublisherCore, WatcherCore
from ..settings import Settings
from .channel import Channel
from .fanout import ChannelFrame
from .outbox import Member
from .stalls import StallClock

__all__ = ["Directory", "PublisherMember", "WatcherMember"]

log = logging.getLogger("facecast.server.channels")

#: Seconds without a message after which a publisher is taken for a connection that
#: blipped: a newer connection with its token may then take its channel (``supersede``).
#: A publisher that sends (frames, pings) keeps its channel against its own token too.
#: Counted while this process's loop runs: its stalls (``stalls``) are not silence.
STALE_AFTER = 1.0


class Directory(Protocol):
    """What a publisher needs of its process's channels (the hub): rigs, claims, services."""

    @property
    def settings(self) -> Settings: ...

    @property
    def executor(self) -> Executor | None: ...

    @property
    def origin(self) -> str: ...

    @property
    def stale_after(self) -> float: ...

    @property
    def stalls(self) -> StallClock: ...

    async def load_rig(self, rig_id: str) -> Rig: ...

    async def claim(self, name: str, publisher: PublisherMember) -> Channel: ...

    def metrics_dropped(self, reason: str) -> None: ...


class WatcherMember(Member):
    """``.../watch``: sends nothing but pings; receives ready, events and results."""

    def __init__(
        self,
        websocket: WebSocket,
        channel: Channel,
        hello: Hello,
        limits: Limits,
        settings: Settings,
    ) -> None:
        core = WatcherCore(ServerProtocol(limits, hello=hello), settings, time.monotonic())
        super().__init__(websocket, (hello.rig, hello.output, hello.dtype), core,
                         secrets.token_hex(8))  # fmt: skip
        self.channel = channel

    def greet(self, ready: Ready) -> None:
        """Queue the ``ready`` the watcher is opened with (before the channel's state)."""
        self.core.send(ready)
        self._deliver()

    async def leave(self) -> None:
        self.channel.remove_member(self)


class PublisherMember(Member):
    """``.../publish``: ``hello`` then frames, like ``/v1/stream``; frames feed the channel.

    Its own results are the channel's results for its hello's (rig, output, dtype): it
    is a member of that key like any watcher, so it costs no extra clone when watchers
    share its key. Options apply channel-wide: ``align``/``scale`` and calibration to
    every key's rig, smoothing of points here (once), smoothing of weights per key.
    """

    watcher = False
    core: PublisherCore

    def __init__(
        self, websocket: WebSocket, directory: Directory, name: str, principal: str
    ) -> None:
        settings = directory.settings
        protocol = ServerProtocol(Limits(max_message_bytes=settings.max_message_bytes))
        core = PublisherCore(protocol, settings, time.monotonic(),
                             idle_timeout=settings.idle_timeout)  # fmt: skip
        super().__init__(websocket, ("", "", ""), core, secrets.token_hex(8), directory.executor)
        core.superseded = self._superseded
        self.directory = directory
        self.name = name
        self.principal = principal
        #: The channel lock's value: this process, this connection, and whose token it is
        #: (a token digest, or "anonymous"), so another process can tell the same caller.
        self.owner = f"{directory.origin}:{self.id}:{principal}"
        #: Set once ``leave`` has given the channel (and its lock) back.
        self.left = asyncio.Event()
        self.channel: Channel | None = None
        self.hello: Hello | None = None
        #: The publisher's smoothing of the points, done once for every key (a `Smoother`:
        #: it starts afresh when ``ts`` goes back, as a stream session's does).
        self._point_filter: Smoother | None = None

    @property
    def frames_in(self) -> int:
        return self.core.counters.frames_in

    @property
    def dropped(self) -> int:
        """Frames of this publisher discarded over the rate."""
        return self.core.counters.dropped_rate

    def _superseded(self) -> int:
        return self.channel.dropped if self.channel is not None else 0

    async def _open(self, hello: Hello) -> None:
        core = self.core
        try:
            rig = await self.directory.load_rig(hello.rig)
            # Built before the claim, so a refused smoothing (a Kalman without noise)
            # claims nothing.
            point_filter = core.point_filter(rig)
            channel = await self.directory.claim(
                self.name, self
            )  # raises CHANNEL_BUSY / OVERLOADED
        except ProtocolError:
            core.failed(time.monotonic())
            raise
        self.hello, self.channel = hello, channel
        self.key = (hello.rig, hello.output, hello.dtype)
        self._point_filter = None if point_filter is None else Smoother(point_filter, "points")
        core.open(rig, time.monotonic(), self.id)
        self._deliver()
        await channel.add_publisher(self, rig)
        log.info("publisher joined",
                 extra={"event": "channel.publish", "channel": self.name, "rig": hello.rig,
                        "by": self.principal})  # fmt: skip

    def _filter_points(self, kalman: KalmanFilter) -> None:
        self._point_filter = Smoother(kalman, "points")

    def _on_frame(self, frame: Frame, now: float, in_burst: bool) -> Awaitable[None]:
        return self._publish(frame, now)

    async def _publish(self, frame: Frame, now: float) -> None:
        """Check ``frame`` (rate, neutral, range), smooth its points, hand it to the channel."""
        arrived = time.time()  # the frame's server_in (§5.4), on the clock pongs tell
        core = self.core
        if not core.frame_allowed(frame, now):
            self.directory.metrics_dropped("rate_limited")
            self._deliver()
            self.arm()
            return
        assert self.channel is not None and self.hello is not None
        points = frame.points
        if core.take_neutral():
            await self._calibrate(points, frame.seq, core.calibrate_noise)
            self._deliver()
        try:
            # Refused here, a frame far outside the layout rig's range (wrong units) never
            # reaches the channel, whose every watched rig would make garbage of it.
            assert core.rig is not None
            core.rig.check_range(points)
        except InputError as exc:
            self.report(frame_error(exc, frame.seq))
            return
        if self._point_filter is not None:
            points = self._point_filter(np.asarray(points, dtype=np.float64), frame.ts)
        hello, smoothing = self.hello, core.channel_smoothing
        submitted = self.channel.submit(
            ChannelFrame(
                seq=frame.seq, ts=frame.ts, points=points, dropped=core.dropped_total(),
                align=hello.align, scale=hello.align_scale, smoothing=smoothing,
                neutral=core.neutral, neutral_noise=core.neutral_noise,
                neutral_blinks=core.neutral_blinks, neutral_contrast=core.neutral_contrast,
                neutral_id=core.neutral_id,
                raw_points=frame.points if self._point_filter is not None else None,
                head=frame.head,
                # Figures only (PROTOCOL.md §5.4): the plausible ones, with our arrival.
                stamps=None if frame.stamps is None else frame.stamps.arrived(arrived),
            )
        )  # fmt: skip
        # Its result (the newest frame's is never superseded) carries this total.
        core.rate.told(submitted.dropped)
        # Let the pump take this frame before reading the next (pipelined frames are
        # then cloned, not superseded), as /v1/stream does.
        await asyncio.sleep(0)

    def supersede(self) -> bool:
        """End this connection if it is silent (the directory's ``stale_after``, ``STALE_AFTER``):
        a newer one with the same token takes its channel. False: it is alive, and keeps
        the channel.

        Silent while this process's loop ran: during a stall of the loop the publisher's
        frames wait unread in the socket, and what wakes first after it (a claim, a bus
        ``evict``) would see the whole stall as silence. A stall of over a second under a
        loaded CI run ended a live publisher that way.
        """
        now = time.monotonic()
        silent = self.directory.stalls.running(self.core.last_message, now)
        if silent < self.directory.stale_after:
            return False
        self.end(ProtocolError(ErrorCode.CHANNEL_BUSY, "a newer connection with the same "
                               "token took over the channel", fatal=True))  # fmt: skip
        return True

    async def leave(self) -> None:
        # Called when the member ends and again by the route (which covers a failed
        # accept): only the first call leaves, and logs.
        channel, self.channel = self.channel, None
        try:
            if channel is not None:
                await channel.remove_publisher(self)
                log.info("publisher left",
                         extra={"event": "channel.unpublish", "channel": self.name,
                                "frames_in": self.frames_in, "dropped": self.dropped})  # fmt: skip
        finally:
            self.left.set()
