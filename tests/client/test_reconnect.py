"""The client's one reconnection loop: backoff bounds, giving up, starting over after success.

The loop is driven against a real server (and a port nothing listens on); only its sleep
is a recording clock, so that the delays it asks for are read, not timed.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from websockets.asyncio.client import ClientConnection

from facecast.client.errors import ConnectionFailed
from facecast.client.handshake import await_ready, open_websocket
from facecast.client.reconnect import RETRYABLE_CODES, Reconnect, reopen_with_backoff
from facecast.client.urls import stream_url
from facecast.protocol import ClientProtocol, ErrorCode, Hello, Limits, ProtocolError
from facecast.server.settings import Settings
from facecast.server.testing import free_port, run_server

POLICY = Reconnect(attempts=4, initial_delay=0.01, max_delay=0.05, factor=3.0)


class RecordingClock:
    """An ``asyncio.sleep`` stand-in that records each delay and yields to the loop once."""

    def __init__(self) -> None:
        self.delays: list[float] = []

    async def sleep(self, seconds: float) -> None:
        self.delays.append(seconds)
        await asyncio.sleep(0)


def _dead_url() -> str:
    return f"ws://127.0.0.1:{free_port()}/v1/stream"


def _opener(urls: list[str]) -> tuple[Callable, list[str]]:
    """An ``open_once`` opening the next of ``urls`` each call, and the list of those tried."""
    tried: list[str] = []

    async def open_once() -> ClientConnection:
        url = urls[len(tried)]
        tried.append(url)
        return await open_websocket(url, {}, Limits(), open_timeout=5.0)

    return open_once, tried


def _gave_up(last: BaseException | None) -> str:
    return f"gave up: {last!r}"


def test_delays_grow_by_the_factor_up_to_max_delay():
    policy = Reconnect(attempts=8, initial_delay=0.1, max_delay=1.0, factor=2.0)

    delays = [policy.delay(n) for n in range(8)]

    assert delays == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.0, 1.0, 1.0, 1.0])


@given(
    initial=st.floats(0.0, 10.0),
    maximum=st.floats(0.0, 60.0),
    factor=st.floats(1.0, 10.0),
    attempt=st.integers(0, 200),
)
def test_a_delay_is_never_negative_nor_above_max_delay_and_never_shrinks(
    initial, maximum, factor, attempt
):
    policy = Reconnect(attempts=1, initial_delay=initial, max_delay=maximum, factor=factor)

    assert 0.0 <= policy.delay(attempt) <= maximum
    assert policy.delay(attempt) <= policy.delay(attempt + 1)


@pytest.mark.parametrize(
    "fields",
    [{"attempts": -1}, {"initial_delay": -0.1}, {"max_delay": -1.0}, {"factor": 0.5}],
)
def test_an_invalid_policy_is_refused(fields):
    with pytest.raises(ValueError, match="invalid reconnection policy"):
        Reconnect(**fields)


def test_gives_up_after_the_attempts_with_the_last_error_when_nothing_listens():
    open_once, tried = _opener([_dead_url()] * POLICY.attempts)
    clock = RecordingClock()

    with pytest.raises(ConnectionFailed, match="gave up") as caught:
        asyncio.run(
            reopen_with_backoff(open_once, POLICY, None, gave_up=_gave_up, sleep=clock.sleep)
        )

    assert len(tried) == POLICY.attempts
    assert clock.delays == pytest.approx([0.01, 0.03, 0.05, 0.05])
    assert caught.value.attempts == POLICY.attempts
    assert isinstance(caught.value.last_error, OSError)


def test_no_attempt_at_all_gives_up_at_once_with_the_reason_of_the_loss():
    open_once, tried = _opener([])
    clock = RecordingClock()
    lost = ConnectionResetError("peer went away")

    with pytest.raises(ConnectionFailed) as caught:
        asyncio.run(
            reopen_with_backoff(
                open_once, Reconnect(attempts=0), lost, gave_up=_gave_up, sleep=clock.sleep
            )
        )

    assert tried == [] and clock.delays == []
    assert caught.value.last_error is lost and caught.value.attempts == 0


def test_backoff_starts_over_after_each_success_against_a_real_server(tmp_path: Path):
    async def run() -> tuple[list[float], list[float]]:
        async with run_server(Settings(rigs_dir=tmp_path / "rigs")) as server:
            live = stream_url(server.base_url)
            delays = []
            for failures in (2, 1):  # two losses: the second starts again at delay(0)
                open_once, tried = _opener([_dead_url()] * failures + [live])
                clock = RecordingClock()
                ws = await reopen_with_backoff(
                    open_once, POLICY, None, gave_up=_gave_up, sleep=clock.sleep
                )
                await ws.close()
                assert tried[-1] == live
                delays.append(clock.delays)
            return delays[0], delays[1]

    first, second = asyncio.run(run())

    assert first == pytest.approx([0.01, 0.03, 0.05])
    assert second == pytest.approx([0.01, 0.03])


async def _hello(url: str, rig: str) -> None:
    """Open a stream at ``url`` and wait for ``ready``; the server's refusal is raised."""
    ws = await open_websocket(url, {}, Limits(), open_timeout=5.0)
    try:
        protocol = ClientProtocol(Limits())
        await ws.send(protocol.send(Hello(rig=rig)))
        await await_ready(ws, protocol)
    finally:
        await ws.close()


def test_a_refusal_retrying_cannot_cure_is_raised_at_the_first_attempt(tmp_path: Path):
    clock = RecordingClock()

    async def run() -> None:
        async with run_server(Settings(rigs_dir=tmp_path / "rigs")) as server:
            url = stream_url(server.base_url)
            await reopen_with_backoff(
                lambda: _hello(url, "no-such-rig"), POLICY, None, gave_up=_gave_up,
                sleep=clock.sleep,
            )  # fmt: skip

    with pytest.raises(ProtocolError) as caught:
        asyncio.run(run())

    assert (
        caught.value.code is ErrorCode.UNKNOWN_RIG and ErrorCode.UNKNOWN_RIG not in RETRYABLE_CODES
    )
    assert len(clock.delays) == 1


def test_an_overloaded_server_is_retried_until_the_attempts_run_out(tmp_path: Path):
    clock = RecordingClock()

    async def run() -> None:
        settings = Settings(rigs_dir=tmp_path / "rigs", max_connections=1)
        async with run_server(settings) as server:
            url = stream_url(server.base_url)
            held = await open_websocket(url, {}, Limits(), open_timeout=5.0)
            try:
                await reopen_with_backoff(
                    lambda: _hello(url, "any"), POLICY, None, gave_up=_gave_up, sleep=clock.sleep
                )
            finally:
                await held.close()

    with pytest.raises(ConnectionFailed) as caught:
        asyncio.run(run())

    assert len(clock.delays) == POLICY.attempts
    last = caught.value.last_error
    assert isinstance(last, ProtocolError) and last.code is ErrorCode.OVERLOADED
