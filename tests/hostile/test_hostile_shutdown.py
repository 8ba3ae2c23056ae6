"""SIGTERM while an upload is still arriving (issue 25, item 5) or being parsed (issue 31,
items 5 and 6), on a real `facecast serve`.

Before: uvicorn cancelled the request when its graceful wait ran out, and the upload got
a 500 with a traceback at error level ("Cancel 1 running task(s), timeout graceful
shutdown exceeded"). Now the request stops at once with 503 ``shutting_down``.
"""

from __future__ import annotations

import json
import selectors
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from facecast.rig.sources.ict import locate_ict
from facecast.server.testing import free_port
from tests.server._server_helpers import server_process, wait_ready


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


#: The longest a shutdown may take here with a parse, a fit or a transfer still running.
#: Issue 31's goal is 2 s, met on a quiet machine (SERVER.md: about 1 s, most of it the
#: interpreter's own exit); a loaded one (10-20 runnable tasks on 2 cores) took up to 3 s.
#: Work that is waited for takes its whole length: a minute in the held-parse test.
MAX_SHUTDOWN_SECONDS = 5.0
#: A server's start on a machine busy with other suites took up to 19 s.
READY_SECONDS = 60.0


def _line(stream, timeout: float) -> bytes:
    with selectors.DefaultSelector() as selector:
        selector.register(stream, selectors.EVENT_READ)
        assert selector.select(timeout), f"nothing printed in {timeout} s"
    return stream.readline()


#: The longest a small upload may wait while a large one's parse holds the fit pool (its
#: own parse is milliseconds; the rest is a loaded machine's scheduling).
MAX_SMALL_UPLOAD_SECONDS = 10.0


def test_a_parse_that_never_ends_delays_no_small_upload_nor_the_exit(tmp_path):
    """The fit pool busy with work that would take a minute (``_held_fit_server``): a
    small upload queued behind it (22 s behind a 150,000-node parse, issue 31), and the
    process waited for it at exit (ThreadPoolExecutor's threads are joined; a 200,000-node
    glTF held a stopping server 118 s). Small uploads have a lane of their own, and the
    pool's daemon threads are abandoned at exit."""
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    port = free_port()
    process = subprocess.Popen(
        [sys.executable, "-m", "tests.hostile._held_fit_server", str(rigs), str(port)],
        cwd=Path(__file__).resolve().parents[2],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        wait_ready(f"http://127.0.0.1:{port}", process, READY_SECONDS)
        assert _line(process.stdout, 20) == b"held\n"
        base = f"http://127.0.0.1:{port}"
        small_started = time.monotonic()
        small = httpx.put(f"{base}/v1/characters/small", content=b"glTF" + bytes(100), timeout=30)
        small_waited = time.monotonic() - small_started
        with socket.create_connection(("127.0.0.1", port), timeout=15) as sock:
            # Over small_upload_bytes (1 MiB): the large lane, queued behind the held parse.
            body = b"glTF" + b"\0" * (2**20 + 996)
            sock.sendall(
                b"PUT /v1/characters/queued HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                b"Content-Type: model/gltf-binary\r\nContent-Length: %d\r\n"
                b"Expect: 100-continue\r\n\r\n" % len(body)
            )
            assert _read_head(sock).startswith(b"HTTP/1.1 100")
            sock.sendall(body)  # read whole, then queued behind the held parse
            # Signalled only once queued: a body the server has not read yet when it closes
            # the connection makes the kernel reset it, and the 503 is lost on the way.
            assert _line(process.stdout, 20) == b"queued\n"
            started = time.monotonic()
            process.send_signal(signal.SIGTERM)
            response = _read_all(sock)
            status = process.wait(30)
            waited = time.monotonic() - started
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(10)
    log = process.stderr.read().decode()
    process.stdout.close()
    process.stderr.close()

    assert small.status_code == 422 and small.json()["code"] == "bad_gltf", small.text
    assert small_waited < MAX_SMALL_UPLOAD_SECONDS, f"a small upload waited {small_waited:.1f} s"
    assert status == 0, log[-2000:]
    assert waited < MAX_SHUTDOWN_SECONDS, f"the process took {waited:.2f} s to exit"
    head, _, body = response.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 503"), response[:300]
    assert json.loads(body)["code"] == "shutting_down"


@pytest.mark.ict
@pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found")
def test_sigterm_during_a_transfer_job_leaves_no_scratch_of_its_own(tmp_path):
    """The job wrote its last record after the store had removed its scratch folder, and
    so made a new one (``.scratch/<pid>-*/.lock``, 3/3): a closed store makes none."""
    from tests.rig._avatars import avatar

    rigs = tmp_path / "rigs"
    rigs.mkdir()
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    env = {"FACECAST_LOG_LEVEL": "info"}
    with server_process(port, rigs, env=env, ready_timeout=READY_SECONDS) as process:
        put = httpx.put(
            f"{base}/v1/characters/ava",
            content=avatar("neutral_only"),
            params={"expressions": "transfer"},  # all 51: seconds of work left at SIGTERM
            timeout=60,
        )
        assert put.status_code == 202, put.text
        deadline = time.monotonic() + 60
        while httpx.get(f"{base}/v1/characters/ava/job").json()["progress"]["done"] < 1:
            assert time.monotonic() < deadline, "the job made no progress"
            time.sleep(0.05)  # polled: the job is a resource
        started = time.monotonic()
        process.send_signal(signal.SIGTERM)
        status = process.wait(30)
        waited = time.monotonic() - started
        log = process.stderr.read().decode()

    assert status == 0, log[-2000:]
    assert waited < MAX_SHUTDOWN_SECONDS, f"the process took {waited:.2f} s to exit"
    assert not list((rigs / ".scratch").glob(f"{process.pid}-*"))
    # Its end recorded in time ("interrupted"), or abandoned mid-expression ("running",
    # which a later server reads as interrupted: the slot is free); never stored.
    record = json.loads((rigs / ".jobs" / "ava.json").read_text())
    assert record["state"] in ("failed", "running"), record
    assert not (rigs / "ava.rig").exists()
    assert "Traceback" not in log
