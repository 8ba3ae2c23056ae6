"""Recorded tracker takes -> source animations: Live Link Face CSV and MediaPipe NDJSON.

The public names of the two readers, livelink_csv.py and mediapipe_ndjson.py (each file's
format is described there), for the callers that import them from here.
"""

from __future__ import annotations

from .livelink_csv import LiveLinkTake, livelink_csv_animation, parse_timecode, read_livelink_csv
from .mediapipe_ndjson import (
    MEDIAPIPE_FEATURES,
    MediaPipeTake,
    load_mediapipe_mapping,
    mediapipe_animation,
    read_mediapipe_ndjson,
)
from .take_text import MAX_TAKE_FRAMES

__all__ = [
    "MAX_TAKE_FRAMES",
    "MEDIAPIPE_FEATURES",
    "LiveLinkTake",
    "MediaPipeTake",
    "livelink_csv_animation",
    "load_mediapipe_mapping",
    "mediapipe_animation",
    "parse_timecode",
    "read_livelink_csv",
    "read_mediapipe_ndjson",
]
