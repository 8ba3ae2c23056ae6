"""The one reconnection loop of the client: a backoff policy and the loops that apply it.

Stream sessions, channel publishers and channel watchers all re-open a lost connection
through `reopen_with_backoff`; sessions and publishers keep reading, and re-opening, in
`supervise`. What "open" and "read" mean (handshake, ``hello``, ``ready``, messages) is
theirs. No sockets here: the loops only call what they are given and sleep between calls.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import TypeVar

from websockets.exceptions import ConnectionClosed, WebSocketException

from facecast.protocol import ErrorCode, ProtocolError

from .errors import ConnectionFailed

__all__ = [
    "OPEN_ERRORS",
    "RETRYABLE_CODES",
    "Reconnect",
    "describe",
    "reopen_with_backoff",
    "supervise",
]

#: Fatal server errors after which reconnecting may succeed; any other fatal error is final.
RETRYABLE_CODES = frozenset({ErrorCode.OVERLOADED, ErrorCode.IDLE_TIMEOUT, ErrorCode.INTERNAL})

#: What failing to open a connection raises (refused, unreachable, handshake refused or
#: timed out); another attempt may succeed.
OPEN_ERRORS: tuple[type[BaseException], ...] = (OSError, TimeoutError, WebSocketException)

T = TypeVar("T")


@dataclass(frozen=True)
class Reconnect:
    """How hard to try to re-open a lost session.

    Attempt ``n`` (from 0) waits ``min(max_delay, initial_delay * factor**n)`` seconds
    first; after ``attempts`` failures in a row the session fails. ``attempts=0`` turns
    reconnection off.
    """

    attempts: int = 5
    initial_delay: float = 0.1
    max_delay: float = 5.0
    factor: float = 2.0

    def __post_init__(self) -> None:
        if self.attempts < 0 or self.initial_delay < 0 or self.max_delay < 0 or self.factor < 1:
            raise ValueError(f"invalid reconnection policy {self!r}")

    def delay(self, attempt: int) -> float:
        return min(self.max_delay, self.initial_delay * self.factor**attempt)


async def reopen_with_backoff(
    open_once: Callable[[], Awaitable[T]],
    reconnect: Reconnect,
    last: BaseException | None,
    *,
    gave_up: Callable[[BaseException | None], str],
    sleep: Callable[[float], Awaitable[object]] = asyncio.sleep,
) -> T:
    """Call ``open_once()`` after each backoff delay until it succeeds or the attempts run out.

    One call re-opens one lost connection, counting attempts from 0: a caller that loses
    the connection again calls it again, so the backoff starts over after every success.

    Parameters
    ----------
    open_once : async callable
        Opens the connection (and waits for ``ready``); raises on failure.
    reconnect : Reconnect
        The policy: how many attempts, how long before each.
    last : BaseException or None
        Why the connection was lost: the last error when no attempt is made.
    gave_up : callable
        The message of the `ConnectionFailed` raised on giving up, from the last error
        (None: the connection closed without one).
    sleep : async callable
        Waits the given seconds before an attempt (`asyncio.sleep`; a test's clock).

    Returns
    -------
    What ``open_once`` returned, once it succeeds.

    Raises
    ------
    ConnectionFailed
        ``reconnect.attempts`` attempts failed in a row (``attempts``, ``last_error``).
    ProtocolError
        A server error that retrying cannot cure (not in `RETRYABLE_CODES`), at once.
    """
    for attempt in range(reconnect.attempts):
        await sleep(reconnect.delay(attempt))
        try:
            opened = await open_once()
        except ProtocolError as exc:
            if exc.code not in RETRYABLE_CODES:
                raise
            last = exc
        except OPEN_ERRORS as exc:
            last = exc
        else:
            return opened
    raise ConnectionFailed(gave_up(last), attempts=reconnect.attempts, last_error=last)


async def supervise(
    read: Callable[[], Awaitable[BaseException | None]],
    reopen: Callable[[BaseException | None], Awaitable[object]],
    *,
    closing: Callable[[], bool],
    lost: Callable[[], None] = lambda: None,
) -> None:
    """Read a connection until it ends, then re-open it; again, until ``closing()``.

    ``read()`` returns when the connection ends, with the fatal error that ended it (or
    None); a dropped connection (``ConnectionClosed``, ``OSError``) is such an end too.
    Unless the caller is closing, ``lost()`` is told, then ``reopen(reason)`` re-opens
    (`reopen_with_backoff`). Returns once closing; raises the fatal `ProtocolError` that
    retrying cannot cure (not in `RETRYABLE_CODES`), or ``reopen``'s `ConnectionFailed`.
    """
    while True:
        reason: BaseException | None
        try:
            reason = await read()
        except (ConnectionClosed, OSError) as exc:
            reason = exc
        if closing():
            return
        lost()
        if isinstance(reason, ProtocolError) and reason.code not in RETRYABLE_CODES:
            raise reason
        await reopen(reason)


def describe(exc: BaseException) -> str:
    """``exc`` for a message: a protocol error as it prints, anything else with its type."""
    text = str(exc) or type(exc).__name__
    return text if isinstance(exc, ProtocolError) else f"{type(exc).__name__}: {text}"
