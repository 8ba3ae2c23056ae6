#!/usr/bin/env python3
"""Measures what a tokenless client costs a real `facecast serve` on 127.0.0.1 (SERVER.md).

Ping floods that never read (1 and 10 connections, 8 s), slowloris (265 connections that
send nothing or half a request head), a refused connection that reads nothing, and 10
refused connections sending large messages, against each WebSocket implementation; prints server RSS, /healthz answers and connection
lifetimes. Loopback only, bounded in count and time. Run from the repository:
`.venv/bin/python scripts/hostile_costs.py`. Uses the test suite's raw peer (tests/hostile).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from facecast.server.testing import free_port
from tests.hostile._raw import flood_pings, open_raw


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def start(ws: str, rigs: Path, *env_pairs: str) -> tuple[subprocess.Popen, int]:
    port = free_port()
    env = {**os.environ, "FACECAST_LOG_LEVEL": "warning", "FACECAST_ACCESS_LOG": "false",
           "FACECAST_AUTH": "true", "FACECAST_TOKENS": "secret:admin"}  # fmt: skip
    env.update(pair.split("=", 1) for pair in env_pairs)
    process = subprocess.Popen(
        [sys.executable, "-m", "facecast.cli", "serve", "--port", str(port),
         "--rigs", str(rigs), "--ws", ws],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1).status_code == 200:
                return process, port
        except httpx.TransportError:
            time.sleep(0.1)
    process.kill()
    raise TimeoutError("server did not start")


def stop(process: subprocess.Popen) -> None:
    process.terminate()
    process.wait(30)


def ping_flood(ws: str, rigs: Path, connections: int, seconds: float = 8.0) -> None:
    process, port = start(ws, rigs)
    try:
        before = rss_mb(process.pid)
        peers = [open_raw(port, "/v1/stream") for _ in range(connections)]
        cut = [False] * connections
        peak = before

        def run(i: int) -> None:
            cut[i] = flood_pings(*peers[i], count=10**9, seconds=seconds)

        threads = [threading.Thread(target=run, args=(i,)) for i in range(connections)]
        for thread in threads:
            thread.start()
        while any(t.is_alive() for t in threads):
            peak = max(peak, rss_mb(process.pid))
            time.sleep(0.2)
        after = rss_mb(process.pid)
        print(f"ping flood, {ws:17s} {connections:2d} conn, {seconds:g} s: RSS {before:6.1f} -> "
              f"peak {peak:6.1f} -> {after:6.1f} MB; cut {sum(cut)}/{connections}")  # fmt: skip
        for sock, _ in peers:
            sock.close()
    finally:
        stop(process)


def slowloris(ws: str, rigs: Path, count: int = 265) -> None:
    process, port = start(ws, rigs)
    try:
        before = rss_mb(process.pid)
        held = []
        for i in range(count):
            sock = socket.create_connection(("127.0.0.1", port), timeout=5)
            if i % 2:
                sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
            held.append(sock)
        statuses = [httpx.get(f"http://127.0.0.1:{port}{p}", timeout=5).status_code
                    for p in ("/healthz", "/readyz")]  # fmt: skip
        held_rss = rss_mb(process.pid)
        start_t = time.monotonic()
        open_ = set(range(count))
        while open_ and time.monotonic() - start_t < 60:
            for i in list(open_):
                held[i].setblocking(False)
                try:
                    if held[i].recv(1) == b"":
                        open_.discard(i)
                except BlockingIOError:
                    pass
                except OSError:
                    open_.discard(i)
            time.sleep(0.1)
        print(f"slowloris, {ws:17s} {count} conn: /healthz,/readyz {statuses}; RSS {before:.1f} "
              f"-> {held_rss:.1f} MB held; all closed after {time.monotonic() - start_t:.1f} s "
              f"({len(open_)} still open)")  # fmt: skip
        for sock in held:
            sock.close()
    finally:
        stop(process)


def refused_silent(ws: str, rigs: Path) -> None:
    process, port = start(ws, rigs)
    try:
        t0 = time.monotonic()
        sock, _ = open_raw(port, "/v1/stream")
        sock.settimeout(0.2)
        # Read nothing until the server is done with it: then the socket has EOF/RST queued.
        while time.monotonic() - t0 < 60:
            try:
                sock.send(b"")
            except OSError:
                break
            info = subprocess.run(["ss", "-tnH", "state", "established", f"( sport = :{port} )"],
                                  capture_output=True, text=True).stdout  # fmt: skip
            if not info.strip():
                break
            time.sleep(0.1)
        print(
            f"refused, reads nothing, {ws:17s}: server side gone after "
            f"{time.monotonic() - t0:.1f} s"
        )
        sock.close()
    finally:
        stop(process)


def large_messages(ws: str, rigs: Path, connections: int = 10) -> None:
    """Refused connections each sending 2 MiB messages (just under ws_max_size) unread."""
    process, port = start(ws, rigs)
    try:
        before = peak = rss_mb(process.pid)
        peers = [open_raw(port, "/v1/stream") for _ in range(connections)]

        def run(sock: socket.socket, conn) -> None:
            conn.send_binary(b"\x00" * (2 * 1024 * 1024))
            message = b"".join(conn.data_to_send())
            sock.settimeout(0.5)
            deadline = time.monotonic() + 6
            for _ in range(40):
                try:
                    sock.sendall(message)
                except OSError:
                    return
                if time.monotonic() > deadline:
                    return

        threads = [threading.Thread(target=run, args=peer) for peer in peers]
        for thread in threads:
            thread.start()
        while any(t.is_alive() for t in threads):
            peak = max(peak, rss_mb(process.pid))
            time.sleep(0.1)
        print(f"large messages, {ws:17s} {connections} refused conn x 40 x 2 MiB: RSS "
              f"{before:.1f} -> peak {peak:.1f} MB")  # fmt: skip
        for sock, _ in peers:
            sock.close()
    finally:
        stop(process)


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="facecast-hostile-") as tmp:
        rigs = Path(tmp)
        for ws in ("websockets-sansio", "websockets"):
            ping_flood(ws, rigs, 1)
            ping_flood(ws, rigs, 10)
            slowloris(ws, rigs)
            refused_silent(ws, rigs)
            large_messages(ws, rigs)


if __name__ == "__main__":
    main()
