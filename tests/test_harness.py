"""The process harness the benchmarks and the tests share (``facecast.cli.bench.harness``)."""

from __future__ import annotations

import shutil

import pytest

from facecast.cli.bench.harness import RedisServer, accepts_connections, python_server


def test_a_server_that_dies_before_listening_is_reported_with_its_log(tmp_path):
    server = python_server(
        "facecast.cli.bench.servers:serve_vertices_floor", str(tmp_path / "no-such-folder"),
        log_path=tmp_path / "floor.log",
    )  # fmt: skip

    with server, pytest.raises(RuntimeError) as caught:
        server.wait_listening(timeout=60)

    assert "exited with 1 before listening" in str(caught.value)
    assert "bare.npz" in str(caught.value)  # the end of its log: what it could not read


def test_a_floor_server_listens_until_stopped(tmp_path):
    server = python_server("facecast.cli.bench.servers:serve_websockets_echo")

    with server:
        server.wait_listening(timeout=60)
        listening = accepts_connections(server.port)

    assert listening
    assert server.returncode is not None  # stopped on leaving the block
    assert not accepts_connections(server.port)


@pytest.mark.skipif(shutil.which("redis-server") is None, reason="needs redis-server")
def test_redis_comes_back_on_the_same_port_after_a_kill():
    redis = RedisServer().start()
    try:
        port = redis.port
        redis.kill()
        down = redis.ping()
        redis.start()
        up = redis.ping()
    finally:
        redis.kill()

    assert (down, up) == (False, True)
    assert redis.port == port and redis.url == f"redis://127.0.0.1:{port}/0"
