"""Broadcast channels: a publisher and its watchers, their outbox, fan-out once per key, the
bus between processes, the routes.
"""
