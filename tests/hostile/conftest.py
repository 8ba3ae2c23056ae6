"""Fixtures of the hostile-client suite: a rig directory, tokens, uvicorn's implementations.

Every flood here targets a real server on 127.0.0.1 and is bounded in count and time.
"""

from __future__ import annotations

import pytest

from facecast.server.serving.http_guard import HTTP_IMPLEMENTATIONS
from tests.channels._helpers import RIG_IDS, tiny_rig, write_rigs

TOKENS = {
    "stream-token": frozenset({"stream"}),
    "viewer-token": frozenset({"viewer"}),
    "other-viewer-token": frozenset({"viewer"}),
    "publisher-token": frozenset({"publisher"}),
}


@pytest.fixture(params=sorted(set(HTTP_IMPLEMENTATIONS) - {"auto"}))
def http_impl(request) -> str:
    """uvicorn's HTTP implementation under test."""
    return request.param


@pytest.fixture(scope="session")
def rigs():
    return {rig_id: tiny_rig(seed) for seed, rig_id in enumerate(RIG_IDS)}


@pytest.fixture
def rigs_dir(tmp_path, rigs):
    directory = tmp_path / "rigs"
    write_rigs(directory, rigs)
    return directory


def pytest_collection_modifyitems(config, items) -> None:
    # uvicorn's "websockets" implementation is deprecated upstream but still supported
    # and tested here on purpose; its deprecation warnings are not ours to fix.
    for item in items:
        if "tests/hostile/" in item.nodeid:
            item.add_marker(pytest.mark.filterwarnings("ignore::DeprecationWarning"))
            item.add_marker(
                pytest.mark.filterwarnings("ignore::uvicorn.config.UvicornDeprecationWarning")
            )
