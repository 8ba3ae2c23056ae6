"""The pieces pinned to uvicorn's internals: its HTTP and WebSocket protocols with guards, and
the transport seam.
"""
