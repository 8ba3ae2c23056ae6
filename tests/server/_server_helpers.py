"""Shared helpers of the server tests: tiny rigs, example-set archives, WS and process tools."""

from __future__ import annotations

import asyncio
import io
import logging
import os
import signal
import subprocess
import sys
import tarfile
import time
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import numpy as np

from facecast.cli.bench.harness import answers_ok
from facecast.cli.bench.harness import wait_until as poll_until
from facecast.protocol import ClientProtocol, Error, Hello, Ready, decode_server, encode
from facecast.rig import ExampleSet, fit
from facecast.rig.io.meshio import write_obj

NAMES = ("neutral", "smile", "frown", "jaw")


def tiny_example_set(num_vertices: int = 16, seed: int = 0) -> ExampleSet:
    """4 examples, 5 feature points, a ``num_vertices`` target strip."""
    rng = np.random.default_rng(seed)
    m, k = len(NAMES), 5
    source = np.repeat(rng.normal(size=(1, k, 3)), m, axis=0)
    source[1:] += rng.normal(scale=0.3, size=(m - 1, k, 3))
    target = np.repeat(rng.normal(size=(1, num_vertices, 3)), m, axis=0)
    target[1:] += rng.normal(scale=0.3, size=(m - 1, num_vertices, 3))
    faces = np.array([[i, i + 1, i + 2] for i in range(num_vertices - 2)])
    return ExampleSet(NAMES, source, target, faces)


def tiny_rig(num_vertices: int = 16, seed: int = 0):
    return fit(tiny_example_set(num_vertices, seed))


def frame_points(rig, seed: int, dtype=np.float32) -> np.ndarray:
    """Feature points (K, 3) near the rig's neutral, different per ``seed``."""
    rng = np.random.default_rng(1000 + seed)
    return (rig.source_neutral + rng.normal(scale=0.1, size=rig.source_neutral.shape)).astype(dtype)


def write_example_folder(folder: Path, example_set: ExampleSet | None = None) -> ExampleSet:
    """A ``facecast.toml`` folder: .npy source points and .obj targets."""
    es = example_set or tiny_example_set()
    (folder / "source").mkdir(parents=True)
    (folder / "target").mkdir()
    lines = []
    for i, name in enumerate(es.names):
        np.save(folder / f"source/{name}.npy", es.source_points[i])
        write_obj(folder / f"target/{name}.obj", es.target_vertices[i], es.target_faces)
        if i:
            lines.append(f'{name} = ["source/{name}.npy", "target/{name}.obj"]')
    (folder / "facecast.toml").write_text(
        '[source]\nneutral = "source/neutral.npy"\n'
        '[target]\nneutral = "target/neutral.obj"\n'
        "[examples]\n" + "\n".join(lines) + "\n"
    )
    return es


def zip_bytes(members: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def tar_bytes(members: dict[str, bytes], *, gz: bool) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz" if gz else "w") as archive:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            archive.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


def folder_members(folder: Path, prefix: str = "") -> dict[str, bytes]:
    return {
        prefix + p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@contextmanager
def server_logs() -> Iterator[list[logging.LogRecord]]:
    """Every record facecast and uvicorn log while the block runs (after their filters).

    Enter it once the server runs: uvicorn configures its loggers when it starts.
    """
    records: list[logging.LogRecord] = []

    class _Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    handler = _Keep(logging.DEBUG)
    loggers = [logging.getLogger(name) for name in ("uvicorn", "facecast")]
    for logger in loggers:
        logger.addHandler(handler)
    try:
        yield records
    finally:
        for logger in loggers:
            logger.removeHandler(handler)


def errors_logged(records: list[logging.LogRecord]) -> list[str]:
    """The messages of records at error level or above, or carrying a traceback."""
    return [r.getMessage() for r in records if r.levelno >= logging.ERROR or r.exc_info]


# -- WebSocket helpers -----------------------------------------------------------------


async def raw_websocket(host: str, port: int, path: str, headers: dict[str, str] | None = None):
    """A WebSocket handshake by hand: (reader, writer, status line) for frames no client sends."""
    import base64

    reader, writer = await asyncio.open_connection(host, port)
    key = base64.b64encode(os.urandom(16)).decode()
    headers = {"Host": f"{host}:{port}", **(headers or {})}
    lines = [
        f"GET {path} HTTP/1.1",
        "Upgrade: websocket",
        "Connection: Upgrade",
        f"Sec-WebSocket-Key: {key}",
        "Sec-WebSocket-Version: 13",
        *(f"{name}: {value}" for name, value in (headers or {}).items()),
    ]
    writer.write(("\r\n".join(lines) + "\r\n\r\n").encode())
    await writer.drain()
    head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10)
    return reader, writer, head.split(b"\r\n", 1)[0].decode()


def masked_frame(opcode: int, payload: bytes) -> bytes:
    """One final client frame (RFC 6455 §5.2), masked, payload under 126 bytes."""
    mask = os.urandom(4)
    body = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    return bytes([0x80 | opcode, 0x80 | len(payload)]) + mask + body


async def close_code_of(reader, timeout: float = 10.0) -> int:
    """Read server frames until a close frame; its status code."""
    async with asyncio.timeout(timeout):
        while True:
            first, second = await reader.readexactly(2)
            length = second & 0x7F
            if length == 126:
                length = int.from_bytes(await reader.readexactly(2), "big")
            elif length == 127:
                length = int.from_bytes(await reader.readexactly(8), "big")
            payload = await reader.readexactly(length)
            if first & 0x0F == 0x8:
                return int.from_bytes(payload[:2], "big")


async def open_session(ws, rig_id: str, **hello: Any) -> Ready:
    """Send hello on an open connection and return the server's ready."""
    await ws.send(encode(Hello(rig=rig_id, **hello)))
    message = decode_server(await asyncio.wait_for(ws.recv(), 10))
    assert isinstance(message, Ready), message
    return message


async def recv_message(ws, timeout: float = 10.0):
    return decode_server(await asyncio.wait_for(ws.recv(), timeout))


async def recv_error(ws, timeout: float = 10.0) -> Error:
    """The next message, which must be an error."""
    message = await recv_message(ws, timeout)
    assert isinstance(message, Error), message
    return message


def client_protocol() -> ClientProtocol:
    return ClientProtocol()


# -- subprocess servers ----------------------------------------------------------------


def serve_argv(*args: str) -> list[str]:
    """The command line starting ``facecast serve`` in a fresh interpreter (the full CLI:
    a command module that fails to import fails the server's start, as it would a user's)."""
    return [sys.executable, "-m", "facecast.cli", "serve", *args]


@contextmanager
def server_process(
    port: int,
    rigs: Path,
    *extra: str,
    env: dict[str, str] | None = None,
    ready_timeout: float = 60.0,
) -> Iterator[subprocess.Popen]:
    """A ``facecast serve`` subprocess on 127.0.0.1:``port``; ready when this yields
    (within ``ready_timeout`` s: a machine busy with other suites starts it slowly)."""
    full_env = {**os.environ, **(env or {})}
    process = subprocess.Popen(
        serve_argv("--host", "127.0.0.1", "--port", str(port), "--rigs", str(rigs), *extra),
        env=full_env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        # Its own process group: a supervisor killed (by the test, or here when it never got
        # ready) leaves its --workers behind, and they would go on running after the test.
        start_new_session=True,
    )
    try:
        wait_ready(f"http://127.0.0.1:{port}", process, ready_timeout)
        yield process
    finally:
        if process.poll() is None:
            process.kill()
        process.wait(10)
        with suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        if process.stderr:
            process.stderr.close()


def wait_ready(base_url: str, process: subprocess.Popen, timeout: float = 60.0) -> None:
    """Poll ``/healthz`` until it answers; fail early if the process died (with its stderr)."""

    def exited() -> str | None:
        if process.poll() is None:
            return None
        err = process.stderr.read().decode() if process.stderr else ""
        return f"server exited with {process.returncode}: {err[-2000:]}"

    url = f"{base_url}/healthz"
    poll_until(lambda: answers_ok(url), f"server at {base_url} ready", timeout, exited=exited)


def stop(process: subprocess.Popen, sig: int = signal.SIGTERM, timeout: float = 15.0) -> int:
    process.send_signal(sig)
    return process.wait(timeout)


async def wait_until(predicate, timeout: float = 10.0) -> None:
    """Wait for a condition on the server's state (it runs in its own thread: no event to
    await across threads)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        await asyncio.sleep(0.01)
