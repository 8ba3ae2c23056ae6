"""``WS /v1/stream``: the route and one streaming session."""
