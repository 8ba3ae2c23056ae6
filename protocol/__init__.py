"""facecast.protocol: the wire format, sans-I/O (bytes in, typed messages out).

No asyncio, no sockets; imports only numpy and msgpack. The spec is PROTOCOL.md.
"""
