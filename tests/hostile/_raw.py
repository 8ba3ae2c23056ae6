"""A hostile peer on a bare TCP socket: WebSocket handshake and frames from websockets' sans-I/O core.

It reads only what it chooses to (the handshake), so tests can play a client that floods
and never reads; the server's side is observed through uvicorn's own connection set.
"""

from __future__ import annotations

import socket
import time

from websockets.client import ClientProtocol
from websockets.http11 import Response
from websockets.uri import parse_uri

from facecast.protocol import SUBPROTOCOL


def open_raw(port: int, path: str, *, rcvbuf: int = 4096) -> tuple[socket.socket, ClientProtocol]:
    """A connected socket past the WebSocket handshake (101 read), with a tiny receive buffer."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.settimeout(5)
    sock.connect(("127.0.0.1", port))
    conn = ClientProtocol(parse_uri(f"ws://127.0.0.1:{port}{path}"), subprotocols=[SUBPROTOCOL])
    conn.send_request(conn.connect())
    sock.sendall(b"".join(conn.data_to_send()))
    while not any(isinstance(e, Response) for e in conn.events_received()):
        data = sock.recv(4096)
        if not data:
            raise ConnectionError("closed during the handshake")
        conn.receive_data(data)
    if conn.handshake_exc is not None:
        raise conn.handshake_exc
    return sock, conn


def flood_pings(sock: socket.socket, conn: ClientProtocol, *, count: int, seconds: float) -> bool:
    """Send up to ``count`` 125-byte pings in ``seconds``, reading nothing; True if cut."""
    conn.send_ping(b"p" * 125)
    ping = b"".join(conn.data_to_send())
    batch = ping * 100
    sock.settimeout(0.2)
    deadline = time.monotonic() + seconds
    sent = 0
    while sent < count and time.monotonic() < deadline:
        try:
            sock.sendall(batch)
        except TimeoutError:
            continue  # the server stopped reading (back-pressure): keep trying till the end
        except OSError:
            return True
        sent += 100
    return False


def server_write_buffers(server) -> list[int]:
    """Bytes waiting in the server's transport buffer, per open connection."""
    return [
        c.transport.get_write_buffer_size()
        for c in list(server.server.server_state.connections)
        if c.transport is not None and not c.transport.is_closing()
    ]
