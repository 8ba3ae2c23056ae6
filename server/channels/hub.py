"""The channels of one process: creation and removal, rigs, publisher claims, maintenance, figures.

Links the local channels to the other processes through the bus (heartbeats, lock
refreshes, reports) and answers ``GET /v1/channels``; no cloning and no sockets here.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import time
from concurrent.futures import Executor
from typing import TYPE_CHECKING, Any

from facecast.protocol import ErrorCode, ProtocolError
from facecast.rig import Rig

from ..connection.opening import load_rig
from ..settings import Settings
from ..storage.rig_store import RigStore
from .bus import LOCK_TTL_MS, SHUTDOWN_STOP_SECONDS, Bus, BusUnavailable, make_bus, stop_tasks
from .channel import Channel
from .context import ChannelContext, ChannelMetrics, EmptiedChannel
from .members import STALE_AFTER
from .stalls import StallClock, tick_forever

if TYPE_CHECKING:
    from ..metrics import Metrics
    from .members import PublisherMember

__all__ = ["ChannelHub"]

log = logging.getLogger("facecast.server.channels")

#: Heartbeats, lock refreshes and reports to other processes: this often.
MAINTENANCE_INTERVAL = 1.0
#: Seconds a claim waits for a publisher that is leaving to give the channel back (its
#: lock release is one Redis call, which the bus bounds at 1 s) before CHANNEL_BUSY.
RELEASE_WAIT = 1.5
#: Seconds a returning publisher (auth on, same token) waits for its older connection,
#: here or on another process, to be silent for ``members.STALE_AFTER``, ended and give
#: the channel back, or for the lock of a process that died to expire (``LOCK_TTL_MS``),
#: before CHANNEL_BUSY.
RECLAIM_WAIT = LOCK_TTL_MS / 1000 + RELEASE_WAIT
#: How often a claim asks again for a lock another process holds.
_CLAIM_POLL = 0.05
#: How often a claim asks again for that process to end this token's older connection.
_EVICT_AGAIN = 0.5


class ChannelHub:
    """The channels of one process, their rigs, and their link to other processes."""

    def __init__(self, settings: Settings, store: RigStore, metrics: Metrics) -> None:
        self.settings = settings
        self.store = store
        self.metrics = metrics
        self.bus: Bus = make_bus(settings.redis_url)
        self.channels: dict[str, Channel] = {}
        #: What every channel is handed (its clone pool set at ``start``).
        self.context = ChannelContext(
            settings=settings,
            bus=self.bus,
            executor=None,
            metrics=ChannelMetrics.register(metrics, stage_timing=settings.stage_timing),
            on_empty=self.maybe_drop,
        )
        #: ``members.STALE_AFTER`` and ``RECLAIM_WAIT`` for this hub's claims: the tests of
        #: a takeover shorten them on a running server instead of waiting out 6.5 s.
        self.stale_after = STALE_AFTER
        self.reclaim_wait = RECLAIM_WAIT
        #: This process's loop stalls, which a publisher's silence does not count (ticked
        #: from ``start`` on: without ticks all time is taken for a stall).
        self.stalls = StallClock(time.monotonic())
        self._maintenance: asyncio.Task[None] | None = None
        self._ticker: asyncio.Task[None] | None = None
        self._stopping: set[asyncio.Task[None]] = set()

    @property
    def executor(self) -> Executor | None:
        """The clone pool (None before ``start``: asyncio's default)."""
        return self.context.executor

    @property
    def origin(self) -> str:
        """This process's id on the bus (a publisher's lock names it)."""
        return self.bus.origin

    async def start(self, executor: Executor) -> None:
        self.context = dataclasses.replace(self.context, executor=executor)
        if self.settings.workers > 1 and not self.bus.distributed:
            log.warning(
                "channels without --redis are per worker process: a publisher and its "
                "viewers meet only on the same worker",
                extra={"event": "channels.no_redis"},
            )
        self._ticker = asyncio.create_task(tick_forever(self.stalls), name="facecast-stalls")
        await self.bus.start(self._on_bus)
        self._maintenance = asyncio.create_task(self._maintain(), name="facecast-channels")

    async def close(self) -> None:
        tasks = [task for task in (self._maintenance, self._ticker) if task is not None]
        await stop_tasks(tasks, timeout=SHUTDOWN_STOP_SECONDS)
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
            channel = self.channels[name] = Channel(self.context, name)
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

    def maybe_drop(self, channel: EmptiedChannel) -> None:
        """Forget ``channel`` if it is empty and still this process's (its ``on_empty``)."""
        if channel.empty and self.channels.get(channel.name) is channel:
            del self.channels[channel.name]
            self.bus.unsubscribe(channel.name)
            # Keep a reference until done: the loop holds tasks only weakly.
            task = asyncio.get_running_loop().create_task(channel.stop())
            self._stopping.add(task)
            task.add_done_callback(self._stopping.discard)

    async def load_rig(self, rig_id: str) -> Rig:
        """The rig ``rig_id`` (file I/O in a thread); fatal UNKNOWN_RIG if there is none."""
        return await load_rig(self.store, rig_id)

    async def claim(self, name: str, publisher: PublisherMember) -> Channel:
        """Make ``publisher`` the channel's only one, here and (with Redis) everywhere.

        A publisher that is leaving (its connection closed, its lock on its way out, here
        or on another process) is waited for, at most ``RELEASE_WAIT``. With auth on, an
        older connection of the same token (a connection that blipped, not yet noticed
        gone) is ended once it has been silent for ``members.STALE_AFTER`` (this process's
        loop stalls not counted), here or through the bus on another process, and waited
        for, at most ``RECLAIM_WAIT``; one that keeps sending keeps the channel (two pages
        of one performer do not take it from each other in turn). Raises fatal
        CHANNEL_BUSY when another publisher keeps the channel past that, OVERLOADED (retry
        later) when the shared registry cannot be reached to check.
        """
        loop = asyncio.get_running_loop()
        started = loop.time()
        busy = ProtocolError(ErrorCode.CHANNEL_BUSY, f"channel {name[:64]!r} already has a publisher",
                             fatal=True)  # fmt: skip
        # A same-token connection ended (here or elsewhere) earns the longer wait.
        budget, evicted_at = RELEASE_WAIT, -math.inf
        while True:
            channel = self.channel(name)
            holder = channel.publisher
            done: asyncio.Event | None = None
            if channel.releasing is not None:
                done = channel.releasing
            elif holder is not None and holder.ending:
                done = holder.left
            elif holder is not None and self._same_caller(holder.owner, publisher):
                budget = self.reclaim_wait
                if holder.supersede():
                    done = holder.left
                # else it still sends: ask again until it falls silent, or give up
            elif holder is not None or channel.claimed_by is not None:
                raise busy
            elif await self._take(channel, publisher):
                return channel
            else:
                # Another process holds the lock: its publisher leaving, or this token's.
                owner = await self._holder(name)
                if owner is not None and self._same_caller(owner, publisher):
                    budget = self.reclaim_wait
                    if loop.time() - evicted_at >= _EVICT_AGAIN:  # bus events may be lost
                        self.bus.send(name, "evict", owner.encode())
                        evicted_at = loop.time()
            deadline = started + budget
            if loop.time() >= deadline:
                self.maybe_drop(channel)
                raise busy
            if done is None:
                await asyncio.sleep(min(_CLAIM_POLL, deadline - loop.time()))
                continue
            try:
                async with asyncio.timeout_at(deadline):
                    await done.wait()
            except TimeoutError:
                self.maybe_drop(channel)
                raise busy from None

    async def _take(self, channel: Channel, publisher: PublisherMember) -> bool:
        """Take the bus's lock for ``publisher`` (False: another process holds it)."""
        channel.claimed_by = publisher
        try:
            ok = await self.bus.claim(channel.name, publisher.owner)
        except BusUnavailable as exc:
            channel.claimed_by = None
            self.maybe_drop(channel)
            raise ProtocolError(ErrorCode.OVERLOADED, f"channel registry unavailable ({exc}); "
                                "try again later", fatal=True) from None  # fmt: skip
        if not ok:
            channel.claimed_by = None
        return ok

    async def _holder(self, name: str) -> str | None:
        try:
            return await self.bus.holder(name)
        except BusUnavailable:
            return None

    def _same_caller(self, owner: str, publisher: PublisherMember) -> bool:
        """Whether the lock ``owner`` is another connection of ``publisher``'s token.

        Only with auth on: without tokens every caller is "anonymous".
        """
        return (
            self.settings.auth_enabled
            and owner != publisher.owner
            and owner.rpartition(":")[2] == publisher.principal
        )

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
                if channel.publisher is not publisher:
                    # It left while the refresh was on its way, which re-takes a missing
                    # lock (Redis restarted): the leave's release may have gone first,
                    # and the lock must not outlive its publisher for LOCK_TTL_MS.
                    await self.bus.release(channel.name, publisher.owner)
                    continue
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
