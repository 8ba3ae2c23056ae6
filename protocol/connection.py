"""Sans-I/O session state machines for both ends of a connection (PROTOCOL.md §5, §9).

Feed received bytes in, get typed messages (or ProtocolError) out; hand messages in, get
bytes to send out. The caller owns the socket; nothing here blocks, sleeps or awaits.
"""

from __future__ import annotations

from enum import Enum
from typing import Any, NoReturn

from facecast.protocol.arrays import check_result_finite
from facecast.protocol.codec import (
    DEFAULT_LIMITS,
    decode_client,
    decode_server,
    encode,
    encode_result,
    reject_text,
)
from facecast.protocol.errors import ErrorCode, ProtocolError
from facecast.protocol.fastframe import decode_frame
from facecast.protocol.limits import Limits
from facecast.protocol.messages import (
    Calibrate,
    Calibrated,
    ChannelIdle,
    ChannelLive,
    ClientMessage,
    Error,
    FaceLost,
    Frame,
    Hello,
    Ping,
    Pong,
    Ready,
    Result,
    ServerMessage,
)


class ServerState(Enum):
    """Where a server-side session is (§9)."""

    AWAITING_HELLO = "awaiting_hello"
    STREAMING = "streaming"
    CLOSED = "closed"


class ClientState(Enum):
    """Where a client-side session is (§9)."""

    AWAITING_READY = "awaiting_ready"
    STREAMING = "streaming"
    CLOSED = "closed"


def _wrong_state(message: str, *, fatal: bool, seq: int | None = None) -> ProtocolError:
    return ProtocolError(ErrorCode.WRONG_STATE, message, seq=seq, fatal=fatal)


class ServerProtocol:
    """The server's view of one connection.

    ``receive`` validates order as well as content: a ``frame`` or ``calibrate`` before
    ``hello`` is a fatal WRONG_STATE, a second ``hello`` or anything but ``ping`` from a
    watcher a non-fatal one. Once `send` has
    sent a `Ready`, frames and calibrations whose point count is not the rig's K raise
    WRONG_POINT_COUNT (non-fatal). Any error raised before the session is open is fatal,
    because there is no session to continue.

    Parameters
    ----------
    limits : Limits
        Bounds for decoding.
    hello : Hello or None
        Parameters negotiated out of band (a channel watcher's query string, §2.1); the
        session then starts in STREAMING, never expects a ``hello`` and accepts only
        ``ping``.
    """

    def __init__(self, limits: Limits = DEFAULT_LIMITS, *, hello: Hello | None = None) -> None:
        self.limits = limits
        self.hello: Hello | None = hello
        self.ready: Ready | None = None
        self.watching = hello is not None
        self.state = ServerState.AWAITING_HELLO if hello is None else ServerState.STREAMING

    def receive(self, data: bytes) -> ClientMessage:
        """Decode one received binary message and check it fits the session's state.

        Raises
        ------
        ProtocolError
            With ``fatal`` set when the connection must be closed after reporting it.
        """
        if self.state is ServerState.CLOSED:
            raise _wrong_state("the session is closed", fatal=True)
        try:
            message = decode_client(data, self.limits)
        except ProtocolError as exc:
            fatal = (
                exc.fatal
                or self.state is ServerState.AWAITING_HELLO
                or exc.code is ErrorCode.UNSUPPORTED_VERSION
            )
            raise exc.evolve(fatal=fatal) from None
        if self.state is ServerState.AWAITING_HELLO:
            if isinstance(message, Hello):
                self.hello = message
                self.state = ServerState.STREAMING
            elif not isinstance(message, Ping):
                raise _wrong_state(
                    f"{message.TYPE} before hello",
                    fatal=True,
                    seq=getattr(message, "seq", None),
                )
            return message
        if isinstance(message, Ping):
            return message
        if self.watching:
            raise _wrong_state(f"a watcher may only send ping, not {message.TYPE}", fatal=False)
        if isinstance(message, Hello):
            raise _wrong_state("hello twice; the session is already open", fatal=False)
        if isinstance(message, Frame | Calibrate) and message.points is not None:
            self._check_point_count(message)
        return message

    def receive_frame(self, data: bytes) -> Frame | None:
        """``data`` as a `Frame` the open session takes as is, or None: `receive` decides.

        The per-frame fast path: only a frame in the canonical layout (`fastframe`), with
        the rig's point count, on a streaming session that is not a watcher's. None says
        nothing about validity; it never raises and changes no state.
        """
        if self.state is not ServerState.STREAMING or self.watching or self.ready is None:
            return None
        frame = decode_frame(data, self.limits)
        if frame is None or frame.points.shape[0] != self.ready.num_points:
            return None
        return frame

    def receive_text(self, text: str) -> NoReturn:
        """Reject a text WebSocket message: TEXT_NOT_SUPPORTED (fatal before hello)."""
        try:
            reject_text(text)
        except ProtocolError as exc:
            raise exc.evolve(fatal=self.state is not ServerState.STREAMING) from None

    def _check_point_count(self, message: Frame | Calibrate) -> None:
        if self.ready is None or message.points is None:
            return
        k = self.ready.num_points
        if message.points.shape[0] != k:
            raise ProtocolError(
                ErrorCode.WRONG_POINT_COUNT,
                f"{message.TYPE}.points has {message.points.shape[0]} points; rig "
                f"{self.ready.rig!r} needs K={k}",
                seq=getattr(message, "seq", None),
            )

    def send(self, message: ServerMessage) -> bytes:
        """Encode a message to send, checking it is allowed now.

        `Ready` is allowed once, after ``hello`` (or at once for a pre-negotiated
        session); an `Error` with ``fatal`` closes the session; results and events need
        an open session. Raises ProtocolError(WRONG_STATE) otherwise: a server bug.
        """
        if self.state is ServerState.CLOSED:
            raise _wrong_state(f"cannot send {message.TYPE}: the session is closed", fatal=True)
        if isinstance(message, Error):
            if message.fatal:
                self.state = ServerState.CLOSED
            return encode(message)
        if isinstance(message, Pong):
            return encode(message)
        if self.state is not ServerState.STREAMING:
            raise _wrong_state(f"cannot send {message.TYPE} before hello", fatal=False)
        if isinstance(message, Ready):
            if self.ready is not None:
                raise _wrong_state("ready was already sent", fatal=False)
            self.ready = message
        elif self.ready is None:
            raise _wrong_state(f"cannot send {message.TYPE} before ready", fatal=False)
        elif isinstance(message, Result):
            check_result_finite(message.values, f"result.{message.output}", message.seq)
        return encode(message)

    def send_result(
        self, seq: int, ts: float, values: Any, *, output: str, proc_us: int, dropped: int
    ) -> bytes:
        """Bytes of a `Result` the server computed: ``send(Result(...))``'s, made faster.

        The per-frame path: the session state is checked as `send` does, the fields are
        trusted (``values`` a valid array for ``output``; see `encode_result`) except
        that ``values`` must be finite (§4): RESULT_NOT_FINITE (not fatal) otherwise.
        """
        if self.ready is None or self.state is not ServerState.STREAMING:
            raise _wrong_state("cannot send result before ready", fatal=False)
        check_result_finite(values, f"result.{output}", seq)
        return encode_result(seq, ts, output, values, proc_us, dropped)

    def fail(self, error: ProtocolError) -> bytes:
        """Bytes of the `Error` reporting ``error``; closes the session when it is fatal."""
        return self.send(Error.of(error))

    def close(self) -> None:
        """Mark the session closed (the socket went away)."""
        self.state = ServerState.CLOSED


class ClientProtocol:
    """The client's view of one connection: send `Hello`, wait for `Ready`, stream.

    Parameters
    ----------
    limits : Limits
        Bounds for decoding server messages.
    watching : bool
        True for a channel watcher (§2.3): no ``hello`` is sent, the server's ``ready``
        opens the session.
    """

    def __init__(self, limits: Limits = DEFAULT_LIMITS, *, watching: bool = False) -> None:
        self.limits = limits
        self.watching = watching
        self.hello: Hello | None = None
        self.ready: Ready | None = None
        self.state = ClientState.AWAITING_READY

    def send(self, message: ClientMessage) -> bytes:
        """Encode a message to send, checking it is allowed now (WRONG_STATE otherwise)."""
        if self.state is ClientState.CLOSED:
            raise _wrong_state(f"cannot send {message.TYPE}: the session is closed", fatal=True)
        if isinstance(message, Hello):
            if self.watching or self.hello is not None:
                raise _wrong_state("hello was already sent or is not used here", fatal=False)
            self.hello = message
        elif isinstance(message, Frame | Calibrate) and self.state is not ClientState.STREAMING:
            raise _wrong_state(f"cannot send {message.TYPE} before ready", fatal=False)
        return encode(message)

    def receive(self, data: bytes) -> ServerMessage:
        """Decode one received message and check it fits the session.

        Raises
        ------
        ProtocolError
            For undecodable bytes, a message out of order, or a result that does not
            match what ``ready`` announced.
        """
        if self.state is ClientState.CLOSED:
            raise _wrong_state("the session is closed", fatal=True)
        message = decode_server(data, self.limits)
        if isinstance(message, Error):
            if message.fatal:
                self.state = ClientState.CLOSED
            return message
        if isinstance(message, Pong):
            return message
        if isinstance(message, Ready):
            if self.state is not ClientState.AWAITING_READY:
                raise _wrong_state("ready twice", fatal=False)
            if not self.watching and self.hello is None:
                raise _wrong_state("ready before hello was sent", fatal=False)
            self.ready = message
            self.state = ClientState.STREAMING
            return message
        if self.state is not ClientState.STREAMING or self.ready is None:
            raise _wrong_state(f"{message.TYPE} before ready", fatal=False)
        if isinstance(message, Result):
            self._check_result(message, self.ready)
        elif not isinstance(message, Calibrated | ChannelIdle | ChannelLive | FaceLost):
            raise _wrong_state(f"unexpected {message.TYPE}", fatal=False)
        return message

    @staticmethod
    def _check_result(result: Result, ready: Ready) -> None:
        expected = {
            "weights": (ready.num_examples,),
            "vertices": (ready.num_vertices, 3),
            "moving": (ready.result_vertices, 3),
            "points": (ready.num_points, 3),
        }[ready.output]
        # A "moving" session's results carry its N vertices in ``vertices`` (§5.2.2).
        carried = "vertices" if ready.output == "moving" else ready.output
        if (
            result.output != carried
            or result.dtype != ready.dtype
            or result.values.shape != expected
        ):
            raise ProtocolError(
                ErrorCode.INVALID_FIELD,
                f"result carries {result.output} {result.dtype} {result.values.shape}; ready "
                f"announced {ready.output} {ready.dtype} {expected}",
                seq=result.seq,
            )

    def close(self) -> None:
        """Mark the session closed (the socket went away)."""
        self.state = ClientState.CLOSED
