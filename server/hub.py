"""The channels of one process: creation and removal, rigs, publisher claims, maintenance, figures.

Links the local channels to the other processes through the bus (heartbeats, lock
refreshes, reports) and answers ``GET /v1/channels``; no cloning and no sockets here.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from concurrent.futures import Executor
from typing import TYPE_CHECKING, Any

from prometheus_client import Counter, Gauge

from facecast.protocol import ErrorCode, ProtocolError
from facecast.rig import Rig
from facecast.rig.errors import RigError

from .bus import Bus, BusUnavailable, make_bus
from .channels import Channel
from .core import rig_unavailable
from .settings import Settings
from .store import RigNotFoundError, RigStore, valid_rig_id

if TYPE_CHECKING:
    from facecast.rig import Rig

    from .members import PublisherMember
    from .metrics import Metrics

__all__ = ["ChannelHub"]

log = logging.getLogger("facecast.server.channels")

#: Heartbeats, lock refreshes and reports to other processes: this often.
MAINTENANCE_INTERVAL = 1.0


class ChannelHub:
    """The channels of one process, their rigs, and their link to other processes."""

    def __init__(self, settings: Settings, store: RigStore, metrics: Metrics) -> None:
        self.settings = settings
        self.store = store
        self.metrics = metrics
        self.bus: Bus = make_bus(settings.redis_url)
        self.channels: dict[str, Channel] = {}
        self.executor: Executor | None = None
        self.max_points = 4096
        registry = metrics.registry
        self.frames_counter = Counter(
            "facecast_channel_frames", "Frames received by channels", registry=registry
        )
        self.clones_counter = Counter(
            "facecast_channel_clones",
            "Clones of channel frames (one per frame per watched rig/output/dtype)",
            registry=registry,
        )
        self.results_counter = Counter(
            "facecast_channel_results", "Results offered to channel members", registry=registry
        )
        self.members_gauge = Gauge(
            "facecast_channel_members",
            "Connected channel members",
            ["role"],
            registry=registry,
            multiprocess_mode="livesum",
        )
        self._maintenance: asyncio.Task[None] | None = None
        self._stopping: set[asyncio.Task[None]] = set()

    async def start(self, executor: Executor) -> None:
        self.executor = executor
        if self.settings.workers > 1 and not self.bus.distributed:
            log.warning(
                "channels without --redis are per worker process: a publisher and its "
                "viewers meet only on the same worker",
                extra={"event": "channels.no_redis"},
            )
        await self.bus.start(self._on_bus)
        self._maintenance = asyncio.create_task(self._maintain(), name="facecast-channels")

    async def close(self) -> None:
        if self._maintenance is not None:
            self._maintenance.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._maintenance
        for channel in list(self.channels.values()):
            await channel.stop()
        await self.bus.close()

    def not_ready_reason(self) -> str | None:
        return self.bus.not_ready_reason()

    def metrics_dropped(self, reason: str) -> None:
        self.metrics.frames_dropped.labels(reason).inc()

    # -- channels ------------------------------------------------------------------------
    def channel(self, name: str) -> Channel:
        channel = self.channels.get(name)
        if channel is None:
            channel = self.channels[name] = Channel(self, name)
            self.bus.subscribe(name)
        return channel

    async def open_channel(self, name: str) -> Channel:
        """``channel(name)``; a channel new here first learns whether another process publishes.

        Without this a watcher joining a live channel on another process would be told
        ``channel_idle`` until the next heartbeat.
        """
        new = name not in self.channels
        channel = self.channel(name)
        if new and self.bus.distributed:
            with contextlib.suppress(BusUnavailable):
                if await self.bus.publisher_present(name):
                    channel.remote_seen()
        return channel

    def maybe_drop(self, channel: Channel) -> None:
        if channel.empty and self.channels.get(channel.name) is channel:
            del self.channels[channel.name]
            self.bus.unsubscribe(channel.name)
            # Keep a reference until done: the loop holds tasks only weakly.
            task = asyncio.get_running_loop().create_task(channel.stop())
            self._stopping.add(task)
            task.add_done_callback(self._stopping.discard)

    async def load_rig(self, rig_id: str) -> Rig:
        """The rig ``rig_id`` (file I/O in a thread); fatal UNKNOWN_RIG if there is none."""
        if not valid_rig_id(rig_id):
            raise ProtocolError(
                ErrorCode.UNKNOWN_RIG, f"no rig with id {rig_id[:64]!r}", fatal=True
            )
        try:
            rig: Rig = await asyncio.get_running_loop().run_in_executor(
                None, self.store.get, rig_id
            )
            return rig
        except (RigNotFoundError, RigError) as exc:
            raise rig_unavailable(rig_id, exc) from None

    async def claim(self, name: str, publisher: PublisherMember) -> Channel:
        """Make ``publisher`` the channel's only one, here and (with Redis) everywhere.

        Raises fatal CHANNEL_BUSY when another publisher has it, OVERLOADED (retry
        later) when the shared registry cannot be reached to check.
        """
        channel = self.channel(name)
        busy = ProtocolError(ErrorCode.CHANNEL_BUSY, f"channel {name[:64]!r} already has a publisher",
                             fatal=True)  # fmt: skip
        if channel.publisher is not None or channel.claimed_by is not None:
            raise busy
        channel.claimed_by = publisher
        try:
            ok = await self.bus.claim(name, publisher.owner)
        except BusUnavailable as exc:
            channel.claimed_by = None
            self.maybe_drop(channel)
            raise ProtocolError(ErrorCode.OVERLOADED, f"channel registry unavailable ({exc}); "
                                "try again later", fatal=True) from None  # fmt: skip
        if not ok:
            channel.claimed_by = None
            self.maybe_drop(channel)
            raise busy
        return channel

    def _on_bus(self, name: str, origin: str, kind: str, payload: bytes | None) -> None:
        channel = self.channels.get(name)
        if channel is not None:
            channel.on_bus(kind, payload)

    async def _maintain(self) -> None:
        while True:
            await asyncio.sleep(MAINTENANCE_INTERVAL)
            try:
                await self._maintain_once()
            except Exception:  # a bug here must not stop heartbeats for good
                log.exception("channel maintenance failed", extra={"event": "channels.error"})

    async def _maintain_once(self) -> None:
        for channel in list(self.channels.values()):
            channel.update_live()
            channel.snapshot()
            publisher = channel.publisher
            if publisher is None or not self.bus.distributed:
                continue
            self.bus.send(channel.name, "hb")
            try:
                kept = await self.bus.refresh(channel.name, publisher.owner)
            except BusUnavailable:
                continue  # keep publishing locally; re-taken when Redis is back
            if not kept:
                publisher.end(ProtocolError(ErrorCode.CHANNEL_BUSY,
                                            "another publisher took the channel while the "
                                            "registry was unreachable", fatal=True))  # fmt: skip
        if self.bus.distributed:
            await self.bus.report({n: c.report() for n, c in self.channels.items()})

    # -- figures -------------------------------------------------------------------------
    async def _cluster(self) -> dict[str, dict[str, Any]]:
        """Per-process reports by process id: this one's fresh, others' from the bus."""
        reports: dict[str, dict[str, Any]] = {}
        if self.bus.distributed:
            with contextlib.suppress(BusUnavailable):
                for origin, body in (await self.bus.reports()).items():
                    if origin != self.bus.origin:
                        reports[origin] = body.get("channels", {})
        reports[self.bus.origin] = {n: c.report() for n, c in self.channels.items()}
        return reports

    async def info(self, name: str) -> dict[str, Any] | None:
        """The channel's figures: this process's, plus every process's (``processes``)."""
        cluster = await self._cluster()
        per_process = {origin: chans[name] for origin, chans in cluster.items() if name in chans}
        if not per_process:
            return None
        return _combine(name, per_process, self.bus.origin)

    async def list(self) -> list[dict[str, Any]]:
        cluster = await self._cluster()
        names = sorted({n for chans in cluster.values() for n in chans})
        out = []
        for name in names:
            per = {o: chans[name] for o, chans in cluster.items() if name in chans}
            full = _combine(name, per, self.bus.origin)
            out.append({k: full[k] for k in ("name", "publisher", "viewers", "viewers_per_rig")})
        return out


def _combine(name: str, per_process: dict[str, dict[str, Any]], here: str) -> dict[str, Any]:
    local = per_process.get(here) or {}
    per_rig: dict[str, int] = {}
    for report in per_process.values():
        for rig, count in report.get("viewers_per_rig", {}).items():
            per_rig[rig] = per_rig.get(rig, 0) + int(count)
    return {
        "name": name,
        "publisher": any(r.get("publisher") for r in per_process.values()),
        "viewers": sum(per_rig.values()),
        "viewers_per_rig": per_rig,
        **{
            k: local.get(k, 0)
            for k in (
                "fps_in",
                "fps_out",
                "frames",
                "dropped",
                "skipped",
                "outbox_max",
                "clones",
                "catchup_clones",
                "clones_per_frame",
            )
        },
        "face_lost": bool(local.get("face_lost", False)),
        "keys": local.get("keys", []),
        "process": here,
        "processes": [
            {"process": origin, **report} for origin, report in sorted(per_process.items())
        ],
    }
