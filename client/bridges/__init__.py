"""Bridges between facecast channels and outside tools: Live Link Face in, VMC out.

Each bridge is a thin asyncio loop around a sans-I/O codec (``livelink``'s packet
parser, ``vmc``'s OSC bundles) and ``channel``'s WebSocket publisher/watcher; none of
them computes weights itself (the server does) or imports facecast.server.
"""
