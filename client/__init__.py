"""facecast.client: the Python client library, the ``facecast`` CLI, load generator and viewer.

It talks to a server through ``facecast.protocol`` and HTTP only; the ``demo`` command and
the snapshot tool are the exceptions that also start a server in-process.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__all__ = ["ConnectionFailed", "Reconnect", "StreamSession", "connect"]

if TYPE_CHECKING:
    from facecast.client.connection import ConnectionFailed, Reconnect, StreamSession, connect


def __getattr__(name: str):
    # Loaded on first use (PEP 562), not on import: the CLI (facecast.client.cli) must set
    # its BLAS thread count before anything imports numpy, and the connection does.
    if name in __all__:
        return getattr(importlib.import_module("facecast.client.connection"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
