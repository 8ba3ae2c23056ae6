"""SIGTERM while an upload is still arriving (issue 25, item 5), on a real `facecast serve`.

Before: uvicorn cancelled the request when its graceful wait ran out, and the upload got
a 500 with a traceback at error level ("Cancel 1 running task(s), timeout graceful
shutdown exceeded"). Now the request stops at once with 503 ``shutting_down``.
"""

from __future__ import annotations

import json
import signal
import socket

from facecast.server.testing import free_port
from tests.server._server_helpers import server_process


def _read_head(sock: socket.socket) -> bytes:
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(4096)
        if not chunk:
            break
        data += chunk
    return data


def _read_all(sock: socket.socket) -> bytes:
    data = b""
    while chunk := sock.recv(4096):
        data += chunk
    return data


def test_sigterm_answers_an_upload_in_flight_503_without_an_error_log(tmp_path):
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    port = free_port()
    env = {"FACECAST_SHUTDOWN_TIMEOUT": "1", "FACECAST_LOG_LEVEL": "info"}
    with server_process(port, rigs, env=env) as process:
        with socket.create_connection(("127.0.0.1", port), timeout=15) as sock:
            # Expect: 100-continue: uvicorn says "100 Continue" when the handler starts
            # reading the body, so the SIGTERM comes while the upload is being read.
            sock.sendall(
                b"PUT /v1/rigs/trickled HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                b"Content-Type: application/octet-stream\r\nContent-Length: 100000\r\n"
                b"Expect: 100-continue\r\n\r\n"
            )
            assert _read_head(sock).startswith(b"HTTP/1.1 100")
            sock.sendall(b"x" * 1000)  # a trickle: far from the 100,000 announced
            process.send_signal(signal.SIGTERM)
            response = _read_all(sock)
        status = process.wait(15)
        log = process.stderr.read().decode()

    head, _, body = response.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 503"), response[:300]
    assert json.loads(body)["code"] == "shutting_down"
    assert status == 0
    lines = [json.loads(line) for line in log.splitlines() if line.startswith("{")]
    assert [e for e in lines if e["level"] in ("error", "critical")] == []
    assert "Traceback" not in log
