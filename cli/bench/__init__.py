"""Benchmarks behind ``facecast bench``: each prints figures beside a baseline from the same run.

Nothing here is a test; the figures are measured, printed and optionally written as JSON.
"""
