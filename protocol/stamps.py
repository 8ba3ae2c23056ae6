"""The optional stage times a ``frame`` carries and a channel ``result`` relays (PROTOCOL.md §5.4).

One small value type with its checks, its wire map and the plausibility window a server
applies; it knows nothing of sessions or figures (the viewer pages compute those).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Final

from facecast.protocol.fields import check_float, check_map

__all__ = ["PUBLISHER_STAMPS", "STAMP_FUTURE_SLACK", "STAMP_MAX_AGE", "Stamps"]

#: The stamps a publisher sets, in the order of the path (§5.4).
PUBLISHER_STAMPS: Final = ("captured", "tracked", "sent")
#: A publisher stamp later than the server's arrival time by more than this (seconds) is
#: from the future: the server does not relay it. Clock offsets estimated by ping (§5.4)
#: are good to half a round trip; a second covers any sane one.
STAMP_FUTURE_SLACK: Final = 1.0
#: A publisher stamp older than this (seconds) at the server's arrival is not relayed: no
#: live frame spends 10 s before its server.
STAMP_MAX_AGE: Final = 10.0


@dataclass(frozen=True, kw_only=True)
class Stamps:
    """Times of one frame along the path, seconds on the server's clock (Unix epoch).

    Attributes
    ----------
    captured : float or None
        The camera frame's capture time (the browser's frame metadata, else its arrival).
    tracked : float or None
        When the tracker's landmarks were ready.
    sent : float or None
        When the frame was handed to the publisher's socket.
    server_in : float or None
        When the server received the frame; set by the server, never by a publisher.

    Each is optional: a sender sets what it knows. The publisher's three are its own
    clock plus its estimate of the server's offset (§5.4); they are figures for people
    and benchmarks only, never used to decide anything.
    """

    captured: float | None = None
    tracked: float | None = None
    sent: float | None = None
    server_in: float | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if value is not None:
                object.__setattr__(self, f.name, check_float(value, f"stamps.{f.name}"))

    def serialize(self) -> dict[str, float]:
        return {f.name: v for f in fields(self) if (v := getattr(self, f.name)) is not None}

    @classmethod
    def parse(cls, obj: Any, where: str) -> Stamps:
        """The stamps in a decoded wire map; ProtocolError (with ``where`` in it) otherwise.

        Unknown keys are ignored (§3); nil is absence.
        """
        check_map(obj, where)
        assert isinstance(obj, Mapping)
        values = {}
        for f in fields(cls):
            value = obj.get(f.name)
            if value is not None:
                values[f.name] = check_float(value, f"{where}.{f.name}")
        stamps = object.__new__(cls)  # checked above: skip __post_init__'s second pass
        stamps.__dict__.update(dict.fromkeys(f.name for f in fields(cls)) | values)
        return stamps

    def arrived(self, server_in: float) -> Stamps | None:
        """These publisher stamps as the server relays them, received at ``server_in``.

        A stamp outside [server_in - STAMP_MAX_AGE, server_in + STAMP_FUTURE_SLACK] is
        dropped (a wrong clock, or a lie), and so is one out of the path's order after the
        ones kept; a publisher's own ``server_in`` is replaced. None: nothing to relay.
        """
        kept: dict[str, float] = {}
        last = server_in - STAMP_MAX_AGE
        for name in PUBLISHER_STAMPS:
            value = getattr(self, name)
            if value is not None and last <= value <= server_in + STAMP_FUTURE_SLACK:
                kept[name] = last = value
        if not kept:
            return None
        return Stamps(**kept, server_in=server_in)
