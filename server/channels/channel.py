"""One broadcast channel in one process: its members by key, the pump, liveness and face-lost.

A frame is cloned once per watched (rig, output, dtype) and the bytes offered to every
member of that key. No WebSocket I/O here (see ``members``), no registry (see ``hub``): what
it needs of them is its `ChannelContext` and the `ChannelMember` and `ChannelPublisher` shapes.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from facecast.protocol import ChannelIdle, ChannelLive, Error, FaceLost, ProtocolError, encode
from facecast.rig.errors import InputError

from ..compute.cloning import frame_error
from ..compute.stages import CPU_CLOCK
from .bus import SHUTDOWN_STOP_SECONDS, stop_tasks
from .context import ChannelContext, ChannelMember, ChannelPublisher
from .fanout import ChannelFrame, Key, KeyState, PointsKeyState, key_state
from .outbox import offer_results

if TYPE_CHECKING:
    from facecast.rig import Rig

__all__ = ["Channel"]

log = logging.getLogger("facecast.server.channels")

#: A remote publisher is taken as gone when no frame or heartbeat came for this long.
REMOTE_LIVE_SECONDS = 3.0
#: Results a lost face eases with, per second (PROTOCOL.md §5.2.7).
EASE_FPS = 30.0
_RATE_WINDOW = 4  # maintenance snapshots the rates are measured over


class Channel:
    """One channel in this process.

    Frames (from the local publisher, or from another process through the bus) go
    into a one-slot mailbox; the pump clones the newest one once per key in the clone
    threads and offers the bytes to every member of that key. Superseded frames are
    counted in ``dropped``.
    """

    def __init__(self, context: ChannelContext, name: str) -> None:
        self.context = context
        self.name = name
        self.members: dict[Key, set[ChannelMember]] = {}
        self.states: dict[Key, KeyState | PointsKeyState] = {}
        self.publisher: ChannelPublisher | None = None
        self.claimed_by: ChannelPublisher | None = None
        #: Set while a publisher that left is giving its lock back (``hub.claim`` waits).
        self.releasing: asyncio.Event | None = None
        self.remote_live_until = 0.0
        self.live = False
        self.lost = False
        self.last_frame: ChannelFrame | None = None
        self.frames_in = 0
        self.frames_cloned = 0
        self.clones = 0
        self.catchup_clones = 0
        self.results_out = 0
        self.dropped = 0
        self._loop = asyncio.get_running_loop()
        self._pending: tuple[ChannelFrame, float] | None = None
        self._last_arrival = 0.0
        self._last_frame_at = 0.0
        self._frame_in_live = False
        self._catchup: set[Key] = set()
        self._wake = asyncio.Event()
        self._frame_seen = asyncio.Event()
        self._rates: deque[tuple[float, int, int, int, int]] = deque(maxlen=_RATE_WINDOW)
        self.snapshot()
        self._pump = asyncio.create_task(self._pump_loop(), name=f"channel-{name[:32]}-pump")
        self._face: asyncio.Task[None] | None = None

    # -- membership ----------------------------------------------------------------------
    @property
    def empty(self) -> bool:
        return not self.members and self.publisher is None and self.claimed_by is None

    def watchers(self, key: Key | None = None) -> list[ChannelMember]:
        groups = self.members.values() if key is None else [self.members.get(key, set())]
        return [m for group in groups for m in group if m.watcher]

    def _join(self, member: ChannelMember, rig: Rig) -> KeyState | PointsKeyState:
        state = self.states.get(member.key)
        if state is None:
            state = self.states[member.key] = key_state(member.key, rig)
        self.members.setdefault(member.key, set()).add(member)
        self.context.metrics.members.labels(_role(member)).inc()
        return state

    def add_watcher(self, member: ChannelMember, rig: Rig) -> None:
        """Register a watcher whose ``ready`` is already queued; it gets the state at once."""
        state = self._join(member, rig)
        event = ChannelLive if self.live else ChannelIdle
        member.offer(encode(event(channel=self.name)))
        if self.lost and self.last_frame is not None:
            member.offer(encode(FaceLost(since=self.last_frame.ts)))
        if state.last_bytes is not None:
            member.offer_result(state.last_bytes)
        elif self.last_frame is not None:
            # A key nobody watched yet: clone the newest frame for it now.
            self._catchup.add(member.key)
            self._wake.set()

    def remove_member(self, member: ChannelMember) -> None:
        group = self.members.get(member.key)
        if group is None or member not in group:
            return
        group.discard(member)
        self.context.metrics.members.labels(_role(member)).dec()
        if not group:
            del self.members[member.key]
            self.states.pop(member.key, None)
        self.context.on_empty(self)

    async def add_publisher(self, publisher: ChannelPublisher, rig: Rig) -> None:
        self.claimed_by = None
        self.publisher = publisher
        self._join(publisher, rig)
        self.context.bus.send(self.name, "live")
        self.update_live()

    async def remove_publisher(self, publisher: ChannelPublisher) -> None:
        claimed = self.claimed_by is publisher
        if claimed:
            self.claimed_by = None
        if self.publisher is publisher:
            self.publisher = None
            self.remove_member(publisher)
            self.context.bus.send(self.name, "idle")
            self.update_live()
        elif not claimed:
            return
        released = self.releasing = asyncio.Event()
        try:
            await self.context.bus.release(self.name, publisher.owner)
        finally:
            self.releasing = None
            released.set()
        self.context.on_empty(self)

    # -- liveness and face-lost ----------------------------------------------------------
    def update_live(self) -> None:
        live = self.publisher is not None or self.remote_live_until > self._loop.time()
        if live == self.live:
            return
        self.live, self.lost, self._frame_in_live = live, False, False
        if self._face is not None:
            self._face.cancel()
            self._face = None
        if live:
            self._face = asyncio.create_task(
                self._face_watch(), name=f"channel-{self.name[:32]}-face"
            )
        self.broadcast(encode((ChannelLive if live else ChannelIdle)(channel=self.name)))

    def remote_seen(self) -> None:
        """Another process has this channel's publisher (a frame, a heartbeat, its lock)."""
        self.remote_live_until = self._loop.time() + REMOTE_LIVE_SECONDS
        self.update_live()

    def broadcast(self, data: bytes) -> None:
        """Offer one encoded event to every watcher (not to the publisher)."""
        for member in self.watchers():
            member.offer(data)

    async def _face_watch(self) -> None:
        after = self.context.settings.face_lost_after
        while True:
            self._frame_seen.clear()
            if not self._frame_in_live or self.last_frame is None:
                await self._frame_seen.wait()
                continue
            delay = self._last_frame_at + after - self._loop.time()
            if delay > 0:
                # Sleeps to the deadline the newest frame set, then looks again: no wake
                # (a task switch and a timer) per frame.
                await asyncio.sleep(delay)
                continue
            self.lost = True
            self.broadcast(encode(FaceLost(since=self.last_frame.ts)))
            log.info("face lost", extra={"event": "channel.face_lost", "channel": self.name})
            await self._ease(self.last_frame)
            if self.lost:
                await self._frame_seen.wait()

    async def _ease(self, frame: ChannelFrame) -> None:
        """Blend every watched key from the held pose to the neutral over ``face_lost_ease`` s."""
        steps = max(1, round(self.context.settings.face_lost_ease * EASE_FPS))
        for step in range(1, steps + 1):
            alpha = step / steps
            states = [s for k, s in self.states.items() if self.watchers(k)]
            futures = [
                self._loop.run_in_executor(
                    self.context.executor, s.ease, alpha, frame.seq, frame.ts, frame.dropped
                )
                for s in states
            ]
            results = await asyncio.gather(*futures, return_exceptions=True)
            if not self.lost:
                return
            for state, data in zip(states, results, strict=True):
                if isinstance(data, bytes):
                    for member in self.watchers(state.key):
                        member.offer_result(data)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(1.0 / EASE_FPS):
                    await self._frame_seen.wait()
                    return  # a frame arrived: the face is back

    # -- frames --------------------------------------------------------------------------
    def submit(self, frame: ChannelFrame) -> ChannelFrame:
        """A frame from this process's publisher: to the other processes, then here.

        Returns the frame as accepted: when it supersedes a pending one, its ``dropped``
        counts that one too (``accept`` counts it in ``self.dropped``), so the result of
        a burst's last frame carries every frame the burst lost.
        """
        if self._pending is not None:
            frame = dataclasses.replace(frame, dropped=frame.dropped + 1)
        if self.context.bus.distributed:
            # Before ``accept``: the bus's send loop, woken first, writes the frame to
            # Redis before the pump's fan-out holds the loop (`RedisBus` says how).
            self.context.bus.send(self.name, "frame", frame.to_bytes())
        self.accept(frame)
        return frame

    def on_bus(self, kind: str, payload: bytes | None) -> None:
        """An event from another process (see ``bus``)."""
        if kind == "evict":  # our publisher's token came back on another process
            publisher = self.publisher
            if publisher is not None and payload == publisher.owner.encode():
                publisher.supersede()  # if it is silent; the claimant asks again
            return
        if kind == "idle":
            self.remote_live_until = 0.0
            self.update_live()
            return
        if self.publisher is not None:
            return  # split brain (lock lost while Redis was away): ours wins locally
        self.remote_seen()
        if kind == "frame" and payload is not None:
            try:
                frame = ChannelFrame.from_bytes(payload, self.context.max_points)
            except (ValueError, KeyError, TypeError, ProtocolError) as exc:
                log.warning("bad frame from the bus", extra={"event": "channel.bad_frame",
                                                             "error": str(exc)})  # fmt: skip
                return
            self.accept(frame)

    def accept(self, frame: ChannelFrame) -> None:
        now = time.perf_counter()
        if self._pending is not None:
            self.dropped += 1
            self.context.metrics.dropped.labels("channel_superseded").inc()
        self._pending = (frame, now)
        self.last_frame, self._last_arrival = frame, now
        self._last_frame_at = self._loop.time()
        self._frame_in_live = True
        self.frames_in += 1
        self.context.metrics.frames.inc()
        if self.lost:
            self.lost = False
            self.broadcast(encode(ChannelLive(channel=self.name)))
        self._frame_seen.set()
        self._wake.set()

    async def _pump_loop(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            if self._pending is not None:
                frame, arrived = self._pending
                self._pending = None
                self._catchup.clear()  # this frame reaches every key anyway
                await self._clone(frame, arrived, list(self.members), count=True)
            elif self._catchup and self.last_frame is not None:
                keys = list(self._catchup)
                self._catchup.clear()
                await self._clone(self.last_frame, self._last_arrival, keys, count=False)

    async def _clone(
        self, frame: ChannelFrame, arrived: float, keys: list[Key], *, count: bool
    ) -> None:
        states = [self.states[k] for k in keys if k in self.states]
        if not states:
            return
        stages = self.context.metrics.stages
        call: _CloneCall = _clone_call if stages is None else _timed_clone_call
        outcomes: list[bytes | tuple[bytes, float] | BaseException | None] = [None] * len(states)
        threaded: list[tuple[int, asyncio.Future[bytes | tuple[bytes, float]]]] = []
        for i, s in enumerate(states):
            if s.inline(frame):
                # Microseconds (weights, points): here, not through a clone thread,
                # whose round trip costs the loop more than the clone.
                try:
                    outcomes[i] = call(s, frame, arrived, count)
                except Exception as exc:
                    outcomes[i] = exc
            else:
                future = self._loop.run_in_executor(
                    self.context.executor, call, s, frame, arrived, count
                )
                threaded.append((i, future))
        if threaded:
            done = await asyncio.gather(*(f for _, f in threaded), return_exceptions=True)
            for (i, _), got in zip(threaded, done, strict=True):
                outcomes[i] = got
        results: list[bytes | BaseException] = []
        for outcome in outcomes:
            assert outcome is not None  # every state got one above
            if isinstance(outcome, tuple):  # _timed_clone_call's, so stages is set
                encoded, seconds = outcome
                if stages is not None:
                    # A key's clone (its weights, any blend, and its encode) counts as "weights".
                    stages.add("weights", seconds)
                results.append(encoded)
            else:
                results.append(outcome)
        offered = 0
        for state, data in zip(states, results, strict=True):
            if isinstance(data, InputError | ProtocolError):
                self._clone_refused(state, frame, data)
                continue
            if isinstance(data, BaseException):
                log.error("clone failed", exc_info=data,
                          extra={"event": "channel.clone_failed", "rig": state.rig_id})  # fmt: skip
                continue
            state.failing = False
            if stages is None:
                offered += offer_results(self.members.get(state.key, ()), data)
            else:
                writing = CPU_CLOCK()
                n = offer_results(self.members.get(state.key, ()), data)
                stages.add("write", CPU_CLOCK() - writing, n)
                offered += n
        # Counted once per frame, not once per key.
        if offered:
            self.results_out += offered
            self.context.metrics.results.inc(offered)
        # ``output=points`` keys only encode the frame: not clones (PROTOCOL.md §2.4).
        cloned = sum(1 for s in states if s.CLONES)
        if count:
            self.frames_cloned += 1
            self.clones += cloned
            self.context.metrics.clones.inc(cloned)
        else:
            self.catchup_clones += cloned

    def _clone_refused(
        self, state: KeyState | PointsKeyState, frame: ChannelFrame, exc: InputError | ProtocolError
    ) -> None:
        """Tell who must know that ``frame`` gave no result for ``state``'s key."""
        # A ProtocolError here is RESULT_NOT_FINITE: the frame overflows this key's dtype.
        error = frame_error(exc, frame.seq) if isinstance(exc, InputError) else exc
        publisher = self.publisher
        if publisher is not None and publisher.key == state.key:
            publisher.report(error)
        elif not state.failing:
            # Another rig's problem (its K differs from the layout rig's, or the frame
            # overflows its dtype): its watchers are told once per streak; the publisher
            # is not.
            log.warning("frame does not fit a watched rig",
                        extra={"event": "channel.rig_mismatch", "channel": self.name,
                               "rig": state.rig_id, "error": str(exc)})  # fmt: skip
            message = f"the channel's frames do not fit rig {state.rig_id!r}: {exc}"
            if isinstance(exc, ProtocolError):
                message = f"rig {state.rig_id!r}: {exc.message}"
            notice = ProtocolError(error.code, message, seq=frame.seq)
            for member in self.watchers(state.key):
                member.offer(encode(Error.of(notice)))
        state.failing = True

    # -- figures -------------------------------------------------------------------------
    def snapshot(self) -> None:
        self._rates.append((self._loop.time(), self.frames_in, self.results_out,
                            self.clones, self.frames_cloned))  # fmt: skip

    def report(self) -> dict[str, Any]:
        """This process's figures of the channel (JSON-able; also sent to other processes)."""
        t0, f0, r0, c0, n0 = self._rates[0]
        dt = self._loop.time() - t0
        frames = self.frames_cloned - n0
        per_rig: dict[str, int] = {}
        keys = []
        for key, group in sorted(self.members.items()):
            count = sum(1 for m in group if m.watcher)
            if count:
                per_rig[key[0]] = per_rig.get(key[0], 0) + count
            keys.append({"rig": key[0], "output": key[1], "dtype": key[2], "viewers": count})
        everyone = [m for group in self.members.values() for m in group]
        skipped = sum(m.skipped for m in everyone)
        return {
            "publisher": self.live,
            "publisher_here": self.publisher is not None,
            "face_lost": self.lost,
            "viewers": sum(per_rig.values()),
            "viewers_per_rig": per_rig,
            "keys": keys,
            "fps_in": round((self.frames_in - f0) / dt, 2) if dt > 0 else 0.0,
            "fps_out": round((self.results_out - r0) / dt, 2) if dt > 0 else 0.0,
            "frames": self.frames_cloned,
            "dropped": self.dropped,
            "skipped": skipped,
            # The fullest outbox of any member: bounded by members.MAX_OUTBOX.
            "outbox_max": max((m.queued for m in everyone), default=0),
            "clones": self.clones,
            "catchup_clones": self.catchup_clones,
            "clones_per_frame": round((self.clones - c0) / frames, 3)
            if frames
            else (round(self.clones / self.frames_cloned, 3) if self.frames_cloned else 0.0),
        }

    async def stop(self) -> None:
        tasks = [task for task in (self._pump, self._face) if task is not None]
        await stop_tasks(tasks, timeout=SHUTDOWN_STOP_SECONDS)


def _role(member: ChannelMember) -> str:
    return "viewer" if member.watcher else "publisher"


#: A key's clone in a thread or here: its result's bytes (with its seconds when timed).
_CloneCall = Callable[
    [KeyState | PointsKeyState, ChannelFrame, float, bool], bytes | tuple[bytes, float]
]


def _clone_call(
    state: KeyState | PointsKeyState, frame: ChannelFrame, arrived: float, count: bool
) -> bytes:
    return state.clone(frame, arrived, count=count)


def _timed_clone_call(
    state: KeyState | PointsKeyState, frame: ChannelFrame, arrived: float, count: bool
) -> tuple[bytes, float]:
    """``_clone_call`` and its CPU seconds (the clone thread's: the loop adds them up)."""
    started = CPU_CLOCK()
    data = state.clone(frame, arrived, count=count)
    return data, CPU_CLOCK() - started
