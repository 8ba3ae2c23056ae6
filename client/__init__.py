"""facecast.client: the Python client library, the ``facecast`` CLI, load generator and viewer.

It talks to a server through ``facecast.protocol`` and HTTP only; the ``demo`` command and
the snapshot tool are the exceptions that also start a server in-process.
"""

from facecast.client.connection import ConnectionFailed, Reconnect, StreamSession, connect

__all__ = ["ConnectionFailed", "Reconnect", "StreamSession", "connect"]
