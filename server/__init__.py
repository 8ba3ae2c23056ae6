"""facecast.server: FastAPI + uvicorn service holding fitted rigs and streaming sessions.

It owns all I/O of the service (HTTP, WebSocket, files, Redis); the math is ``facecast.rig``
and the wire format ``facecast.protocol``.
"""
