"""Fixtures of the channel tests: rigs on disk, a real redis-server per test that needs one."""

from __future__ import annotations

import pytest

from facecast.cli.bench.harness import RedisServer
from facecast.server.settings import Settings

from ._helpers import RIG_IDS, tiny_rig, write_rigs

TOKENS = {
    "admin-token": frozenset({"admin"}),
    "stream-token": frozenset({"stream"}),
    "viewer-token": frozenset({"viewer"}),
    "publisher-token": frozenset({"publisher"}),
}


@pytest.fixture(scope="session")
def rigs():
    """Three different rigs with the same K: three characters for one performer."""
    return {rig_id: tiny_rig(seed) for seed, rig_id in enumerate(RIG_IDS)}


@pytest.fixture
def rigs_dir(tmp_path, rigs):
    directory = tmp_path / "rigs"
    write_rigs(directory, rigs)
    return directory


@pytest.fixture
def settings(rigs_dir) -> Settings:
    return Settings(rigs_dir=rigs_dir, face_lost_after=30.0)


@pytest.fixture
def redis_server():
    server = RedisServer()
    server.start()
    try:
        yield server
    finally:
        server.kill()


def pytest_collection_modifyitems(config, items) -> None:
    for item in items:
        if "tests/channels/" in item.nodeid:
            item.add_marker(pytest.mark.filterwarnings("ignore::DeprecationWarning"))
