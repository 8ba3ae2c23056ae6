"""The minor items of issue #13: one "publisher left" line per publisher (the exit status
after SIGTERM is tested in tests/server/test_server_process.py, wsproto in test_hostile_settings).
"""

from __future__ import annotations

import logging

import pytest

from facecast.server.settings import Settings
from facecast.server.testing import run_server
from tests.channels._helpers import Publisher, wait_for

pytestmark = pytest.mark.anyio


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.events: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.events.append(getattr(record, "event", ""))


async def test_a_publisher_leaving_is_logged_once(rigs_dir, ws_impl):
    records = _Records()
    logger = logging.getLogger("facecast.server.channels")
    try:
        async with run_server(Settings(rigs_dir=rigs_dir), ws=ws_impl) as server:
            logger.addHandler(records)  # after uvicorn has configured logging
            publisher = await Publisher.open(server.ws_url, "stage", "alpha")
            await publisher.close()
            # The route's task ends after both of its leave() calls.
            tasks = server.server.server_state.tasks
            await wait_for(lambda: not tasks, 5, "the publisher's connection to end")
    finally:
        logger.removeHandler(records)

    assert records.events.count("channel.unpublish") == 1
