"""facecast.client: the Python client library, the ``facecast`` CLI, load generator and viewer.

It talks to a server only through ``facecast.protocol`` and HTTP; it never reaches into
``facecast.server``.
"""
