"""Where a frame's numbers are made: its weights (smoothed) and vertices, batched vertex
blends, stage timings.
"""
