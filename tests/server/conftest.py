"""Fixtures of the server tests: a real uvicorn per test (``run_server``), rigs, tokens.

``run_server`` itself lives in ``facecast.server.testing`` so other packages' tests can
import it; it is re-exported here.
"""

from __future__ import annotations

import pytest
from _server_helpers import tiny_rig

from facecast.server.settings import Settings
from facecast.server.testing import run_server

__all__ = ["run_server"]

TOKENS = {
    "admin-token": frozenset({"admin"}),
    "stream-token": frozenset({"stream"}),
    "viewer-token": frozenset({"viewer"}),
    "publisher-token": frozenset({"publisher"}),
}


@pytest.fixture(scope="session")
def rig():
    return tiny_rig()


@pytest.fixture
def settings(tmp_path) -> Settings:
    """Open (no auth) settings over a fresh rig directory."""
    return Settings(rigs_dir=tmp_path / "rigs")


@pytest.fixture
def auth_settings(tmp_path) -> Settings:
    return Settings(rigs_dir=tmp_path / "rigs", auth=True, tokens=TOKENS)


def pytest_collection_modifyitems(config, items) -> None:
    # uvicorn's "websockets" implementation is deprecated upstream but still shipped and
    # still tested here on purpose; its deprecation warnings are not ours to fix.
    for item in items:
        if "tests/server/" in item.nodeid:
            item.add_marker(pytest.mark.filterwarnings("ignore::DeprecationWarning"))
            item.add_marker(
                pytest.mark.filterwarnings("ignore::uvicorn.config.UvicornDeprecationWarning")
            )
