"""Bridges between facecast channels and outside tools: trackers in, VMC out.

Each bridge is a thin asyncio loop around a sans-I/O codec (``livelink``'s and
``ifacialmocap``'s packet parsers, ``vmc``'s OSC bundles) and facecast.client.channel's
WebSocket publisher/watcher; ``tracker`` holds what the trackers in share. None of them computes
weights itself (the server does) or imports facecast.server.
"""
