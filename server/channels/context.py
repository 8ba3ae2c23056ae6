"""What a channel is given: a frozen context of shared services, and the shapes of its members.

A `Channel` needs the app's settings, the bus, the clone pool, its collectors and a way
to say it is empty; and of its members, only what the protocols below name. It is
handed these, not the hub: the channels package imports one way (hub → members →
channel → context).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Protocol

from prometheus_client import Counter, Gauge

from facecast.protocol import ProtocolError

from ..compute.stages import StageTimes
from ..connection.outbox import Outbox
from ..metrics import Metrics
from ..settings import Settings
from .bus import Bus
from .fanout import Key

__all__ = [
    "ChannelContext",
    "ChannelMember",
    "ChannelMetrics",
    "ChannelPublisher",
    "EmptiedChannel",
]


class EmptiedChannel(Protocol):
    """A channel as its directory sees it when told it is empty (``on_empty``)."""

    @property
    def name(self) -> str: ...

    @property
    def empty(self) -> bool: ...

    async def stop(self) -> None: ...


@dataclass(frozen=True)
class ChannelMetrics:
    """The collectors every channel of an app counts into (registered once, in its registry)."""

    frames: Counter
    clones: Counter
    results: Counter
    members: Gauge
    #: The app's ``facecast_frames_dropped`` (labelled by reason).
    dropped: Counter
    #: Where stage times go, with ``settings.stage_timing`` only.
    stages: StageTimes | None

    @classmethod
    def register(cls, metrics: Metrics, *, stage_timing: bool) -> ChannelMetrics:
        registry = metrics.registry
        return cls(
            frames=Counter(
                "facecast_channel_frames", "Frames received by channels", registry=registry
            ),
            clones=Counter(
                "facecast_channel_clones",
                "Clones of channel frames (one per frame per watched rig/output/dtype)",
                registry=registry,
            ),
            results=Counter(
                "facecast_channel_results", "Results offered to channel members", registry=registry
            ),
            members=Gauge(
                "facecast_channel_members",
                "Connected channel members",
                ["role"],
                registry=registry,
                multiprocess_mode="livesum",
            ),
            dropped=metrics.frames_dropped,
            stages=metrics.stages if stage_timing else None,
        )


@dataclass(frozen=True)
class ChannelContext:
    """What the channels of one process share (the hub builds it; channels only read it).

    Attributes
    ----------
    settings : the app's (``face_lost_after``, ``face_lost_ease``)
    bus : the link to other processes (frames, presence, locks)
    executor : the clone pool (None: asyncio's default, before the app has started)
    metrics : the collectors channels count into
    on_empty : told when a channel has no member, publisher or claim left
    max_points : the largest K a frame from the bus may have
    """

    settings: Settings
    bus: Bus
    executor: Executor | None
    metrics: ChannelMetrics
    on_empty: Callable[[EmptiedChannel], None]
    max_points: int = 4096


class ChannelMember(Protocol):
    """What a channel needs of a member: its key and its outbox."""

    @property
    def key(self) -> Key: ...

    @property
    def outbox(self) -> Outbox: ...

    @property
    def watcher(self) -> bool: ...

    @property
    def skipped(self) -> int: ...

    @property
    def queued(self) -> int: ...

    def offer(self, data: bytes) -> None: ...

    def offer_result(self, data: bytes) -> None: ...


class ChannelPublisher(ChannelMember, Protocol):
    """What a channel (and its claim) needs of its publisher, beyond a member's outbox."""

    @property
    def owner(self) -> str: ...

    @property
    def principal(self) -> str: ...

    @property
    def left(self) -> asyncio.Event: ...

    @property
    def ending(self) -> bool: ...

    def report(self, error: ProtocolError) -> None: ...

    def supersede(self) -> bool: ...

    def end(self, error: ProtocolError) -> None: ...
