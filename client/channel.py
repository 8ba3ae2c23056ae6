"""WebSocket ends of a broadcast channel for bridges: a frame publisher and a result watcher.

Speaks PROTOCOL.md §2.1 (``/v1/channels/{name}/publish`` and ``.../watch``) with
facecast.protocol's state machines; it must not interpret results (the bridges do) and
never re-encodes messages by hand.

A live source cannot wait: while the publisher is reconnecting, frames are dropped
(counted in ``stats.dropped``), never queued.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncGenerator, Callable, Mapping
from dataclasses import dataclass
from urllib.parse import quote, urlencode

import numpy as np
from websockets.asyncio.client import ClientConnection
from websockets.exceptions import ConnectionClosed

from facecast.protocol import (
    PUBLISH_PATH,
    STREAM_PATH,
    WATCH_PATH,
    Calibrate,
    Calibrated,
    ClientProtocol,
    Error,
    ErrorCode,
    Frame,
    Head,
    Hello,
    Limits,
    Pong,
    ProtocolError,
    Ready,
    Result,
    ServerMessage,
)

from .errors import ConnectionFailed
from .handshake import await_ready, close_websocket, open_websocket
from .reconnect import (
    OPEN_ERRORS,
    RETRYABLE_CODES,
    Reconnect,
    describe,
    reopen_with_backoff,
    supervise,
)
from .urls import auth_headers, resolve_token, stream_url

__all__ = [
    "FramePublisher",
    "PublisherStats",
    "channel_url",
    "watch_channel",
]

log = logging.getLogger("facecast.bridges")

#: Refused ``seq``s a publisher remembers above its newest result (bounded memory).
_MAX_REFUSED_KEPT = 1024
_DEFAULT_RECONNECT = Reconnect()


def channel_url(
    base_url: str, channel: str, kind: str, query: Mapping[str, str] | None = None
) -> str:
    """The WebSocket URL of a channel's ``publish`` or ``watch`` endpoint under ``base_url``.

    ``http://h:p`` + ("stage", "watch", {"rig": "demo"}) ->
    ``ws://h:p/v1/channels/stage/watch?rig=demo``; the name is URL-encoded.
    """
    if kind not in ("publish", "watch"):
        raise ValueError(f"kind must be 'publish' or 'watch', got {kind!r}")
    if not 1 <= len(channel) <= 256:
        raise ValueError(f"a channel name has 1 to 256 characters, got {len(channel)}")
    root = stream_url(base_url)[: -len(STREAM_PATH)]
    template = PUBLISH_PATH if kind == "publish" else WATCH_PATH
    url = root + template.format(name=quote(channel, safe=""))
    return f"{url}?{urlencode(dict(query))}" if query else url


async def _open(
    url: str, token: str | None, limits: Limits, open_timeout: float
) -> ClientConnection:
    return await open_websocket(url, auth_headers(resolve_token(token)), limits, open_timeout)


@dataclass
class PublisherStats:
    """Counters of a `FramePublisher` (all connections)."""

    sent: int = 0
    results: int = 0
    errors: int = 0
    dropped: int = 0
    reconnects: int = 0
    #: Frames the server discarded unprocessed (the newest ``result.dropped``, §8).
    server_dropped: int = 0
    #: Frames the server refused with an error naming their ``seq`` and did not count
    #: in ``dropped`` (invalid frames, §8; ``RATE_LIMITED`` ones are in ``dropped``).
    refused: int = 0


class FramePublisher:
    """Sends frames of points to a publish endpoint; reads and discards the results.

    Parameters
    ----------
    url : str
        Full WebSocket URL: ``channel_url(base, name, "publish")`` (or a
        ``/v1/stream`` URL: the publish endpoint speaks the same protocol).
    hello : Hello
        The session's ``hello`` (rig, options).
    token : str, optional
        Bearer token; default ``FACECAST_TOKEN``.
    reconnect : Reconnect
        How hard to re-open a lost connection.
    open_timeout : float
        Seconds for the handshake plus ``ready``.
    on_result : callable, optional
        Called with every `Result` the server sends back (on the event loop: keep it
        short); results are otherwise discarded, except the last (``last_result``).

    Use ``async with FramePublisher(...) as pub: await pub.send(points, ts)``.
    """

    def __init__(
        self,
        url: str,
        hello: Hello,
        *,
        token: str | None = None,
        reconnect: Reconnect = _DEFAULT_RECONNECT,
        open_timeout: float = 10.0,
        limits: Limits | None = None,
        on_result: Callable[[Result], None] | None = None,
    ) -> None:
        self.url = url
        self.on_result = on_result
        self.hello = hello
        self.token = token
        self.reconnect = reconnect
        self.open_timeout = open_timeout
        self.limits = limits or Limits()
        self.stats = PublisherStats()
        self.ready: Ready | None = None
        #: The filter the server runs on the points (PROTOCOL.md §5.1.1): ``ready``'s,
        #: then the last ``calibrated``'s (an auto smoothing turns Kalman at a calibrate
        #: with a noise, §5.2.5); None without smoothing.
        self.smoothing: str | None = None
        self.last_result: Result | None = None
        self._ws: ClientConnection | None = None
        self._protocol: ClientProtocol | None = None
        self._supervisor: asyncio.Task[None] | None = None
        self._failure: BaseException | None = None
        self._closing = False
        self._seq = 0
        #: Set whenever the server answers a frame (a result or an error naming it).
        self._answer = asyncio.Event()
        #: The highest ``seq`` with a result, and the refused ``seq``s above it (pruned
        #: as results pass them, at most `_MAX_REFUSED_KEPT`): what `drain` waits on.
        self._result_seq = -1
        self._refused_seqs: set[int] = set()
        #: ``result.dropped`` is per session: the totals of earlier connections.
        self._dropped_before = 0
        self._session_dropped = 0
        #: The neutral (and its noise) to re-base on, sent again on every connection.
        self._calibration: Calibrate | None = None

    async def _connect(self) -> None:
        ws = await _open(self.url, self.token, self.limits, self.open_timeout)
        try:
            protocol = ClientProtocol(self.limits)
            await ws.send(protocol.send(self.hello))
            async with asyncio.timeout(self.open_timeout):
                ready = await await_ready(ws, protocol)
        except BaseException:
            await ws.close()
            raise
        if self.ready is not None and ready.num_points != self.ready.num_points:
            await ws.close()
            raise ProtocolError(
                ErrorCode.INVALID_FIELD,
                f"rig {ready.rig!r} changed while reconnecting (K={self.ready.num_points} "
                f"before, {ready.num_points} now)",
                fatal=True,
            )
        if self._calibration is not None:
            # The server forgets a neutral with the connection: restore it before frames.
            try:
                await ws.send(protocol.send(self._calibration))
            except BaseException:
                await ws.close()
                raise
        self.ready = ready
        self.smoothing = ready.smoothing
        self._dropped_before += self._session_dropped
        self._session_dropped = 0
        self._ws, self._protocol = ws, protocol

    async def start(self) -> FramePublisher:
        """Connect and wait for ``ready``.

        Raises
        ------
        ConnectionFailed
            The server cannot be reached or refused the handshake (e.g. HTTP 404 when
            the server has no channels).
        ProtocolError
            The server answered ``hello`` with an error (unknown rig, bad token...).
        """
        try:
            await self._connect()
        except OPEN_ERRORS as exc:
            raise ConnectionFailed(f"cannot publish to {self.url}: {describe(exc)}") from exc
        self._supervisor = asyncio.create_task(self._supervise(), name="facecast-publisher")
        return self

    async def _read_until_lost(self) -> BaseException | None:
        # The socket is forgotten when it ends, not when close() cancels the read: close()
        # must still close it (else the server sees the publisher leave only at its timeout).
        try:
            reason = await self._read()
        except (ConnectionClosed, OSError):
            self._ws = None
            raise
        self._ws = None
        return reason

    async def _read(self) -> BaseException | None:
        assert self._ws is not None and self._protocol is not None
        async for data in self._ws:
            if isinstance(data, str):
                continue
            try:
                message = self._protocol.receive(data)
            except ProtocolError as exc:
                self.stats.errors += 1
                log.warning("publisher: undecodable server message: %s", exc)
                continue
            if isinstance(message, Result):
                self.stats.results += 1
                self._count_dropped(message.dropped)
                self.last_result = message
                if message.seq > self._result_seq:
                    self._result_seq = message.seq
                    self._refused_seqs = {q for q in self._refused_seqs if q > message.seq}
                self._answer.set()
                if self.on_result is not None:
                    self.on_result(message)
            elif isinstance(message, Calibrated):
                if message.smoothing is not None:
                    self.smoothing = message.smoothing
            elif isinstance(message, Error):
                if message.dropped is not None:
                    # RATE_LIMITED carries the running total too: the only report of a
                    # burst's tail, which no later result gives (PROTOCOL.md §8).
                    self._count_dropped(message.dropped)
                    self._answer.set()
                error = message.to_exception()
                if error.fatal:
                    return error
                self.stats.errors += 1
                # An over-rate frame is counted in that total, not refused (§6.1, §8).
                if message.seq is not None and error.code != ErrorCode.RATE_LIMITED:
                    self.stats.refused += 1
                    if message.seq > self._result_seq:
                        if len(self._refused_seqs) >= _MAX_REFUSED_KEPT:
                            self._refused_seqs.discard(min(self._refused_seqs))
                        self._refused_seqs.add(message.seq)
                    self._answer.set()
                log.warning("publisher: server error %s", error)
        return None

    def _count_dropped(self, total: int) -> None:
        # The session's running total; an error may overtake results encoded before it,
        # hence the max (as StreamSession counts it).
        self._session_dropped = max(self._session_dropped, total)
        self.stats.server_dropped = self._dropped_before + self._session_dropped

    async def _supervise(self) -> None:
        try:
            await supervise(self._read_until_lost, self._reconnect, closing=lambda: self._closing)
        except asyncio.CancelledError:
            raise
        except (ProtocolError, ConnectionFailed) as exc:
            self._failure = exc
        except Exception as exc:  # a bug here must still end the publisher loudly
            self._failure = ConnectionFailed(f"the publisher failed: {exc!r}")
        finally:
            self._answer.set()  # a drain() waiting on an answer learns there is none

    async def _reconnect(self, reason: BaseException | None) -> None:
        await reopen_with_backoff(self._connect, self.reconnect, reason, gave_up=self._gave_up)
        self.stats.reconnects += 1
        log.info("publisher: reconnected to %s", self.url)

    def _gave_up(self, last: BaseException | None) -> str:
        return (
            f"lost {self.url} and gave up after {self.reconnect.attempts} attempt(s): "
            f"{'closed' if last is None else describe(last)}"
        )

    @property
    def connected(self) -> bool:
        return self._ws is not None

    @property
    def unaccounted(self) -> int:
        """Frames sent that are neither a result, a counted drop nor a refusal (§8).

        0 once the server has answered everything, unless frames were lost with a
        connection or the server skipped one without counting it.
        """
        stats = self.stats
        return max(0, stats.sent - stats.results - stats.server_dropped - stats.refused)

    def _settled(self) -> bool:
        """Whether every frame is answered: counted (§8), or the last that can still get a
        result has got it."""
        if self.stats.sent and not self.unaccounted:
            return True
        target = self._seq - 1
        while target in self._refused_seqs:
            target -= 1
        return self._result_seq >= target

    async def drain(self, timeout: float) -> bool:
        """Wait until the server has answered every frame sent; False after ``timeout`` s.

        Results come in processing order (§8), so the result of the last frame not
        refused settles every frame before it; a refused (invalid) frame's error comes
        at once and may overtake earlier results, so refusals are skipped, not waited
        for. An over-rate last frame gets no result: it is settled once a `RATE_LIMITED`
        total counts it (within about a second, §8), else the timeout bounds the wait.
        True at once when nothing was sent.
        """
        try:
            async with asyncio.timeout(timeout):
                while not self._settled():
                    if self._failure is not None or self._supervisor is None:
                        return False
                    self._answer.clear()
                    await self._answer.wait()
        except TimeoutError:
            return False
        return True

    async def send(self, points: np.ndarray, ts: float, head: Head | None = None) -> int | None:
        """Send one frame; its ``seq``, or None when it was dropped (reconnecting).

        ``head``: the performer's head pose, relayed to the channel's watchers (§5.3).

        Raises
        ------
        ProtocolError or ConnectionFailed
            The publisher has failed for good (fatal server error, gave up
            reconnecting), or it was closed.
        """
        if self._failure is not None:
            raise self._failure
        if self._closing:
            raise ConnectionFailed("the publisher is closed")
        ws, protocol = self._ws, self._protocol
        if ws is None or protocol is None:
            self.stats.dropped += 1
            return None
        seq = self._seq
        data = protocol.send(Frame(seq=seq, ts=float(ts), points=points, head=head))
        try:
            await ws.send(data)
        except ConnectionClosed:
            self.stats.dropped += 1  # the supervisor notices and reconnects
            return None
        self._seq += 1
        self.stats.sent += 1
        return seq

    async def calibrate(
        self,
        points: np.ndarray,
        noise: float | None = None,
        blinks: Mapping[str, np.ndarray] | None = None,
        blink_contrast: tuple[float, float] | None = None,
    ) -> None:
        """Re-base the channel's rigs on the performer's neutral ``points`` (K, 3).

        ``noise``: the landmark noise measured while the neutral was held; given, every
        watched rig is re-based noise-aware and bounded (PROTOCOL.md §5.1.3), as the
        /perform page asks, and ``blinks`` ({"eyeBlinkLeft" / "eyeBlinkRight": (K, 3)},
        the performer's captured closed eyes) are read as closed on each, through their own
        ``blink_contrast`` curve (low, high) when given. Frames sent after
        this use the neutral (the server handles a publisher's messages in order); it is
        sent again after every reconnection. The server's ``calibrated`` is not awaited; a
        refusal is logged as any error is.
        """
        closed = None if not blinks else {
            name: np.asarray(p, dtype=np.float32) for name, p in blinks.items()
        }  # fmt: skip
        message = Calibrate(
            points=np.asarray(points, dtype=np.float32), noise=noise, blinks=closed,
            blink_contrast=blink_contrast if closed else None,
        )  # fmt: skip
        self._calibration = message
        ws, protocol = self._ws, self._protocol
        if ws is None or protocol is None:
            return  # reconnecting: _connect sends it
        with contextlib.suppress(ConnectionClosed):  # the supervisor reconnects and resends
            await ws.send(protocol.send(message))

    async def close(self) -> None:
        """Close the connection. Idempotent."""
        self._closing = True
        if self._supervisor is not None:
            self._supervisor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._supervisor
        if self._ws is not None:
            await close_websocket(self._ws)
            self._ws = None

    async def __aenter__(self) -> FramePublisher:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


async def watch_channel(
    url: str,
    *,
    token: str | None = None,
    reconnect: Reconnect = _DEFAULT_RECONNECT,
    open_timeout: float = 10.0,
    limits: Limits | None = None,
) -> AsyncGenerator[ServerMessage, None]:
    """The messages a watch endpoint sends: ``ready``, then results and channel events.

    Parameters
    ----------
    url : str
        ``channel_url(base, name, "watch", {"rig": ..., "output": "weights"})``.

    Yields
    ------
    Ready (again after each reconnection), Result, ChannelIdle, ChannelLive, FaceLost,
    and non-fatal Error messages.

    Raises
    ------
    ConnectionFailed
        The first connection failed, or reconnection gave up.
    ProtocolError
        A fatal server error that reconnecting cannot cure (unknown rig, bad token).
    """
    limits = limits or Limits()

    async def open_once() -> tuple[ClientConnection, ClientProtocol, Ready]:
        ws = await _open(url, token, limits, open_timeout)
        try:
            protocol = ClientProtocol(limits, watching=True)
            async with asyncio.timeout(open_timeout):
                ready = await await_ready(ws, protocol)
        except BaseException:
            await ws.close()
            raise
        return ws, protocol, ready

    def gave_up(last: BaseException | None) -> str:
        return f"lost {url} and gave up after {reconnect.attempts} attempt(s)"

    reason: BaseException | None = None
    try:
        ws, protocol, ready = await open_once()
    except OPEN_ERRORS as exc:
        raise ConnectionFailed(f"cannot watch {url}: {describe(exc)}") from exc
    except ProtocolError as exc:
        # Refused once the WebSocket was open: a refusal retrying may cure is a lost
        # connection like any other; the first *connection* is never retried.
        if exc.code not in RETRYABLE_CODES:
            raise
        reason = exc
        ws, protocol, ready = await reopen_with_backoff(
            open_once, reconnect, reason, gave_up=gave_up
        )
    while True:
        fatal: ProtocolError | None = None
        try:
            yield ready
            async for data in ws:
                if isinstance(data, str):
                    continue
                try:
                    message = protocol.receive(data)
                except ProtocolError as exc:
                    log.warning("watcher: undecodable server message: %s", exc)
                    continue
                if isinstance(message, Pong):
                    continue
                if isinstance(message, Error) and message.fatal:
                    fatal = message.to_exception()
                    break
                yield message
        except (ConnectionClosed, OSError):
            pass
        finally:
            await close_websocket(ws)
        if fatal is not None and fatal.code not in RETRYABLE_CODES:
            raise fatal
        ws, protocol, ready = await reopen_with_backoff(
            open_once, reconnect, fatal, gave_up=gave_up
        )
