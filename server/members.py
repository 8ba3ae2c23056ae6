"""The two kinds of channel connection: a watcher, and the channel's one publisher.

Each has a reader task and a writer task around a bounded outbox (the newest result
replaces an unsent one), so a slow client only ever slows itself. They do no cloning and
no fan-out: frames go to the `Channel`, results come back from it as shared bytes.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
from typing import TYPE_CHECKING, Any

import numpy as np
from starlette.websockets import WebSocket

from facecast.protocol import (
    CHANNEL_OUTPUTS,
    Calibrate,
    Calibrated,
    ErrorCode,
    Frame,
    Hello,
    Limits,
    Ping,
    Pong,
    ProtocolError,
    ServerProtocol,
    close_code,
)
from facecast.rig.errors import InputError, RigError
from facecast.rig.filters import KalmanFilter, OneEuroFilter

from .cloning import frame_error, smoothing_filter
from .fanout import ChannelFrame
from .frame_rate import FrameRateLimit
from .outbox import Closing, Member
from .session import ready_message

if TYPE_CHECKING:
    from .channels import Channel
    from .hub import ChannelHub

__all__ = ["PublisherMember", "WatcherMember"]

log = logging.getLogger("facecast.server.channels")


class WatcherMember(Member):
    """``.../watch``: sends nothing but pings; receives ready, events and results."""

    def __init__(
        self, websocket: WebSocket, channel: Channel, hello: Hello, limits: Limits
    ) -> None:
        super().__init__(websocket, (hello.rig, hello.output, hello.dtype),
                         ServerProtocol(limits, hello=hello))  # fmt: skip
        self.channel = channel

    async def _read_loop(self) -> None:
        while True:
            message = await self.ws.receive()
            if message["type"] == "websocket.disconnect":
                return
            try:
                decoded = self.decode(message)
                if isinstance(decoded, Ping):
                    self.offer(self.protocol.send(Pong(id=decoded.id, ts=decoded.ts)))
            except ProtocolError as exc:
                self.report(exc)

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

    def __init__(self, websocket: WebSocket, hub: ChannelHub, name: str, principal: str) -> None:
        settings = hub.settings
        super().__init__(websocket, ("", "", ""),
                         ServerProtocol(Limits(max_message_bytes=settings.max_message_bytes)))  # fmt: skip
        self.hub = hub
        self.name = name
        self.principal = principal
        self.owner = f"{hub.bus.origin}:{self.id}"
        self.channel: Channel | None = None
        self.hello: Hello | None = None
        self.frames_in = 0
        self.dropped = 0
        self._rig: Any = None
        self._rate = FrameRateLimit(
            settings.max_fps,
            settings.rate_burst,
            total=self._dropped_total,
            tell=lambda error: self.offer(self.protocol.send(error)),
        )
        self._point_filter: OneEuroFilter | KalmanFilter | None = None
        self._neutral: np.ndarray | None = None
        self._neutral_id = ""
        #: The layout rig as the frames see it (calibrated once a neutral is captured):
        #: what their range is checked against before they reach the channel.
        self._range_rig: Any = None
        self._calibrate_next = False

    async def _read_loop(self) -> None:
        timeout = self.hub.settings.idle_timeout
        while True:
            try:
                async with asyncio.timeout(timeout):
                    message = await self.ws.receive()
            except TimeoutError:
                error = ProtocolError(ErrorCode.IDLE_TIMEOUT,
                                      f"no message for {timeout:g} s; closing", fatal=True)  # fmt: skip
                raise Closing(close_code(error), "idle timeout", error) from None
            if message["type"] == "websocket.disconnect":
                return
            try:
                decoded = self.decode(message)
                if isinstance(decoded, Frame):
                    await self._on_frame(decoded)
                elif isinstance(decoded, Ping):
                    self.offer(self.protocol.send(Pong(id=decoded.id, ts=decoded.ts)))
                elif isinstance(decoded, Hello):
                    await self._on_hello(decoded)
                elif isinstance(decoded, Calibrate):
                    await self._on_calibrate(decoded)
            except ProtocolError as exc:
                self.report(exc)

    async def _on_hello(self, hello: Hello) -> None:
        if hello.output not in CHANNEL_OUTPUTS:
            raise ProtocolError(ErrorCode.INVALID_FIELD, f"hello.output {hello.output!r} is "
                                f"for /v1/stream only; a channel serves {list(CHANNEL_OUTPUTS)}",
                                fatal=True)  # fmt: skip
        rig = await self.hub.load_rig(hello.rig)
        # Built before the claim, so a refused smoothing (a Kalman without noise) claims nothing.
        sm = hello.smoothing
        point_filter = smoothing_filter(sm, rig) if sm and sm.target == "points" else None
        channel = await self.hub.claim(self.name, self)  # raises CHANNEL_BUSY / OVERLOADED
        self.hello, self._rig, self.channel = hello, rig, channel
        self._range_rig = rig
        self.key = (hello.rig, hello.output, hello.dtype)
        self._point_filter = point_filter
        self._calibrate_next = hello.calibration
        s = self.hub.settings
        self.offer(self.protocol.send(ready_message(self.id, hello, rig, self.protocol.limits, s)))
        await channel.add_publisher(self, rig)
        log.info("publisher joined",
                 extra={"event": "channel.publish", "channel": self.name, "rig": hello.rig,
                        "by": self.principal})  # fmt: skip

    async def _on_frame(self, frame: Frame) -> None:
        assert self.channel is not None and self.hello is not None
        self.frames_in += 1
        if not self._rate.allow():
            self.dropped += 1
            self.hub.metrics_dropped("rate_limited")
            self._rate.discarded(frame.seq)
            return
        points = frame.points
        if self._calibrate_next:
            self._calibrate_next = False
            if await self._set_neutral(points, frame.seq):
                self.offer(self.protocol.send(Calibrated(active=True, seq=frame.seq)))
        try:
            # Refused here, a frame far outside the layout rig's range (wrong units) never
            # reaches the channel, whose every watched rig would make garbage of it.
            self._range_rig.check_range(points)
        except InputError as exc:
            self.report(frame_error(exc, frame.seq))
            return
        if self._point_filter is not None:
            points = self._point_filter(np.asarray(points, dtype=np.float64).reshape(-1), frame.ts)
            points = points.reshape(frame.points.shape)
        hello = self.hello
        smoothing = (
            hello.smoothing if hello.smoothing and hello.smoothing.target == "weights" else None
        )
        submitted = self.channel.submit(
            ChannelFrame(
                seq=frame.seq, ts=frame.ts, points=points, dropped=self._dropped_total(),
                align=hello.align, scale=hello.align_scale, smoothing=smoothing,
                neutral=self._neutral, neutral_id=self._neutral_id,
                raw_points=frame.points if self._point_filter is not None else None,
                head=frame.head,
            )
        )  # fmt: skip
        # Its result (the newest frame's is never superseded) carries this total.
        self._rate.told(submitted.dropped)
        # Let the pump take this frame before reading the next (pipelined frames are
        # then cloned, not superseded), as /v1/stream does.
        await asyncio.sleep(0)

    def _dropped_total(self) -> int:
        """Frames of this publisher discarded so far: over the rate, or superseded (§8)."""
        return self.dropped + (self.channel.dropped if self.channel is not None else 0)

    async def _set_neutral(self, points: np.ndarray, seq: int | None) -> bool:
        loop = asyncio.get_running_loop()
        try:
            # Checks the neutral on the publisher's rig; every key re-bases its own.
            calibrated = await loop.run_in_executor(self.hub.executor, self._rig.calibrated, points)
        except RigError as exc:
            self.report(ProtocolError(ErrorCode.CALIBRATION_FAILED,
                                      f"calibration failed: {exc}", seq=seq))  # fmt: skip
            return False
        self._range_rig = calibrated
        self._neutral = np.array(points, copy=True)
        self._neutral_id = secrets.token_hex(6)
        return True

    async def _on_calibrate(self, message: Calibrate) -> None:
        if message.reset:
            self._calibrate_next = False
            self._neutral, self._neutral_id = None, ""
            self._range_rig = self._rig
            self.offer(self.protocol.send(Calibrated(active=False)))
        elif message.points is None:
            self._calibrate_next = True
        elif await self._set_neutral(message.points, None):
            self.offer(self.protocol.send(Calibrated(active=True)))

    async def leave(self) -> None:
        # Called when the member ends and again by the route (which covers a failed
        # accept): only the first call leaves, and logs.
        self._rate.close()
        channel, self.channel = self.channel, None
        if channel is not None:
            await channel.remove_publisher(self)
            log.info("publisher left",
                     extra={"event": "channel.unpublish", "channel": self.name,
                            "frames_in": self.frames_in, "dropped": self.dropped})  # fmt: skip
