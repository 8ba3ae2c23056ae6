"""The asyncio client of ``WS /v1/stream``: one session that sends frames and receives results.

Reconnects with exponential backoff and keeps sequence numbers and latency statistics
across connections; bytes are facecast.protocol's (PROTOCOL.md), never re-encoded here.

Use as a context manager (or ``session = await connect(...)`` then ``await
session.close()``)::

    async with connect("http://127.0.0.1:8000", rig="demo") as session:
        result = await session.clone(points)          # request/response
        for i, p in enumerate(frames):                # pipelined
            await session.send(p, seq=i)
        async for result in session: ...

Errors, by kind:

- a non-fatal server ``error`` (bad frame, rate limited, ...) is raised from `receive`
  / the ``async for`` loop as `ProtocolError` (``fatal=False``, with ``seq`` when it is
  about one frame); the session stays open. ``receive(errors="return")`` and
  ``results(errors="return")`` hand it back as a value instead.
- a fatal ``error`` whose code is in `RETRYABLE_CODES` (server overloaded, idle, internal)
  or a dropped connection starts reconnection; any other fatal error (unknown rig, bad
  token) is raised as `ProtocolError` from every later call.
- when reconnection gives up, every later call raises `ConnectionFailed`.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import time
from collections.abc import AsyncIterator, Generator
from typing import Any, Literal

import numpy as np
from websockets.asyncio.client import ClientConnection
from websockets.exceptions import ConnectionClosed

from facecast.protocol import (
    Calibrate,
    Calibrated,
    ClientProtocol,
    Error,
    ErrorCode,
    Frame,
    Hello,
    Limits,
    Ping,
    Pong,
    ProtocolError,
    Ready,
    Result,
    Smoothing,
)

from .errors import ConnectionFailed
from .handshake import await_ready, close_websocket, open_websocket
from .latency import LatencyTracker
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
    "RETRYABLE_CODES",
    "ConnectionFailed",
    "Reconnect",
    "StreamSession",
    "connect",
]

#: Server results kept waiting for the application; the reader stops reading beyond
#: this, so TCP pushes back and the server's newest-frame policy drops, not our memory.
DEFAULT_MAX_QUEUE = 256

_DEFAULT_RECONNECT = Reconnect()


class _Marker:
    def __init__(self, name: str) -> None:
        self.name = name

    def __repr__(self) -> str:
        return f"<{self.name}>"


#: Queue items that are not results: the session ended; a new connection was opened.
_END = _Marker("end")
_RECONNECTED = _Marker("reconnected")


class StreamSession:
    """One logical streaming session, kept open across reconnections.

    Build it with `connect`. Attributes worth reading:

    Attributes
    ----------
    ready : Ready
        The server's ``ready`` of the first connection: rig id, names (M), K, V, output,
        dtype and the server's limits.
    latency : LatencyTracker
        Round-trip times by ``seq``; ``latency.stats()`` gives p50/p95/p99/max.
    reconnects : int
        Connections re-opened after a loss.
    lost_in_flight : int
        Frames in flight when a connection was lost (they get no result).
    """

    def __init__(
        self,
        url: str,
        hello: Hello,
        *,
        token: str | None,
        reconnect: Reconnect,
        open_timeout: float,
        max_queue: int,
        limits: Limits,
    ) -> None:
        self.url = url
        self.hello = hello
        self.reconnect = reconnect
        self.open_timeout = open_timeout
        self.max_queue = max_queue
        self.limits = limits
        self._headers = auth_headers(token)
        self.ready: Ready | None = None
        self.latency = LatencyTracker()
        self.reconnects = 0
        self.lost_in_flight = 0
        self._ws: ClientConnection | None = None
        self._protocol: ClientProtocol | None = None
        self._queue: asyncio.Queue[Any] = asyncio.Queue()
        self._room = asyncio.Event()
        self._connected = asyncio.Event()
        self._failed = asyncio.Event()
        self._failure: BaseException | None = None
        self._closing = False
        self._supervisor: asyncio.Task[None] | None = None
        self._next_seq = 0
        self._t0 = time.perf_counter()
        self._dropped_before = 0  # server drop counts of connections already closed
        self._dropped_now = 0
        self._ping_ids = itertools.count()
        self._pings: dict[int, asyncio.Future[float]] = {}
        self._calibrations: list[asyncio.Future[Calibrated]] = []
        self._calibration_points: np.ndarray | None = None

    # -- opening -------------------------------------------------------------------------
    async def _start(self) -> None:
        try:
            await self._open()
        except OPEN_ERRORS as exc:
            raise ConnectionFailed(
                f"cannot open a session at {self.url}: {describe(exc)}", last_error=exc
            ) from exc
        self._supervisor = asyncio.create_task(self._supervise(), name="facecast-client")

    async def _open(self) -> None:
        """Connect, send ``hello``, wait for ``ready``; raises on any failure."""
        ws = await open_websocket(self.url, self._headers, self.limits, self.open_timeout)
        try:
            protocol = ClientProtocol(self.limits)
            # A refusing server sends its error and closes at once: still read that error.
            with contextlib.suppress(ConnectionClosed):
                await ws.send(protocol.send(self.hello))
            async with asyncio.timeout(self.open_timeout):
                ready = await await_ready(ws, protocol)
            self._check_same_rig(ready)
            if self._calibration_points is not None:
                # The server forgets calibration with the connection: restore it.
                await ws.send(protocol.send(Calibrate(points=self._calibration_points)))
        except BaseException:
            await ws.close()
            raise
        self._ws, self._protocol = ws, protocol
        self._connected.set()

    def _check_same_rig(self, ready: Ready) -> None:
        if self.ready is None:
            self.ready = ready
            return
        old = self.ready
        if (ready.names, ready.num_points, ready.num_vertices, ready.result_vertices) != (
            old.names,
            old.num_points,
            old.num_vertices,
            old.result_vertices,
        ) or (
            ready.moving is not None
            and (old.moving is None or not np.array_equal(ready.moving, old.moving))
        ):
            raise ProtocolError(
                ErrorCode.INVALID_FIELD,
                f"rig {ready.rig!r} changed on the server while reconnecting "
                f"(M={old.num_examples}, K={old.num_points} before; "
                f"M={ready.num_examples}, K={ready.num_points} now)",
                fatal=True,
            )

    # -- the reader and reconnection ---------------------------------------------------
    async def _supervise(self) -> None:
        try:
            await supervise(self._read_open, self._reconnect,
                            closing=lambda: self._closing, lost=self._connection_lost)  # fmt: skip
        except asyncio.CancelledError:
            raise
        except (ProtocolError, ConnectionFailed) as exc:
            self._fail(exc)
        except Exception as exc:  # a bug here must still end the session loudly
            self._fail(ConnectionFailed(f"the client reader failed: {exc!r}", last_error=exc))

    async def _read_open(self) -> BaseException | None:
        assert self._ws is not None and self._protocol is not None
        return await self._read(self._ws, self._protocol)

    async def _read(self, ws: ClientConnection, protocol: ClientProtocol) -> BaseException | None:
        """Read until the connection ends; the fatal error that ended it, if any."""
        async for data in ws:
            if isinstance(data, str):
                await self._deliver(
                    ProtocolError(ErrorCode.TEXT_NOT_SUPPORTED, "server sent a text message")
                )
                continue
            try:
                message = protocol.receive(data)
            except ProtocolError as exc:
                await self._deliver(exc)
                continue
            if isinstance(message, Result):
                self.latency.received(message.seq)
                self._dropped_now = max(self._dropped_now, message.dropped)
                await self._deliver(message)
            elif isinstance(message, Error):
                if message.dropped is not None:
                    # RATE_LIMITED carries the total too: the frames of a burst's tail,
                    # which no later result reports (PROTOCOL.md §8). It may overtake
                    # results encoded before it, hence the max.
                    self._dropped_now = max(self._dropped_now, message.dropped)
                error = message.to_exception()
                if error.fatal:
                    return error
                await self._deliver(error)
            elif isinstance(message, Pong):
                pinged = self._pings.pop(message.id, None)
                if pinged is not None and not pinged.done():
                    pinged.set_result(time.perf_counter() - message.ts)
            elif isinstance(message, Calibrated):
                while self._calibrations:
                    calibrating = self._calibrations.pop(0)
                    if not calibrating.done():
                        calibrating.set_result(message)
                        break
        return None

    def _connection_lost(self) -> None:
        self._connected.clear()
        self.lost_in_flight += self.latency.forget()
        self._dropped_before += self._dropped_now
        self._dropped_now = 0
        if self._protocol is not None:
            self._protocol.close()

    async def _reconnect(self, reason: BaseException | None) -> None:
        await reopen_with_backoff(self._open, self.reconnect, reason, gave_up=self._gave_up)
        self.reconnects += 1
        self._queue.put_nowait(_RECONNECTED)

    def _gave_up(self, last: BaseException | None) -> str:
        why = "the connection closed" if last is None else describe(last)
        return (
            f"lost the session at {self.url} and gave up after "
            f"{self.reconnect.attempts} reconnection attempt(s); last error: {why}"
        )

    async def _deliver(self, item: Any) -> None:
        while self._queue.qsize() >= self.max_queue:
            self._room.clear()
            await self._room.wait()
        self._queue.put_nowait(item)

    def _fail(self, exc: BaseException) -> None:
        self._failure = exc
        self._failed.set()
        self._queue.put_nowait(_END)
        waiters: list[asyncio.Future[Any]] = [*self._pings.values(), *self._calibrations]
        for future in waiters:
            if not future.done():
                future.set_exception(exc)
        self._pings.clear()
        self._calibrations.clear()

    def _raise_if_done(self) -> None:
        if self._failure is not None:
            raise self._failure
        if self._closing:
            raise ConnectionFailed("the session is closed")

    async def _wait_connected(self) -> None:
        self._raise_if_done()
        if self._connected.is_set():
            return
        waiters = {
            asyncio.ensure_future(self._connected.wait()),
            asyncio.ensure_future(self._failed.wait()),
        }
        try:
            await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiter in waiters:
                waiter.cancel()
        self._raise_if_done()

    # -- sending -------------------------------------------------------------------------
    @property
    def num_points(self) -> int:
        """K, the feature points each frame must carry."""
        assert self.ready is not None
        return self.ready.num_points

    @property
    def names(self) -> tuple[str, ...]:
        """The rig's M example names (``names[0]`` is the neutral)."""
        assert self.ready is not None
        return self.ready.names

    @property
    def moving(self) -> np.ndarray | None:
        """With output "moving": the (N,) indices of the vertices results carry, else None."""
        assert self.ready is not None
        return self.ready.moving

    def full_vertices(self, vertices: np.ndarray, neutral: np.ndarray) -> np.ndarray:
        """The whole mesh of a "moving" result: ``neutral`` with ``vertices`` at ``moving``.

        Parameters
        ----------
        vertices : (N, 3) or (F, N, 3) float
            Results' vertices, in the order of ``moving``.
        neutral : (V, 3) float
            The target's neutral mesh (``Rig.target_neutral``, or the model's positions).

        Returns
        -------
        (V, 3) or (F, V, 3) float32: equal to a "vertices" result of the same frames
        (bit for bit in f32: the vertices not sent are the neutral's in every blend).
        """
        moving, ready = self.moving, self.ready
        if moving is None or ready is None:
            raise ValueError("full_vertices needs a session whose output is moving")
        vertices = np.asarray(vertices)
        neutral = np.asarray(neutral, dtype=np.float32)
        if neutral.shape != (ready.num_vertices, 3) or vertices.shape[-2:] != (
            moving.size,
            3,
        ):
            raise ValueError(
                f"expected vertices (..., {moving.size}, 3) and a neutral "
                f"({ready.num_vertices}, 3), got {vertices.shape} and {neutral.shape}"
            )
        full = np.array(np.broadcast_to(neutral, (*vertices.shape[:-2], *neutral.shape)))
        full[..., moving, :] = vertices
        return full

    @property
    def dropped(self) -> int:
        """Frames the server reported dropping (newest-frame policy, rate limit), all connections."""
        return self._dropped_before + self._dropped_now

    @property
    def next_seq(self) -> int:
        """The ``seq`` the next `send` without one will use."""
        return self._next_seq

    @property
    def close_code(self) -> int | None:
        """How the last connection ended: 1000 when both sides closed it, 1006 when the
        closing handshake did not complete; None while it is open or before one opened."""
        return None if self._ws is None else self._ws.close_code

    @property
    def connected(self) -> bool:
        """True while a connection is open (False while reconnecting or after failure)."""
        return self._connected.is_set()

    def _frame_points(self, points: Any) -> np.ndarray:
        array = np.asarray(points)
        if array.dtype.kind != "f" or array.dtype.itemsize not in (2, 4, 8):
            array = array.astype(np.float64)
        k = self.num_points
        if array.shape != (k, 3):
            raise ProtocolError(
                ErrorCode.WRONG_POINT_COUNT,
                f"points must have shape ({k}, 3) for rig {self.hello.rig!r}, got {array.shape}",
            )
        return array

    async def send(self, points: Any, *, seq: int | None = None, t: float | None = None) -> int:
        """Send one frame without waiting for its result.

        Parameters
        ----------
        points : (K, 3) float16/32/64
            Feature points, sent in their own float dtype (other dtypes as float64).
        seq : int, optional
            Sequence number; default one more than the last sent. Later frames without
            ``seq`` continue from it.
        t : float, optional
            Source timestamp, seconds, echoed in the result; default seconds since the
            session opened.

        Returns
        -------
        int
            The frame's ``seq``.

        While the session is reconnecting this waits until it is open again. A frame
        sent into a connection that is just being lost gets no result, like a frame the
        server drops (`lost_in_flight` counts them).
        """
        array = self._frame_points(points)
        seq = self._next_seq if seq is None else seq
        ts = time.perf_counter() - self._t0 if t is None else t
        frame = Frame(seq=seq, ts=ts, points=array)
        await self._wait_connected()
        assert self._ws is not None and self._protocol is not None
        data = self._protocol.send(frame)
        self._next_seq = seq + 1
        self.latency.sent(seq)
        # The reader notices a closed connection and reconnects; the frame is lost then.
        with contextlib.suppress(ConnectionClosed):
            await self._ws.send(data)
        return seq

    # -- receiving -----------------------------------------------------------------------
    async def _next_item(self) -> Any:
        item = await self._queue.get()
        self._room.set()
        if item is _END:
            self._queue.put_nowait(_END)  # every later call sees the end too
        return item

    async def receive(
        self, *, errors: Literal["raise", "return"] = "raise", timeout: float | None = None
    ) -> Result | ProtocolError:
        """The next result, in the order the server sent them.

        Parameters
        ----------
        errors : {"raise", "return"}
            What to do with a non-fatal server error: raise it (default), or return the
            `ProtocolError` in place of a result.
        timeout : float, optional
            Seconds to wait; `TimeoutError` after.

        Raises
        ------
        ProtocolError
            A server error (non-fatal ones only with ``errors="raise"``; fatal ones
            always, after which the session is over).
        ConnectionFailed
            Reconnection gave up, or the session was closed.
        """
        async with asyncio.timeout(timeout):
            while True:
                if self._closing and self._queue.empty():
                    self._raise_if_done()
                item = await self._next_item()
                if item is _RECONNECTED:
                    continue
                if item is _END:
                    self._raise_if_done()
                if isinstance(item, ProtocolError) and errors == "raise":
                    raise item
                assert isinstance(item, Result | ProtocolError), item
                return item

    async def results(
        self, errors: Literal["raise", "return"] = "raise"
    ) -> AsyncIterator[Result | ProtocolError]:
        """Results (and, with ``errors="return"``, non-fatal errors) until the session ends.

        Ends quietly when the session is closed by `close`; raises like `receive`
        otherwise.
        """
        while True:
            try:
                yield await self.receive(errors=errors)
            except ConnectionFailed:
                if self._closing and self._failure is None:
                    return
                raise

    def __aiter__(self) -> AsyncIterator[Result | ProtocolError]:
        return self.results("raise")

    async def clone(self, points: Any, *, timeout: float = 10.0) -> Result:
        """Send one frame and wait for its result (request/response).

        Results of earlier pipelined frames still arriving are discarded. If the
        connection is lost meanwhile the frame is sent again once it is re-opened.

        Raises
        ------
        ProtocolError
            An error about this frame (or a fatal one).
        TimeoutError
            No result within ``timeout`` seconds (e.g. the frame was dropped by the
            server's rate limit).
        """
        async with asyncio.timeout(timeout):
            seq = await self.send(points)
            sent_on = self.reconnects  # the connection the frame went out on
            while True:
                item = await self._next_item()
                if item is _END:
                    self._raise_if_done()
                if item is _RECONNECTED:
                    if self.reconnects != sent_on:  # not a marker of an older reconnection
                        seq = await self.send(points)
                        sent_on = self.reconnects
                elif isinstance(item, Result):
                    if item.seq == seq:
                        return item
                elif item.seq is None or item.seq == seq:
                    raise item

    async def ping(self, *, timeout: float = 10.0) -> float:
        """Round-trip time of a protocol ``ping``, seconds."""
        await self._wait_connected()
        assert self._ws is not None and self._protocol is not None
        probe_id = next(self._ping_ids)
        waiter: asyncio.Future[float] = asyncio.get_running_loop().create_future()
        self._pings[probe_id] = waiter
        try:
            await self._ws.send(self._protocol.send(Ping(id=probe_id, ts=time.perf_counter())))
            async with asyncio.timeout(timeout):
                return await waiter
        finally:
            self._pings.pop(probe_id, None)

    async def calibrate(
        self, points: Any = None, *, reset: bool = False, timeout: float = 10.0
    ) -> Calibrated:
        """Capture the performer's neutral (``points``, or the next frame sent) or ``reset``.

        Explicit points are sent again after a reconnection; "next frame" is not.
        """
        array = None if points is None else self._frame_points(points)
        await self._wait_connected()
        assert self._ws is not None and self._protocol is not None
        waiter: asyncio.Future[Calibrated] = asyncio.get_running_loop().create_future()
        self._calibrations.append(waiter)
        await self._ws.send(self._protocol.send(Calibrate(points=array, reset=reset)))
        async with asyncio.timeout(timeout):
            calibrated = await waiter
        self._calibration_points = array if calibrated.active and array is not None else None
        return calibrated

    # -- closing -------------------------------------------------------------------------
    async def close(self) -> None:
        """Close the connection; later calls raise `ConnectionFailed`. Idempotent."""
        if self._closing:
            return
        self._closing = True
        self._queue.put_nowait(_END)
        if self._supervisor is not None:
            self._supervisor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._supervisor
        if self._ws is not None:
            await close_websocket(self._ws)
        self._connected.clear()

    async def __aenter__(self) -> StreamSession:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class _Connecting:
    """What `connect` returns: await it for a session, or use it as ``async with``."""

    def __init__(self, session: StreamSession) -> None:
        self._session = session

    def __await__(self) -> Generator[Any, None, StreamSession]:
        return self._open().__await__()

    async def _open(self) -> StreamSession:
        await self._session._start()
        return self._session

    async def __aenter__(self) -> StreamSession:
        return await self._open()

    async def __aexit__(self, *exc: object) -> None:
        await self._session.close()


def connect(
    url: str,
    rig: str,
    *,
    output: Literal["weights", "vertices", "moving"] = "weights",
    dtype: Literal["f32", "f16"] = "f32",
    token: str | None = None,
    align: bool = False,
    align_scale: bool = False,
    calibration: bool = False,
    smoothing: Smoothing | None = None,
    reconnect: Reconnect | int = _DEFAULT_RECONNECT,
    open_timeout: float = 10.0,
    max_queue: int = DEFAULT_MAX_QUEUE,
    limits: Limits | None = None,
) -> _Connecting:
    """Open a streaming session on the server at ``url``.

    Parameters
    ----------
    url : str
        The server's base URL, ``http://host:port`` or ``https://host`` (the WebSocket
        URL ``ws(s)://.../v1/stream`` is derived).
    rig : str
        Rig id on the server.
    output : {"weights", "vertices", "moving"}
        Results carry (M,) weights, (V, 3) target vertices, or (N, 3) vertices: only the
        rig's moving ones (``StreamSession.moving``; ``StreamSession.full_vertices``
        puts them into the target's neutral mesh).
    dtype : {"f32", "f16"}
        Result dtype.
    token : str, optional
        Bearer token; default ``FACECAST_TOKEN`` from the environment. Sent in the
        ``Authorization`` header.
    align, align_scale, calibration : bool
        Session options of ``hello`` (PROTOCOL.md §5.1.1).
    smoothing : Smoothing, optional
        The session's smoothing filter (PROTOCOL.md §5.1.1): ``Smoothing()`` is auto (the
        Kalman filter with the rig's noise where the rig was fitted with one, else one-euro
        at its defaults; ``ready.smoothing`` says which runs), ``Smoothing(filter=
        "one-euro")`` or ``Smoothing(filter="kalman")`` names one. Default None: none.
    reconnect : Reconnect or int
        Reconnection policy, or just the number of attempts (0: never reconnect).
    open_timeout : float
        Seconds for the handshake plus ``ready``.
    max_queue : int
        Results buffered for the application before the reader pauses.
    limits : Limits, optional
        Bounds for decoding server messages.

    Returns
    -------
    An awaitable and async context manager giving a `StreamSession`.

    Raises
    ------
    ConnectionFailed
        The server cannot be reached or refused the WebSocket handshake.
    ProtocolError
        The server answered ``hello`` with an error (unknown rig, unauthorized...).
    """
    if max_queue < 1:
        raise ValueError(f"max_queue must be >= 1, got {max_queue}")
    policy = reconnect if isinstance(reconnect, Reconnect) else Reconnect(attempts=reconnect)
    hello = Hello(
        rig=rig,
        output=output,
        dtype=dtype,
        align=align,
        align_scale=align_scale,
        calibration=calibration,
        smoothing=smoothing,
    )
    session = StreamSession(
        stream_url(url),
        hello,
        token=resolve_token(token),
        reconnect=policy,
        open_timeout=open_timeout,
        max_queue=max_queue,
        limits=limits or Limits(),
    )
    return _Connecting(session)
