"""One WebSocket connection, whatever its kind: the sans-I/O rules, the asyncio driver,
admission, the registry, refusals.
"""
