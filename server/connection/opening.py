"""What opening a connection takes: its rig, loaded off the loop, and the ``ready`` it answers.

One rule for ``/v1/stream`` sessions, channel publishers and watchers: a rig that cannot be
loaded is a fatal UNKNOWN_RIG (PROTOCOL.md §7), and ``ready`` states the limits the server
enforces (§5.1). No sockets here.
"""

from __future__ import annotations

import asyncio

from facecast.protocol import ErrorCode, Hello, Limits, ProtocolError, Ready
from facecast.rig import Rig
from facecast.rig.errors import RigError

from ..compute.cloning import smoothing_name
from ..settings import Settings
from ..storage.rig_store import RigNotFoundError, RigStore, valid_rig_id

__all__ = ["load_rig", "ready_message", "rig_unavailable", "watch_ready"]


async def load_rig(store: RigStore, rig_id: str) -> Rig:
    """The rig ``rig_id`` from ``store`` (file I/O and parsing in a thread, never on the loop).

    Raises the fatal UNKNOWN_RIG ProtocolError when there is no such rig or it cannot be
    loaded.
    """
    if not valid_rig_id(rig_id):
        raise ProtocolError(ErrorCode.UNKNOWN_RIG, f"no rig with id {rig_id[:64]!r}", fatal=True)
    try:
        rig: Rig = await asyncio.get_running_loop().run_in_executor(None, store.get, rig_id)
    except (RigNotFoundError, RigError) as exc:
        raise rig_unavailable(rig_id, exc) from None
    return rig


def rig_unavailable(rig_id: str, exc: Exception) -> ProtocolError:
    """The fatal UNKNOWN_RIG for a ``hello`` whose rig could not be loaded (``exc``)."""
    if isinstance(exc, RigNotFoundError):
        return ProtocolError(ErrorCode.UNKNOWN_RIG, f"no rig with id {rig_id!r}", fatal=True)
    return ProtocolError(
        ErrorCode.UNKNOWN_RIG, f"rig {rig_id!r} cannot be loaded: {exc}", fatal=True
    )


def ready_message(
    session_id: str, hello: Hello, rig: Rig, limits: Limits, settings: Settings
) -> Ready:
    """The ``ready`` answering ``hello`` for ``rig``, with the limits the server enforces."""
    return Ready(
        session=session_id,
        rig=hello.rig,
        names=rig.names,
        num_points=rig.num_points,
        num_vertices=rig.num_vertices,
        output=hello.output,
        dtype=hello.dtype,
        moving=rig.moving_vertices if hello.output == "moving" else None,
        smoothing=None if hello.smoothing is None else smoothing_name(hello.smoothing, rig),
        limits={
            "max_points": int(limits.max_points),
            "max_fps": float(settings.max_fps),
            "rate_burst": int(settings.rate_burst),
            "calibrate_rate": float(settings.calibrate_rate),
            "calibrate_burst": int(settings.calibrate_burst),
            "max_message_bytes": int(settings.max_message_bytes),
            "idle_timeout": float(settings.idle_timeout),
        },
    )


def watch_ready(
    session_id: str, rig_id: str, rig: Rig, output: str, dtype: str, settings: Settings
) -> Ready:
    """The ``ready`` a channel watcher gets on joining (§2.1): what it will receive.

    Its limits hold ``max_message_bytes`` only: a watcher sends no frames or calibrations.
    """
    return Ready(
        session=session_id,
        rig=rig_id,
        names=rig.names,
        num_points=rig.num_points,
        num_vertices=rig.num_vertices,
        output=output,
        dtype=dtype,
        limits={"max_message_bytes": int(settings.max_message_bytes)},
    )
