"""The transport seam: found under uvicorn's sans-I/O protocol, refused wherever it cannot be sure.

Every test runs a real uvicorn (both WebSocket implementations) serving a probe route
behind `TransportSeam`, or the real app, and a real websockets client.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket

import numpy as np
import pytest
import websockets
from _server_helpers import server_logs, wait_until
from starlette.applications import Starlette
from starlette.routing import WebSocketRoute
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from starlette.websockets import WebSocket
from websockets.client import ClientProtocol
from websockets.http11 import Response
from websockets.uri import parse_uri

from facecast.protocol import (
    SUBPROTOCOL,
    Frame,
    Hello,
    Ping,
    Pong,
    Ready,
    Result,
    decode_server,
    encode,
)
from facecast.protocol import ClientProtocol as FacecastClient
from facecast.server.app import create_app
from facecast.server.serving.seam import (
    AsgiTransport,
    SansIOTransport,
    TransportSeam,
    binary_frame,
    transport_for,
)
from facecast.server.settings import Settings
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio

_WAIT = 10.0


class _WrapsSend:
    """A middleware outside the seam that wraps every send (as a logging middleware would)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self.sent: list[str] = []

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        async def wrapped(message: Message) -> None:
            self.sent.append(message["type"])
            await send(message)

        await self.app(scope, receive, wrapped)


def _probe_app(seen: list) -> Starlette:
    """One route: accept, find the transport, write two frames through it, report, close."""

    async def probe(websocket: WebSocket) -> None:
        await websocket.accept()
        transport = transport_for(websocket)
        seen.append(("open", type(transport), transport.closed))
        for payload in (b"first", bytes(range(256)) * 300):
            if not transport.write(binary_frame(payload)):
                await websocket.send_bytes(payload)
        await websocket.receive_bytes()  # the client's ack: both frames arrived
        await websocket.close(1000)
        seen.append(("closed", transport.write(binary_frame(b"late")), transport.closed))

    return Starlette(routes=[WebSocketRoute("/probe", probe)])


async def _talk_to_probe(server) -> list[bytes]:
    async with websockets.connect(f"{server.ws_url}/probe") as ws:
        received = [await asyncio.wait_for(ws.recv(), _WAIT) for _ in range(2)]
        await ws.send(b"ack")
        with pytest.raises(websockets.ConnectionClosedOK):
            await asyncio.wait_for(ws.recv(), _WAIT)
    return received


async def test_seam_gives_the_sansio_protocol_a_direct_transport_and_legacy_the_asgi_send(
    settings, ws_impl
):
    seen: list = []

    async with run_server(settings, ws=ws_impl, app=TransportSeam(_probe_app(seen))) as server:
        received = await _talk_to_probe(server)

    expected = SansIOTransport if ws_impl == "websockets-sansio" else AsgiTransport
    assert seen[0] == ("open", expected, False)
    assert received == [b"first", bytes(range(256)) * 300]
    assert seen[1] == ("closed", False, True)


async def test_seam_behind_a_middleware_that_wraps_send_is_refused(settings, ws_impl):
    seen: list = []
    outer = _WrapsSend(TransportSeam(_probe_app(seen)))

    async with run_server(settings, ws=ws_impl, app=outer) as server:
        received = await _talk_to_probe(server)

    assert seen[0] == ("open", AsgiTransport, False)
    assert received == [b"first", bytes(range(256)) * 300]
    # Both frames went through the outer middleware, which therefore saw them.
    assert outer.sent.count("websocket.send") == 2


async def test_an_app_without_the_seam_gets_the_asgi_send(settings, ws_impl):
    seen: list = []

    async with run_server(settings, ws=ws_impl, app=_probe_app(seen)) as server:
        received = await _talk_to_probe(server)

    assert seen[0] == ("open", AsgiTransport, False)
    assert received == [b"first", bytes(range(256)) * 300]


async def test_direct_writes_and_the_queued_count_exist_only_with_the_direct_transport(
    settings, ws_impl
):
    found: list = []

    async def probe(websocket: WebSocket) -> None:
        await websocket.accept()
        transport = transport_for(websocket)
        found.append((transport.direct, transport.messages_waiting()))
        await websocket.close(1000)

    app = TransportSeam(Starlette(routes=[WebSocketRoute("/probe", probe)]))
    async with (
        run_server(settings, ws=ws_impl, app=app) as server,
        websockets.connect(f"{server.ws_url}/probe") as ws,
    ):
        with pytest.raises(websockets.ConnectionClosedOK):
            await asyncio.wait_for(ws.recv(), _WAIT)

    direct, count = found[0]
    assert direct is (ws_impl == "websockets-sansio")
    assert count == 0  # the client sent nothing after the handshake (0 where not known)


async def test_messages_waiting_counts_what_the_app_has_not_read(settings):
    counts: list[int] = []

    async def probe(websocket: WebSocket) -> None:
        await websocket.accept()
        transport = transport_for(websocket)
        await websocket.receive_bytes()
        counts.append(transport.messages_waiting())
        await websocket.receive_bytes()
        counts.append(transport.messages_waiting())
        await websocket.close(1000)

    app = TransportSeam(Starlette(routes=[WebSocketRoute("/probe", probe)]))
    async with run_server(settings, app=app) as server:
        # Both messages in one TCP write: uvicorn queues both in one read of the socket.
        await asyncio.to_thread(_send_two_messages_at_once, server.port, "/probe")

    assert counts == [1, 0]


def _send_two_messages_at_once(port: int, path: str) -> None:
    with socket.create_connection(("127.0.0.1", port), timeout=_WAIT) as sock:
        conn = ClientProtocol(parse_uri(f"ws://127.0.0.1:{port}{path}"))
        conn.send_request(conn.connect())
        sock.sendall(b"".join(conn.data_to_send()))
        while not any(isinstance(e, Response) for e in conn.events_received()):
            conn.receive_data(sock.recv(4096))
        conn.send_binary(b"one")
        conn.send_binary(b"two")
        sock.sendall(b"".join(conn.data_to_send()))
        while conn.close_rcvd is None:  # read until the server's close frame
            data = sock.recv(4096)
            if not data:
                break
            conn.receive_data(data)


async def test_a_client_that_does_not_read_makes_write_refuse_with_bytes_buffered(settings):
    seen: list = []
    refused = asyncio.Event()
    frame = binary_frame(bytes(64 * 1024))

    async def probe(websocket: WebSocket) -> None:
        await websocket.accept()
        transport = transport_for(websocket)
        written = 0
        while written < 2000 and transport.write(frame):  # bounded: 128 MB at most
            written += 1
        seen.append((written, transport.buffered_bytes(), transport.closed))
        refused.set()
        with contextlib.suppress(Exception):  # the client leaves without reading
            await websocket.close(1000)

    app = TransportSeam(Starlette(routes=[WebSocketRoute("/probe", probe)]))
    async with run_server(settings, app=app) as server:
        sock = await asyncio.to_thread(_handshake_without_reading, server.port, "/probe")
        try:
            await asyncio.wait_for(refused.wait(), _WAIT)
        finally:
            sock.close()

    written, buffered, closed = seen[0]
    assert 0 < written < 2000  # back-pressure stopped the direct writes
    assert buffered > 0  # what the socket has not taken waits in uvicorn's transport
    assert closed is False  # paused, not closed: the ASGI send would wait


def _handshake_without_reading(port: int, path: str) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.settimeout(_WAIT)
    sock.connect(("127.0.0.1", port))
    conn = ClientProtocol(parse_uri(f"ws://127.0.0.1:{port}{path}"))
    conn.send_request(conn.connect())
    sock.sendall(b"".join(conn.data_to_send()))
    while not any(isinstance(e, Response) for e in conn.events_received()):
        conn.receive_data(sock.recv(1))  # byte by byte: nothing of the frames is read
    return sock


async def _stream_results(server, rig, frames: int) -> list[Result]:
    protocol = FacecastClient()
    async with websockets.connect(f"{server.ws_url}/v1/stream", subprotocols=[SUBPROTOCOL]) as ws:
        await ws.send(protocol.send(Hello(rig="tiny", output="weights")))
        assert isinstance(protocol.receive(await asyncio.wait_for(ws.recv(), _WAIT)), Ready)
        results = []
        for seq in range(frames):
            points = (rig.source_neutral + 0.01 * seq).astype(np.float32)
            await ws.send(protocol.send(Frame(seq=seq, ts=seq * 1000, points=points)))
            results.append(protocol.receive(await asyncio.wait_for(ws.recv(), _WAIT)))
    return results


async def test_the_app_streams_the_same_results_with_or_without_a_middleware_outside_the_seam(
    tmp_path, rig, ws_impl
):
    settings = Settings(rigs_dir=tmp_path / "rigs")
    settings.rigs_dir.mkdir(parents=True)
    rig.save(settings.rigs_dir / "tiny.rig")
    wrapped = _WrapsSend(create_app(settings))

    async with run_server(settings, ws=ws_impl) as server:
        plain = await _stream_results(server, rig, 5)
    async with run_server(settings, ws=ws_impl, app=wrapped) as server:
        behind = await _stream_results(server, rig, 5)

    assert [r.seq for r in plain] == [r.seq for r in behind] == list(range(5))
    for a, b in zip(plain, behind, strict=True):
        np.testing.assert_array_equal(a.weights, b.weights)
    # Behind the wrapper every result went through the ASGI send (the wrapper saw it).
    assert wrapped.sent.count("websocket.send") >= 1 + 5


def test_create_app_puts_the_seam_outermost(settings):
    app = create_app(settings)

    assert app.user_middleware[0].cls is TransportSeam


# -- frames taken on the protocol's stack (``Transport.take_messages``) -------------------


def _stream_burst(port: int, hello: bytes, burst: list[bytes], replies: int) -> list[bytes]:
    """Open a stream, send ``hello``, then every message of ``burst`` in one TCP write.

    Returns the server's first ``replies`` messages after ``ready``, in order.
    """
    from websockets.frames import Frame as WsFrame
    from websockets.frames import Opcode

    with socket.create_connection(("127.0.0.1", port), timeout=_WAIT) as sock:
        conn = ClientProtocol(
            parse_uri(f"ws://127.0.0.1:{port}/v1/stream"), subprotocols=[SUBPROTOCOL]
        )
        conn.send_request(conn.connect())
        sock.sendall(b"".join(conn.data_to_send()))
        received: list[bytes] = []
        opened = False

        def read_until(count: int) -> None:
            nonlocal opened
            while not opened or len(received) < count:
                for event in conn.events_received():
                    opened = opened or isinstance(event, Response)
                    if isinstance(event, WsFrame) and event.opcode is Opcode.BINARY:
                        received.append(bytes(event.data))
                if not opened or len(received) < count:
                    conn.receive_data(sock.recv(65536))

        read_until(0)  # the handshake's response
        conn.send_binary(hello)
        sock.sendall(b"".join(conn.data_to_send()))
        read_until(1)  # ready
        for message in burst:
            conn.send_binary(message)
        sock.sendall(b"".join(conn.data_to_send()))  # one write: one read on the server
        read_until(1 + replies)
        conn.send_close(1000)
        sock.sendall(b"".join(conn.data_to_send()))
    return received[1:]


def _closed_sessions(records) -> list[dict]:
    return [vars(r) for r in records if getattr(r, "event", None) == "session.close"]


async def test_frames_are_taken_on_the_protocol_stack_only_under_the_sansio_protocol(
    tmp_path, rig, ws_impl
):
    settings = Settings(rigs_dir=tmp_path / "rigs")
    settings.rigs_dir.mkdir(parents=True)
    rig.save(settings.rigs_dir / "tiny.rig")
    async with run_server(settings, ws=ws_impl) as server:
        with server_logs() as records:
            results = await _stream_results(server, rig, 5)
            await wait_until(lambda: _closed_sessions(records))

    assert [r.seq for r in results] == list(range(5))
    (closed,) = _closed_sessions(records)
    assert closed["frames_in"] == 5
    # Under the sans-I/O protocol every frame (each sent after the previous result came
    # back, so the reader was parked) skipped the queue; under the legacy one none did.
    assert closed["frames_taken"] == (5 if ws_impl == "websockets-sansio" else 0)


async def test_a_burst_mixing_frames_and_pings_keeps_frames_behind_what_waits(
    tmp_path, rig, ws_impl
):
    # frame, ping, frame, frame, ping in one TCP write: only the first frame is taken on
    # the protocol's stack; the ping goes to the reader's queue, and every frame after it
    # waits there behind it, so the reader processes them all in arrival order.
    settings = Settings(rigs_dir=tmp_path / "rigs")
    settings.rigs_dir.mkdir(parents=True)
    rig.save(settings.rigs_dir / "tiny.rig")
    protocol = FacecastClient()
    hello = protocol.send(Hello(rig="tiny", output="weights"))
    points = rig.source_neutral.astype(np.float32)
    frame = lambda seq: encode(Frame(seq=seq, ts=seq * 10.0, points=points))  # noqa: E731
    burst = [frame(0), encode(Ping(id=1, ts=1.0)), frame(1), frame(2), encode(Ping(id=2, ts=2.0))]
    async with run_server(settings, ws=ws_impl) as server:
        with server_logs() as records:
            replies = await asyncio.to_thread(_stream_burst, server.port, hello, burst, 5)
            await wait_until(lambda: _closed_sessions(records))

    decoded = [decode_server(data) for data in replies]
    assert [m.seq for m in decoded if isinstance(m, Result)] == [0, 1, 2]
    assert [m.id for m in decoded if isinstance(m, Pong)] == [1, 2]
    (closed,) = _closed_sessions(records)
    if ws_impl == "websockets-sansio":
        assert closed["frames_taken"] == 1
        assert isinstance(decoded[0], Result)  # the taken frame's result left with its read
    else:  # no hook: the reader had every message (and a pong may pass a queued result)
        assert closed["frames_taken"] == 0


async def test_a_burst_of_frames_taken_together_is_answered_in_order(tmp_path, rig, monkeypatch):
    # How many reads the burst arrives in is TCP's choice, and how many frames one read
    # takes within its share of the loop (_TAKE_SECONDS) depends on the machine's load
    # (issue #25 item 8: 12 of 20 on a busy one). Without that share every frame of
    # every read is taken while the reader is parked, however the burst was split; the
    # share itself is the next test's.
    monkeypatch.setattr("facecast.server.stream.session._TAKE_SECONDS", 60.0)
    settings = Settings(rigs_dir=tmp_path / "rigs")
    settings.rigs_dir.mkdir(parents=True)
    rig.save(settings.rigs_dir / "tiny.rig")
    protocol = FacecastClient()
    hello = protocol.send(Hello(rig="tiny", output="weights"))
    frames = [
        encode(Frame(seq=seq, ts=seq * 10.0, points=(rig.source_neutral + 0.01 * seq)))
        for seq in range(20)
    ]
    async with run_server(settings) as server:
        with server_logs() as records:
            replies = await asyncio.to_thread(_stream_burst, server.port, hello, frames, 20)
            await wait_until(lambda: _closed_sessions(records))

    results = [decode_server(data) for data in replies]
    assert [r.seq for r in results] == list(range(20))
    (closed,) = _closed_sessions(records)
    assert closed["frames_in"] == closed["frames_taken"] == 20  # none through the queue
    for seq, result in enumerate(results):
        expected = rig.weights(rig.source_neutral + 0.01 * seq)
        np.testing.assert_allclose(result.weights, expected, rtol=1e-5, atol=1e-6)


async def test_a_read_takes_frames_for_its_share_of_the_loop_then_hands_the_rest_on(
    tmp_path, rig, monkeypatch
):
    # With no time to spare per read, only the first frame of each read is taken on the
    # protocol's stack; the rest go through the reader, and every frame is still answered
    # in order (they arrived together, within one burst).
    monkeypatch.setattr("facecast.server.stream.session._TAKE_SECONDS", 0.0)
    settings = Settings(rigs_dir=tmp_path / "rigs")
    settings.rigs_dir.mkdir(parents=True)
    rig.save(settings.rigs_dir / "tiny.rig")
    hello = FacecastClient().send(Hello(rig="tiny", output="weights"))
    frames = [encode(Frame(seq=seq, ts=seq * 10.0, points=rig.source_neutral)) for seq in range(20)]
    async with run_server(settings) as server:
        with server_logs() as records:
            replies = await asyncio.to_thread(_stream_burst, server.port, hello, frames, 20)
            await wait_until(lambda: _closed_sessions(records))

    assert [decode_server(data).seq for data in replies] == list(range(20))
    (closed,) = _closed_sessions(records)
    assert closed["frames_in"] == 20
    assert 1 <= closed["frames_taken"] < 20
