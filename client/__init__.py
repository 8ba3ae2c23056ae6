"""facecast.client: the Python client library of a facecast server, and the viewer's pages.

Stream sessions, channel publish/watch sessions, reconnection, URLs and rig look-ups,
through ``facecast.protocol`` and HTTP only; the ``facecast`` command and the tools built
on this library live in ``facecast.cli``, which this package never imports.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__all__ = ["ConnectionFailed", "Reconnect", "StreamSession", "connect"]

if TYPE_CHECKING:
    from facecast.client.connection import ConnectionFailed, Reconnect, StreamSession, connect


def __getattr__(name: str) -> Any:
    # Loaded on first use (PEP 562), not on import: the CLI (facecast.cli.main) must set
    # its BLAS thread count before anything imports numpy, and the connection does.
    if name in __all__:
        return getattr(importlib.import_module("facecast.client.connection"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
