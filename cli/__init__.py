"""facecast.cli: the ``facecast`` command and the tools behind it, built on facecast.client.

Commands, benchmarks, the load generator, the renderer, the snapshot tool, report helpers
and the tracker/VMC bridges; nothing here is imported by the client library or the server.
"""
