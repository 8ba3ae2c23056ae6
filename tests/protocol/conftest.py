"""Shared fixtures for the protocol tests (helpers live in _protocol_wire)."""

from __future__ import annotations

import pytest
from _protocol_wire import raw


@pytest.fixture
def raw_message():
    return raw
