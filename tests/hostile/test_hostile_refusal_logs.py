"""Refusals a client controls are logged at info, once per streak (issue 25, item 6).

Before: every cross-origin WebSocket handshake refused on the default (sans-I/O)
implementation logged "ASGI callable returned without completing handshake." at error
level, and every refusal an info line of its own: a log flood any web page could cause.
"""

from __future__ import annotations

import logging

import pytest
import websockets

from facecast.server.logs import STREAK_GAP, STREAK_REPORT, RefusalLog
from facecast.server.settings import Settings
from facecast.server.testing import run_server
from tests.channels._helpers import wait_for

pytestmark = pytest.mark.anyio

ATTACKER = "http://attacker.example"
ATTEMPTS = 20


class Records(logging.Handler):
    """Every record the server's loggers let through, whatever its level."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    def events(self, event: str) -> list[logging.LogRecord]:
        return [r for r in self.records if getattr(r, "event", None) == event]

    def above_info(self) -> list[str]:
        return [f"{r.levelname} {r.getMessage()}" for r in self.records if r.levelno > logging.INFO]


class captured:
    """Attach `Records` to uvicorn's and facecast's loggers (after uvicorn configured them)."""

    names = ("uvicorn.error", "uvicorn", "facecast")

    def __enter__(self) -> Records:
        self.handler = Records()
        for name in self.names:
            logging.getLogger(name).addHandler(self.handler)
        return self.handler

    def __exit__(self, *exc: object) -> None:
        for name in self.names:
            logging.getLogger(name).removeHandler(self.handler)


async def test_refused_cross_origin_handshakes_log_one_info_line_and_no_error(tmp_path, ws_impl):
    settings = Settings(rigs_dir=tmp_path / "rigs", access_log=False)
    async with run_server(settings, ws=ws_impl) as server:
        with captured() as logs:
            statuses = []
            for _ in range(ATTEMPTS):
                with pytest.raises(websockets.InvalidStatus) as info:
                    async with websockets.connect(f"{server.ws_url}/v1/stream", origin=ATTACKER):
                        pass
                statuses.append(info.value.response.status_code)
            # Each denial's handler has returned once its connection is gone.
            await _connections_closed(server)

    assert statuses == [403] * ATTEMPTS
    assert logs.above_info() == []
    (line,) = logs.events("http.refused")
    assert line.levelno == logging.INFO and line.code == "origin_not_allowed"


async def test_tokenless_stream_attempts_log_one_line_per_streak(tmp_path, ws_impl):
    settings = Settings(rigs_dir=tmp_path / "rigs", access_log=False, auth=True,
                        tokens={"secret": frozenset({"admin"})})  # fmt: skip
    async with run_server(settings, ws=ws_impl) as server:
        with captured() as logs:
            for _ in range(ATTEMPTS):
                async with websockets.connect(f"{server.ws_url}/v1/stream") as ws:
                    # A first message is answered at once (without one the refusal waits
                    # 1 s for it): the streak is the same, the test 20 s shorter.
                    await ws.send(b"\x80")
                    with pytest.raises(websockets.ConnectionClosed):
                        while True:
                            await ws.recv()
            await _connections_closed(server)

    assert logs.above_info() == []
    (line,) = logs.events("stream.refused")
    assert line.code == "UNAUTHORIZED" and line.suppressed == 0


async def _connections_closed(server) -> None:
    tasks = server.server.server_state.tasks
    await wait_for(lambda: not tasks, 10, "the refused connections' handlers to end")


# -- the rule, with its clock passed in ------------------------------------------------
def _log() -> tuple[RefusalLog, Records]:
    logger = logging.getLogger("tests.refusal_log")
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    records = Records()
    for old in list(logger.handlers):
        logger.removeHandler(old)
    logger.addHandler(records)
    return RefusalLog(logger, "x.refused", "refused"), records


def test_a_streak_is_one_line_and_the_next_streak_says_how_many_were_not_logged():
    log, records = _log()
    logged = [log.refused("bad", t) for t in (0.0, 1.0, 2.0, 2.0 + STREAK_GAP * 0.99)]
    assert logged == [True, False, False, False]
    assert log.refused("bad", 2.0 + STREAK_GAP * 2.0)  # a quiet gap: a new streak
    assert [r.suppressed for r in records.records] == [0, 3]


def test_codes_have_streaks_of_their_own():
    log, records = _log()
    assert log.refused("a", 0.0) and log.refused("b", 0.5)
    assert not log.refused("a", 1.0)
    assert [r.code for r in records.records] == ["a", "b"]


def test_a_streak_that_goes_on_is_summarised_every_report_interval():
    log, records = _log()
    steps = int(STREAK_REPORT / (STREAK_GAP / 2)) + 1
    times = [i * STREAK_GAP / 2 for i in range(steps + 1)]  # never a quiet gap
    logged = [t for t in times if log.refused("flood", t)]
    assert logged[0] == 0.0 and len(logged) == 2 and logged[1] >= STREAK_REPORT
    assert records.records[1].suppressed == times.index(logged[1]) - 1
