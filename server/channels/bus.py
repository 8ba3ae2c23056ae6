"""How channel members in different processes meet: an in-process bus, or one on Redis.

Carries small channel events (frames of points, live/idle, heartbeats) and presence
(publisher locks, per-process reports); it never clones, never holds sockets of clients.
Redis going away must not stop the process: every call fails fast and the bus heals itself.
One failed call does not make Redis down (a stall of this process's loop fails every call
it caught in flight): a call started after that failure must fail too (`RedisBus`).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import secrets
import socket
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterable
from typing import Any, TypeVar

import msgpack

from ..errors import BusUnavailable
from ..settings import SettingsError

__all__ = [
    "DOWN_WITHIN",
    "PROBE_INTERVAL",
    "SHUTDOWN_STOP_SECONDS",
    "Bus",
    "BusUnavailable",
    "LocalBus",
    "RedisBus",
    "make_bus",
    "stop_tasks",
]

T = TypeVar("T")

log = logging.getLogger("facecast.server.bus")

#: A publisher lock lives this long unless refreshed (its process died: it frees itself).
LOCK_TTL_MS = 5000
#: A process's report (viewers per rig, rates) lives this long unless refreshed.
REPORT_TTL_MS = 5000
#: Bounds every single Redis call: a hung Redis must not hang a session.
_CALL_TIMEOUT = 1.0
#: How often the bus pings Redis without traffic (and at once after a failed call).
PROBE_INTERVAL = 0.5
#: The longest a Redis that stopped answering is taken for up: the probe's next ping, its
#: 1 s bound, and the 1 s of the ping that confirms it (SERVER.md, "Redis outages and
#: loop stalls"). A Redis that refuses or resets connections is down within the interval.
DOWN_WITHIN = PROBE_INTERVAL + 2 * _CALL_TIMEOUT
#: Frames and events waiting to be published; the oldest go first when Redis is slow.
_MAX_OUTBOX = 256
_BACKOFF_FIRST, _BACKOFF_MAX = 0.1, 2.0

#: How often `stop_tasks` cancels a task again that has not ended.
_RECANCEL_INTERVAL = 0.05
#: How long a task may take to stop at shutdown: past one bounded Redis call and its reply.
SHUTDOWN_STOP_SECONDS = _CALL_TIMEOUT * 2


async def stop_tasks(tasks: Iterable[asyncio.Task[Any]], *, timeout: float) -> None:
    """Cancel ``tasks`` and wait until they end, cancelling again those still running.

    One cancel was not always enough: the bus probe's was seen swallowed inside its ping
    (the task marked cancelling, back in its loop's sleep), and the bus's close, so the
    server's shutdown, waited for it for good (tests gave up after 30 s). Every task that
    awaits Redis runs that risk: the bus's loops, the hub's maintenance, the channels' tasks
    all stop through here at shutdown. Each pass cancels what is left; after ``timeout``
    the rest is logged (``tasks.stuck``) and left behind.
    """
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    pending = {task for task in tasks if not task.done()}
    while pending:
        for task in pending:
            task.cancel()
        left = deadline - loop.time()
        if left <= 0:
            log.error("tasks did not stop", extra={"event": "tasks.stuck",
                      "tasks": sorted(task.get_name() for task in pending)})  # fmt: skip
            return
        _, pending = await asyncio.wait(pending, timeout=min(_RECANCEL_INTERVAL, left))


# Refresh our lock, re-take it if Redis lost it (restart without persistence), else 0.
_REFRESH_LOCK = """
local v = redis.call('get', KEYS[1])
if v == ARGV[1] then return redis.call('pexpire', KEYS[1], ARGV[2]) end
if not v then redis.call('set', KEYS[1], ARGV[1], 'PX', ARGV[2]) return 1 end
return 0
"""
_RELEASE_LOCK = """
if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('del', KEYS[1]) end
return 0
"""

#: on_message(channel name, origin process, kind, payload)
OnMessage = Callable[[str, str, str, bytes | None], None]


def frames_channel(name: str) -> str:
    return f"facecast:channel:{name}:frames"


def lock_key(name: str) -> str:
    return f"facecast:channel:{name}:publisher"


def _process_id() -> str:
    return f"{socket.gethostname()}-{os.getpid()}-{secrets.token_hex(3)}"


class Bus:
    """The in-process interface the channel hub talks to (this base is the no-op of one process)."""

    distributed = False

    def __init__(self) -> None:
        self.origin = _process_id()
        self.on_message: OnMessage | None = None

    async def start(self, on_message: OnMessage) -> None:
        self.on_message = on_message

    async def close(self) -> None:
        pass

    def not_ready_reason(self) -> str | None:
        """Why this process cannot serve channels fully now, or None."""
        return None

    def subscribe(self, name: str) -> None:
        """Receive other processes' events of channel ``name``."""

    def unsubscribe(self, name: str) -> None:
        pass

    def send(self, name: str, kind: str, payload: bytes | None = None) -> None:
        """Hand an event to the other processes; never blocks, may drop when down."""

    async def claim(self, name: str, owner: str) -> bool:
        """Take the channel's publisher lock; False when another owner holds it."""
        return True

    async def refresh(self, name: str, owner: str) -> bool:
        """Keep (or re-take) the lock; False when another owner took it meanwhile."""
        return True

    async def release(self, name: str, owner: str) -> None:
        pass

    async def publisher_present(self, name: str) -> bool:
        """Whether any process holds the channel's publisher lock."""
        return False

    async def holder(self, name: str) -> str | None:
        """The owner holding the channel's publisher lock (None: no one, or one process)."""
        return None

    async def report(self, channels: dict[str, Any]) -> None:
        """Publish this process's per-channel report (viewers per rig, rates)."""

    async def reports(self) -> dict[str, dict[str, Any]]:
        """Every live process's report, by process id (only this one's when local)."""
        return {}


class LocalBus(Bus):
    """Channels of one process: nothing crosses a process boundary."""


class RedisBus(Bus):
    """Channels spanning processes through Redis pub/sub and keys.

    Frames and events go through ``facecast:channel:{name}:frames`` (each process
    subscribes to the channels it has members of); the publisher lock is
    ``facecast:channel:{name}:publisher`` (SET NX PX, refreshed); each process's report
    is ``facecast:proc:{id}`` (JSON, with a TTL). A reader task and a sender task
    reconnect with backoff; ``not_ready_reason`` says when Redis is unreachable.

    Redis is declared down (``bus.down``, ``not_ready_reason``) when a call fails that
    started after an earlier failure was seen: a failure only raises a doubt and wakes the
    probe, whose ping at once confirms it or clears it. Every call caught in flight by one
    stall of this process's loop fails with a timeout, though Redis answered in time; the
    probe's ping after the stall succeeds. A Redis that stopped answering is down within
    ``DOWN_WITHIN``.
    """

    distributed = True

    def __init__(self, url: str) -> None:
        super().__init__()
        # Imported here, not at the top: redis.asyncio takes ~0.2 s to import and a server
        # without a Redis URL (the default) never needs it.
        import redis.asyncio as redis

        self.url = url

        def client(socket_timeout: float | None) -> redis.Redis:
            return redis.Redis.from_url(url, socket_connect_timeout=_CALL_TIMEOUT,
                                        socket_timeout=socket_timeout, retry=None,
                                        health_check_interval=0)  # fmt: skip

        self._redis = client(_CALL_TIMEOUT * 2)
        # Frames leave on a client of their own, without ``socket_timeout``, so that the
        # send loop's first step writes the PUBLISH to the socket. `Channel.submit` wakes
        # the send loop before the pump, so that step runs before this process's fan-out
        # of the same frame (milliseconds with many viewers) and the other processes fan
        # out meanwhile. With a ``socket_timeout`` redis-py writes inside
        # ``asyncio.wait_for``, on Python 3.11 a task of its own: the bytes would wait
        # behind the whole fan-out. Taking the pool's one connection does not suspend
        # while it is up (a connection Redis closed is replaced before the write); the
        # send loop's ``asyncio.timeout`` bounds the write and the reply instead.
        self._publisher = client(None)
        self._names: set[str] = set()
        self._dirty = asyncio.Event()
        self._outbox: deque[tuple[str, bytes]] = deque(maxlen=_MAX_OUTBOX)
        self._has_mail = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []
        self._up = False
        self._reason: str | None = "redis: not connected yet"
        #: When a failure while up was seen and no ping has answered since (loop time).
        self._doubt_since: float | None = None
        #: Wakes the probe to ping at once (a failure to confirm).
        self._check = asyncio.Event()
        self.dropped = 0

    # -- lifecycle ------------------------------------------------------------------------
    async def start(self, on_message: OnMessage) -> None:
        await super().start(on_message)
        self._tasks = [
            asyncio.create_task(self._listen(), name="facecast-bus-listen"),
            asyncio.create_task(self._send_loop(), name="facecast-bus-send"),
            asyncio.create_task(self._probe(), name="facecast-bus-probe"),
        ]

    async def close(self) -> None:
        await stop_tasks(self._tasks, timeout=SHUTDOWN_STOP_SECONDS)
        for client in (self._publisher, self._redis):
            with contextlib.suppress(Exception):
                await client.aclose()

    def not_ready_reason(self) -> str | None:
        return None if self._up else self._reason

    def _failed(self, exc: BaseException, started: float = -math.inf) -> None:
        """A call started at ``started`` (loop time; -inf: unknown) failed with ``exc``."""
        doubt = self._doubt_since
        if not self._up or (doubt is not None and started >= doubt):
            self._down(exc)
            return
        if doubt is None:
            self._doubt_since = asyncio.get_running_loop().time()
            log.info("redis call failed; pinging", extra={"event": "bus.doubt",
                                                          "error": repr(exc)})  # fmt: skip
        self._check.set()

    def _down(self, exc: BaseException) -> None:
        if self._up:
            log.warning("redis unreachable", extra={"event": "bus.down", "error": repr(exc)})
        self._up = False
        self._doubt_since = None
        self._reason = self._unreachable(exc)

    def _unreachable(self, exc: BaseException) -> str:
        return f"redis at {self._safe_url()} unreachable: {type(exc).__name__}"

    def _safe_url(self) -> str:
        # Never log a password embedded in the URL.
        _, sep, tail = self.url.rpartition("@")
        return f"{self.url.split('://')[0]}://***@{tail}" if sep else self.url

    async def _probe(self) -> None:
        """Ping Redis periodically, and at once after a failed call: readiness follows it."""
        loop = asyncio.get_running_loop()
        while True:
            self._check.clear()
            started = loop.time()
            try:
                async with asyncio.timeout(_CALL_TIMEOUT):
                    await self._redis.ping()
                if not self._up:
                    log.info("redis reachable", extra={"event": "bus.up"})
                self._up, self._reason, self._doubt_since = True, None, None
            except Exception as exc:  # any failure means "not usable now"
                self._failed(exc, started)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(PROBE_INTERVAL):
                    await self._check.wait()

    # -- pub/sub --------------------------------------------------------------------------
    def subscribe(self, name: str) -> None:
        self._names.add(name)
        self._dirty.set()

    def unsubscribe(self, name: str) -> None:
        self._names.discard(name)
        self._dirty.set()

    async def _listen(self) -> None:
        backoff = _BACKOFF_FIRST
        while True:
            pubsub = self._redis.pubsub()
            subscribed: set[str] = set()
            try:
                # A control channel keeps the connection subscribed with no channels.
                await pubsub.subscribe("facecast:control")
                while True:
                    if self._dirty.is_set():
                        self._dirty.clear()
                        wanted = set(self._names)
                        add, remove = wanted - subscribed, subscribed - wanted
                        if add:
                            await pubsub.subscribe(*(frames_channel(n) for n in add))
                        if remove:
                            await pubsub.unsubscribe(*(frames_channel(n) for n in remove))
                        subscribed = wanted
                    message = await pubsub.get_message(ignore_subscribe_messages=True, timeout=0.05)
                    backoff = _BACKOFF_FIRST
                    if message is not None and message.get("type") == "message":
                        self._deliver(message["channel"], message["data"])
            except asyncio.CancelledError:
                with contextlib.suppress(Exception):
                    await pubsub.aclose()
                raise
            except Exception as exc:  # connection refused/reset, timeouts: heal below
                self._failed(exc)
                with contextlib.suppress(Exception):
                    await pubsub.aclose()
                # Re-subscribe everything on the next connection.
                self._dirty.set()
                await asyncio.sleep(backoff)
                backoff = min(_BACKOFF_MAX, backoff * 2)

    def _deliver(self, channel: bytes, data: bytes) -> None:
        prefix, suffix = b"facecast:channel:", b":frames"
        if not (channel.startswith(prefix) and channel.endswith(suffix)):
            return
        name = channel[len(prefix) : -len(suffix)].decode("utf-8", "replace")
        try:
            obj = msgpack.unpackb(data, raw=False, max_bin_len=1 << 24, strict_map_key=True)
            origin, kind, payload = obj["o"], obj["k"], obj.get("p")
        except Exception:
            log.warning("bad bus message ignored", extra={"event": "bus.bad_message"})
            return
        if origin == self.origin or self.on_message is None:
            return  # our own events were delivered locally already
        self.on_message(name, origin, kind, payload)

    def send(self, name: str, kind: str, payload: bytes | None = None) -> None:
        if len(self._outbox) == self._outbox.maxlen:
            self.dropped += 1
        data = msgpack.packb({"o": self.origin, "k": kind, "p": payload}, use_bin_type=True)
        self._outbox.append((name, data))
        self._has_mail.set()

    async def _send_loop(self) -> None:
        while True:
            await self._has_mail.wait()
            self._has_mail.clear()
            while self._outbox:
                name, data = self._outbox.popleft()
                started = asyncio.get_running_loop().time()
                try:
                    async with asyncio.timeout(_CALL_TIMEOUT):
                        await self._publisher.publish(frames_channel(name), data)
                except Exception as exc:
                    # Live data: what cannot go now is stale later. Drop and move on.
                    self._failed(exc, started)
                    self.dropped += 1 + len(self._outbox)
                    self._outbox.clear()

    # -- presence -------------------------------------------------------------------------
    async def _call(self, fn: Callable[[], Awaitable[T]]) -> T:
        started = asyncio.get_running_loop().time()
        try:
            async with asyncio.timeout(_CALL_TIMEOUT):
                return await fn()
        except Exception as exc:
            self._failed(exc, started)
            raise BusUnavailable(self._unreachable(exc)) from exc

    async def claim(self, name: str, owner: str) -> bool:
        ok = await self._call(
            lambda: self._redis.set(lock_key(name), owner, nx=True, px=LOCK_TTL_MS)
        )
        return bool(ok)

    async def refresh(self, name: str, owner: str) -> bool:
        ok = await self._call(
            lambda: self._redis.eval(_REFRESH_LOCK, 1, lock_key(name), owner, LOCK_TTL_MS)
        )
        return bool(ok)

    async def release(self, name: str, owner: str) -> None:
        with contextlib.suppress(BusUnavailable):
            await self._call(lambda: self._redis.eval(_RELEASE_LOCK, 1, lock_key(name), owner))

    async def publisher_present(self, name: str) -> bool:
        return bool(await self._call(lambda: self._redis.exists(lock_key(name))))

    async def holder(self, name: str) -> str | None:
        value = await self._call(lambda: self._redis.get(lock_key(name)))
        if isinstance(value, bytes):
            return value.decode("utf-8", "replace")
        return value

    async def report(self, channels: dict[str, Any]) -> None:
        key = f"facecast:proc:{self.origin}"
        body = json.dumps({"at": time.time(), "channels": channels})
        with contextlib.suppress(BusUnavailable):
            await self._call(lambda: self._redis.set(key, body, px=REPORT_TTL_MS))

    async def reports(self) -> dict[str, dict[str, Any]]:
        async def fetch() -> dict[str, dict[str, Any]]:
            keys = [k async for k in self._redis.scan_iter(match="facecast:proc:*", count=100)]
            if not keys:
                return {}
            values = await self._redis.mget(keys)
            out = {}
            for key, value in zip(keys, values, strict=True):
                if value is None:
                    continue
                with contextlib.suppress(ValueError):
                    out[key.decode().removeprefix("facecast:proc:")] = json.loads(value)
            return out

        return await self._call(fetch)


def make_bus(redis_url: str) -> Bus:
    """A `RedisBus` for a ``redis://`` / ``rediss://`` / ``unix://`` URL, else a `LocalBus`."""
    if not redis_url:
        return LocalBus()
    if not redis_url.startswith(("redis://", "rediss://", "unix://")):
        raise SettingsError(
            f"redis_url: expected redis://host:port[/db], rediss://... or unix://..., "
            f"got {redis_url[:60]!r}"
        )
    return RedisBus(redis_url)
