"""What every tracker bridge in (Live Link Face, iFacialMocap) shares: receive, queue, publish.

A UDP receiver that parses each datagram with a tracker's sans-I/O parser and keeps
the newest frames, and the loop that turns a frame's ARKit weights into points through
a source rig and publishes them. It must not parse any tracker's bytes itself (the
tracker modules do) nor compute cloning weights (the server does).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Generic, Protocol, TypeVar, cast

import numpy as np

from facecast.client.channel import FramePublisher
from facecast.errors import FacecastError
from facecast.rig.sources.source_rig import SourceRig

from .head_pose import head_pose as head_pose_of

__all__ = [
    "BridgeStats",
    "DatagramReceiver",
    "HeadSink",
    "TrackerFrame",
    "TrackerPacketError",
    "open_receiver",
    "run_tracker_bridge",
]

log = logging.getLogger("facecast.bridges")


class TrackerPacketError(FacecastError, ValueError):
    """A datagram that is not a valid packet of its tracker; ``code`` says why."""

    code: str = "bad_tracker_packet"

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class TrackerFrame(Protocol):
    """What the bridge loop reads from a parsed packet (a frozen dataclass)."""

    @property
    def weights(self) -> np.ndarray | None: ...  # (52,) ARKit order, None: no face

    @property
    def head(self) -> np.ndarray | None: ...  # (>= 3,) head yaw, pitch, roll, radians

    @property
    def received(self) -> float: ...  # time.monotonic() at arrival


FrameT = TypeVar("FrameT")
TrackerFrameT = TypeVar("TrackerFrameT", bound=TrackerFrame)
#: Called with each published frame's head (yaw, pitch, roll) radians, e.g. a VMC sender.
HeadSink = Callable[[np.ndarray], None]


class DatagramReceiver(asyncio.DatagramProtocol, Generic[FrameT]):
    """Receives a tracker's packets; keeps the newest ``max_queue`` frames.

    A live source must not build up latency: when the consumer falls behind, the
    oldest waiting frame is dropped (``dropped``). Malformed packets are counted
    (``malformed``, ``last_error``) and logged at most once a second, never raised.
    Build with `open_receiver`.
    """

    def __init__(
        self, parse: Callable[[bytes], FrameT], max_queue: int = 4, *, what: str = "tracker"
    ) -> None:
        if max_queue < 1:
            raise ValueError(f"max_queue must be >= 1, got {max_queue}")
        self._parse = parse
        self._what = what
        self._frames: deque[FrameT] = deque(maxlen=max_queue)
        self._arrived = asyncio.Event()
        self._transport: asyncio.DatagramTransport | None = None
        self._last_log = -math.inf
        self.received = 0
        self.malformed = 0
        self.dropped = 0
        self.last_error: TrackerPacketError | None = None
        #: ``time.monotonic()`` of the last datagram, good or bad (-inf: none yet).
        self.last_datagram = -math.inf

    def connection_made(self, transport: asyncio.BaseTransport) -> None:  # asyncio callback
        # A datagram endpoint's transport (asyncio types the callback for every protocol).
        self._transport = cast(asyncio.DatagramTransport, transport)

    def datagram_received(
        self, data: bytes, addr: tuple[str | Any, int]
    ) -> None:  # asyncio callback
        now = time.monotonic()
        self.last_datagram = now
        try:
            frame = self._parse(data)
        except TrackerPacketError as exc:
            self.malformed += 1
            self.last_error = exc
            if now - self._last_log >= 1.0:
                self._last_log = now
                log.warning(
                    "ignoring a bad %s packet from %s: %s (%s)", self._what, addr, exc, exc.code
                )
            return
        self.received += 1
        if len(self._frames) == self._frames.maxlen:
            self.dropped += 1
        self._frames.append(replace(frame, received=now))  # type: ignore[type-var]
        self._arrived.set()

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) actually bound (the port chosen by the OS when 0 was asked)."""
        assert self._transport is not None
        host, port = self._transport.get_extra_info("sockname")[:2]
        return host, port

    def send(self, data: bytes, address: tuple[str, int]) -> None:
        """Send a datagram from the bound socket (a tracker app's "start streaming")."""
        assert self._transport is not None
        self._transport.sendto(data, address)

    async def get(self, timeout: float | None = None) -> FrameT:
        """The oldest waiting frame; waits for one (TimeoutError after ``timeout``)."""
        async with asyncio.timeout(timeout):
            while not self._frames:
                self._arrived.clear()
                await self._arrived.wait()
        return self._frames.popleft()

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()


async def open_receiver(
    receiver: DatagramReceiver[FrameT], host: str, port: int
) -> DatagramReceiver[FrameT]:
    """Bind a UDP socket on (host, port) and let ``receiver`` receive on it."""
    loop = asyncio.get_running_loop()
    await loop.create_datagram_endpoint(lambda: receiver, local_addr=(host, port))
    return receiver


@dataclass
class BridgeStats:
    """What a bridge loop did."""

    frames: int = 0
    published: int = 0
    skipped: int = 0


async def run_tracker_bridge(
    receiver: DatagramReceiver[TrackerFrameT],
    source_rig: SourceRig,
    publisher: FramePublisher,
    *,
    head_pose: bool = False,
    accept: Callable[[TrackerFrameT], bool] | None = None,
    on_head: HeadSink | None = None,
    max_frames: int | None = None,
) -> BridgeStats:
    """Receive frames, turn them into points, publish them; until cancelled or ``max_frames``.

    Parameters
    ----------
    head_pose : bool
        Rotate the points by the frame's head yaw/pitch/roll (open the session with
        ``align`` so the server removes it again); off: the head stays still. Either
        way the head rotation goes out as the frame's ``head`` (PROTOCOL.md §5.3), for
        the watchers' avatar apps.
    accept : callable, optional
        Frames for which it returns False are skipped (e.g. another subject).
    on_head : callable, optional
        Called with every published frame's (3,) head yaw, pitch, roll in radians.
    max_frames : int, optional
        Return after this many frames with a face were published or dropped.

    Each frame is sent as float32 points with ``ts`` = its arrival time on this
    machine's monotonic clock, so latency is measured on one clock.
    """
    stats = BridgeStats()
    while max_frames is None or stats.frames < max_frames:
        frame = await receiver.get()
        if frame.weights is None or (accept is not None and not accept(frame)):
            stats.skipped += 1
            continue
        head = frame.head[:3] if frame.head is not None else None
        # ~52 x 3K multiply-adds: microseconds, fine on the event loop.
        points = source_rig.points(frame.weights, head=head if head_pose else None)
        stats.frames += 1
        pose = None if head is None else head_pose_of(head)
        sent = await publisher.send(points.astype(np.float32), ts=frame.received, head=pose)
        if sent is not None:
            stats.published += 1
        if on_head is not None and head is not None:
            on_head(head)
    return stats
