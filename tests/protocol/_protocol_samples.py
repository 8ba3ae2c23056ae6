"""One fixed example of every protocol message, shared by the golden-bytes tests.

Test data only: the same objects are shown as hex in protocol/PROTOCOL.md.
"""

from __future__ import annotations

import numpy as np

from facecast.protocol import (
    Calibrate,
    Calibrated,
    ChannelIdle,
    ChannelLive,
    Error,
    ErrorCode,
    FaceLost,
    Frame,
    Hello,
    Message,
    Ping,
    Pong,
    Ready,
    Result,
    Smoothing,
)

SAMPLES: dict[str, Message] = {
    "hello": Hello(
        rig="demo",
        output="weights",
        dtype="f32",
        align=True,
        smoothing=Smoothing(min_cutoff=1.0, beta=0.5, d_cutoff=1.0, target="points"),
    ),
    "frame": Frame(
        seq=7,
        ts=12.5,
        points=np.array([[0.0, 1.0, 2.0], [-0.5, 0.25, 1.5]], dtype=np.float32),
    ),
    "calibrate": Calibrate(),
    "ping": Ping(id=1, ts=3.25),
    "ready": Ready(
        session="s1",
        rig="demo",
        names=("neutral", "smile", "jaw_open"),
        num_points=2,
        num_vertices=4,
        output="weights",
        dtype="f32",
        # What a server with default settings sends (PROTOCOL.md §7, §10.6).
        limits={
            "max_points": 4096,
            "max_fps": 240.0,
            "rate_burst": 60,
            "calibrate_rate": 1.0,
            "calibrate_burst": 4,
            "max_message_bytes": 1048576,
            "idle_timeout": 60.0,
        },
    ),
    "result": Result(
        seq=7,
        ts=12.5,
        weights=np.array([0.5, 0.25, 0.25], dtype=np.float32),
        proc_us=180,
        dropped=2,
    ),
    "error": Error(code=ErrorCode.WRONG_POINT_COUNT, message="need K=2 points", seq=8, fatal=False),
    "pong": Pong(id=1, ts=3.25),
    "calibrated": Calibrated(active=True, seq=9),
    "channel_idle": ChannelIdle(channel="stage"),
    "channel_live": ChannelLive(channel="stage"),
    "face_lost": FaceLost(since=12.5),
}
