"""Processes that benchmarks and tests start, wait for and stop: servers, floors, Redis.

One place for a free port, a subprocess listening on it (``facecast serve``, a bare floor
server, redis-server), waiting until it accepts connections or answers ``/readyz``, and
stopping it. It never imports the server: what runs in a process is measured from outside.
In-process servers for tests are ``facecast.server.testing.run_server``'s job, not this one's.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import TracebackType

import httpx

__all__ = [
    "RedisServer",
    "ServerProcess",
    "accepts_connections",
    "answers_ok",
    "facecast_serve",
    "free_port",
    "python_server",
    "start_redis",
    "wait_until",
]

#: Seconds between two looks at a process that is starting: there is no event to wait on
#: in another process, so readiness is polled (never slept on in place of a check).
POLL_SECONDS = 0.05


def free_port(host: str = "127.0.0.1") -> int:
    """A port free right now (for a subprocess that must bind it itself)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        port: int = sock.getsockname()[1]
        return port


def accepts_connections(port: int, host: str = "127.0.0.1") -> bool:
    """Whether something listens on ``host:port`` (a TCP connect succeeds)."""
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


def wait_until(
    check: Callable[[], bool],
    what: str,
    timeout: float,
    *,
    exited: Callable[[], str | None] = lambda: None,
) -> None:
    """Poll ``check`` until true; TimeoutError after ``timeout`` seconds.

    ``exited()`` says why waiting is pointless (the process died: its status and log), or
    None; it is asked between polls and raised as RuntimeError at once.
    """
    deadline = time.monotonic() + timeout
    while not check():
        reason = exited()
        if reason is not None:
            raise RuntimeError(reason)
        if time.monotonic() > deadline:
            raise TimeoutError(f"not {what} within {timeout:g} s")
        time.sleep(POLL_SECONDS)


def answers_ok(url: str) -> bool:
    """Whether ``GET url`` answers 200 (False on any transport error)."""

    try:
        return httpx.get(url, timeout=1.0).status_code == 200
    except httpx.HTTPError:
        return False


class ServerProcess:
    """A subprocess serving on 127.0.0.1:``port``; a context manager that stops it on exit.

    Its stdout and stderr go to ``log_path`` (a file, so a chatty server never blocks on
    a full pipe), or nowhere without one; ``tail()`` reads the end of it for an error.
    """

    def __init__(
        self,
        argv: Sequence[str],
        *,
        port: int,
        name: str,
        env: Mapping[str, str] | None = None,
        log_path: Path | None = None,
        cwd: Path | None = None,
    ) -> None:
        self.argv = list(argv)
        self.port = port
        self.name = name
        self.env = None if env is None else dict(env)
        self.log_path = log_path
        self.cwd = cwd
        self.process: subprocess.Popen[bytes] | None = None

    # -- where it listens -------------------------------------------------------------------

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    @property
    def pid(self) -> int:
        return self._running().pid

    @property
    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    @property
    def returncode(self) -> int | None:
        return None if self.process is None else self.process.poll()

    # -- its life ---------------------------------------------------------------------------

    def start(self) -> ServerProcess:
        """Start the process (once); returns self, not waiting for it to listen."""
        if self.process is not None:
            raise RuntimeError(f"{self.name} was started already")
        env = None if self.env is None else {**os.environ, **self.env}
        if self.log_path is None:
            self.process = subprocess.Popen(
                self.argv, env=env, cwd=self.cwd,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )  # fmt: skip
        else:
            with self.log_path.open("wb") as log:
                self.process = subprocess.Popen(
                    self.argv, env=env, cwd=self.cwd, stdout=log, stderr=subprocess.STDOUT
                )
        return self

    def wait_until(self, check: Callable[[], bool], what: str, timeout: float) -> None:
        """Poll ``check`` until true; RuntimeError at once if the process exits meanwhile,
        TimeoutError after ``timeout`` seconds (each with the end of its log)."""
        process = self._running()

        def exited() -> str | None:
            if process.poll() is None:
                return None
            return f"{self.name} exited with {process.returncode} before {what}{self._tail()}"

        try:
            wait_until(check, what, timeout, exited=exited)
        except TimeoutError as exc:
            raise TimeoutError(f"{self.name}: {exc}{self._tail()}") from None

    def wait_listening(self, timeout: float = 60.0) -> ServerProcess:
        """Return once its port accepts connections."""
        self.wait_until(lambda: accepts_connections(self.port), "listening", timeout)
        return self

    def wait_ready(self, path: str = "/readyz", timeout: float = 30.0) -> ServerProcess:
        """Return once ``GET path`` answers 200 (facecast: ``/readyz`` or ``/healthz``)."""
        self.wait_until(lambda: answers_ok(self.base_url + path), f"ready ({path})", timeout)
        return self

    def stop(self, timeout: float = 15.0) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout`` seconds; its exit status (None: never ran)."""
        if self.process is None:
            return None
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
        return self.process.wait()

    def kill(self) -> None:
        """SIGKILL: no goodbye to its clients, as in a crash."""
        if self.alive:
            assert self.process is not None
            self.process.send_signal(signal.SIGKILL)
            self.process.wait(10)

    def tail(self, chars: int = 4000) -> str:
        """The end of its log ('' without one)."""
        if self.log_path is None or not self.log_path.exists():
            return ""
        return self.log_path.read_text(errors="replace")[-chars:]

    def _tail(self) -> str:
        text = self.tail(2000)
        return f":\n{text}" if text else ""

    def _running(self) -> subprocess.Popen[bytes]:
        if self.process is None:
            raise RuntimeError(f"{self.name} was not started")
        return self.process

    def __enter__(self) -> ServerProcess:
        return self if self.process is not None else self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()


def facecast_serve(
    rigs: Path,
    *extra: str,
    port: int | None = None,
    env: Mapping[str, str] | None = None,
    log_path: Path | None = None,
    name: str = "facecast serve",
) -> ServerProcess:
    """``facecast serve`` on 127.0.0.1 serving ``rigs`` (not started); ``extra`` flags after.

    ``env`` is added to this process's environment (``FACECAST_*`` settings).
    """
    port = free_port() if port is None else port
    argv = [sys.executable, "-m", "facecast.cli", "serve", "--host", "127.0.0.1",
            "--port", str(port), "--rigs", str(rigs), *extra]  # fmt: skip
    return ServerProcess(argv, port=port, name=name, env=env, log_path=log_path)


def python_server(
    entry: str,
    *args: object,
    port: int | None = None,
    env: Mapping[str, str] | None = None,
    log_path: Path | None = None,
    cwd: Path | None = None,
    name: str | None = None,
) -> ServerProcess:
    """A fresh interpreter running ``module:function(port, *args)`` (not started).

    The function serves on 127.0.0.1:``port`` until killed (a bench's floor server);
    ``args`` are passed as their ``repr``, so they must be literals (str, bytes, numbers).
    """
    module, _, function = entry.partition(":")
    port = free_port() if port is None else port
    call = ", ".join(repr(value) for value in (port, *args))
    code = f"from {module} import {function}; {function}({call})"
    return ServerProcess(
        [sys.executable, "-c", code], port=port, name=name or function, env=env,
        log_path=log_path, cwd=cwd,
    )  # fmt: skip


class RedisServer(ServerProcess):
    """A real redis-server on 127.0.0.1, no persistence; kill and restart on the same port."""

    def __init__(self, port: int | None = None, *, executable: str | None = None) -> None:
        exe = executable or shutil.which("redis-server") or "/usr/bin/redis-server"
        port = free_port() if port is None else port
        argv = [exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "",
                "--appendonly", "no", "--protected-mode", "no"]  # fmt: skip
        super().__init__(argv, port=port, name="redis-server")

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self, timeout: float = 10.0) -> RedisServer:
        """Start it (again, after ``kill``: same port) and return once it answers PING."""
        if self.process is not None and self.process.poll() is not None:
            self.process = None  # restarted after a kill
        super().start()
        self.wait_until(self.ping, "answering PING", timeout)
        return self

    def ping(self) -> bool:
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=0.5) as sock:
                sock.sendall(b"PING\r\n")
                return sock.recv(16).startswith(b"+PONG")
        except OSError:
            return False


def start_redis() -> RedisServer | None:
    """A started redis-server, or None when none is installed."""
    exe = shutil.which("redis-server")
    if exe is None:
        return None
    return RedisServer(executable=exe).start()
