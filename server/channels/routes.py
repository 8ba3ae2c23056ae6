"""Channel endpoints: ``WS .../publish``, ``WS .../watch``, ``GET /v1/channels[/{name}]``.

Authenticates, validates the name and the watcher's query, admits, then hands the socket
to a member (``members``); refusals send one protocol ``error`` and close. No channel
logic lives here.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request, WebSocket
from starlette.convertors import Convertor, register_url_convertor

from facecast.protocol import (
    PUBLISH_PATH,
    WATCH_PATH,
    ErrorCode,
    Hello,
    Limits,
    ProtocolError,
    select_subprotocol,
    watch_hello,
)
from facecast.protocol.fields import check_str
from facecast.protocol.messages import POINTS_DTYPES, WATCH_OUTPUTS

from ..connection.admission import authorize_websocket, serve
from ..connection.opening import watch_ready
from ..connection.refusal import refuse
from ..errors import ApiError
from ..guards.auth import Principal, requires
from ..settings import Settings
from .hub import ChannelHub
from .members import PublisherMember, WatcherMember

__all__ = ["router"]

log = logging.getLogger("facecast.server.channels")

router = APIRouter(tags=["channels"])

Viewer = Annotated[Principal, Depends(requires("viewer"))]

MAX_NAME = 256


class _ChannelName(Convertor[str]):
    """``{name:channel}``: any characters, ``/`` and line breaks included (PROTOCOL.md §2.1).

    Starlette's own ``path`` convertor is ``.*``, which stops at a newline: a name with
    CR/LF matched no route and got a bare 403 instead of its channel.
    """

    regex = "(?s:.*)"

    def convert(self, value: str) -> str:
        return value

    def to_string(self, value: str) -> str:
        return value


register_url_convertor("channel", _ChannelName())


def _check_name(name: str) -> None:
    if not 1 <= len(name) <= MAX_NAME:
        raise ProtocolError(
            ErrorCode.INVALID_FIELD,
            f"a channel name has 1 to {MAX_NAME} characters, got {len(name)}",
            fatal=True,
        )


def _watch_query(query: Mapping[str, str], limits: Limits) -> tuple[Hello, str, str]:
    """The watcher's (hello, output, dtype) from its query string (PROTOCOL.md §2.1, §2.4).

    ``output=points`` asks for the published frames themselves; ``rig`` still names the
    layout (K) they must follow, and ``dtype`` is then "f32" or "f64". The hello (the
    rig, a weights session) only opens the watcher's protocol state; the member's key
    says what it receives. Raises a fatal INVALID_FIELD ProtocolError for a bad value.
    """
    try:
        output = check_str(query.get("output", "weights"), "query output", limits,
                           choices=WATCH_OUTPUTS)  # fmt: skip
        if output != "points":
            hello = watch_hello(query, limits)
            return hello, hello.output, hello.dtype
        dtype = check_str(query.get("dtype", "f32"), "query dtype", limits, choices=POINTS_DTYPES)
        rig = query.get("rig")
        return watch_hello({} if rig is None else {"rig": rig}, limits), output, dtype
    except ProtocolError as exc:
        raise exc.evolve(fatal=True) from None


@router.websocket(PUBLISH_PATH.replace("{name}", "{name:channel}"))
async def publish(websocket: WebSocket, name: str) -> None:
    """The channel's one publisher: ``hello`` then frames (PROTOCOL.md §2.1, §5.1)."""
    hub: ChannelHub = websocket.app.state.channels
    subprotocol = select_subprotocol(list(websocket.scope.get("subprotocols") or ()))
    try:
        principal = authorize_websocket(websocket, hub.settings, "publisher")
        _check_name(name)
    except ProtocolError as exc:
        await refuse(websocket, exc.evolve(fatal=True), subprotocol,
                     timeout=hub.settings.refuse_timeout)  # fmt: skip
        return
    member = PublisherMember(websocket, hub, name, principal.name)
    await serve(websocket, member, subprotocol, principal, publisher=True)


@router.websocket(WATCH_PATH.replace("{name}", "{name:channel}"))
async def watch(websocket: WebSocket, name: str) -> None:
    """A viewer of channel ``name`` on one rig (query ``rig``, ``output``, ``dtype``).

    ``output=points`` watchers (recorders) receive the published frames, not a clone.
    """
    hub: ChannelHub = websocket.app.state.channels
    settings: Settings = websocket.app.state.settings
    subprotocol = select_subprotocol(list(websocket.scope.get("subprotocols") or ()))
    limits = Limits(max_message_bytes=settings.max_message_bytes)
    try:
        principal = authorize_websocket(websocket, settings, "viewer")
        _check_name(name)
        hello, output, dtype = _watch_query(websocket.query_params, limits)
        rig = await hub.load_rig(hello.rig)
    except ProtocolError as exc:
        await refuse(websocket, exc.evolve(fatal=True), subprotocol,
                     timeout=settings.refuse_timeout, wait_first=False)  # fmt: skip
        return
    channel = await hub.open_channel(name)
    member = WatcherMember(websocket, channel, hello, limits, settings)
    member.key = (hello.rig, output, dtype)  # what it receives; a points key clones nothing
    member.greet(watch_ready(member.id, hello.rig, rig, output, dtype, settings))
    channel.add_watcher(member, rig)
    log.info("watcher joined", extra={"event": "channel.watch", "channel": name,
                                      "rig": hello.rig, "output": output,
                                      "by": principal.name})  # fmt: skip
    await serve(websocket, member, subprotocol, principal, wait_first=False)


@router.get("/v1/channels", summary="Channels with a publisher or viewers")
async def list_channels(request: Request, _: Viewer) -> dict[str, Any]:
    hub: ChannelHub = request.app.state.channels
    return {"channels": await hub.list()}


@router.get("/v1/channels/{name:channel}", summary="One channel's figures")
async def channel_info(name: str, request: Request, _: Viewer) -> dict[str, Any]:
    hub: ChannelHub = request.app.state.channels
    info = await hub.info(name)
    if info is None:
        raise ApiError(404, "channel_not_found", f"no channel {name[:64]!r} has members")
    return info
