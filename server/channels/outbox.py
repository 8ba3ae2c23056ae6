"""A channel connection: a `Driver` whose outbox keeps only the newest result.

Watchers and the publisher read through the driver's one read loop and write through its
one `Outbox` (``connection.outbox``), with ``collapse``: a result still waiting is
replaced by a newer one, so a slow client only ever slows itself. No protocol decisions
here.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from concurrent.futures import Executor

from starlette.websockets import WebSocket

from ..connection import outbox as connection_outbox
from ..connection.core import ConnectionCore
from ..connection.driver import Driver
from ..connection.outbox import Outbox
from .context import ChannelMember
from .fanout import Key

__all__ = ["MAX_OUTBOX", "Member", "offer_results"]

log = logging.getLogger("facecast.server.channels")

#: Messages waiting in one member's outbox. Consecutive results collapse into the newest,
#: so this bounds control messages (events, pongs, errors); beyond it the oldest go.
MAX_OUTBOX = 32


class Member(Driver):
    """One accepted WebSocket in a channel: its core's rules, an outbox, a writer.

    ``offer_result`` replaces a result still waiting (the viewer skips to the newest
    frame; ``skipped`` counts it); ``offer`` queues a control message. Memory per member
    is at most ``MAX_OUTBOX`` references to bytes shared with other members. The
    subclasses say what to do with frames and hellos.
    """

    watcher = True
    crash_event = "channel.crash"
    log = log

    def __init__(
        self,
        websocket: WebSocket,
        key: Key,
        core: ConnectionCore,
        member_id: str,
        executor: Executor | None = None,
    ) -> None:
        outbox = Outbox(websocket, limit=MAX_OUTBOX, collapse=True)
        super().__init__(websocket, core, f"member-{member_id}", outbox, executor=executor)
        self.id = member_id
        self.key = key

    @property
    def direct(self) -> bool:
        """Whether results are written straight to the socket (``Transport.direct``)."""
        return self.outbox.direct

    @property
    def queued(self) -> int:
        """Messages waiting to be sent (bounded by ``MAX_OUTBOX``)."""
        return self.outbox.queued

    @property
    def sent(self) -> int:
        return self.outbox.sent

    @property
    def skipped(self) -> int:
        return self.outbox.skipped

    def offer_result(self, data: bytes) -> None:
        """Send or queue one result (``offer_results`` for this member alone)."""
        self.outbox.offer_result(data)

    def offer(self, data: bytes) -> None:
        """Send or queue one control message (an event, a pong, an error)."""
        self.outbox.offer(data)


def offer_results(members: Iterable[ChannelMember], data: bytes) -> int:
    """Offer one result to every member of a key: the fan-out's loop, once per key and frame.

    The RFC 6455 frame is built once for all of them (``connection.outbox.offer_results``).
    Returns how many were offered.
    """
    return connection_outbox.offer_results([m.outbox for m in members], data)
