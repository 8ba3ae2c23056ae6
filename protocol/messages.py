"""The twelve protocol messages, by direction, and the public name every caller imports (§5).

Each family lives in its own module: handshake (`Hello`, `Smoothing`, `Ready`), frames
(`Frame`, `Result`), calibration (`Calibrate`, `Calibrated`), control (`Ping`, `Pong`,
`Error`, channel events); `Message` in message.py. Framing, version and type dispatch live
in codec.py, session order in connection.py.
"""

from __future__ import annotations

from typing import Final

from facecast.protocol.arrays import WIRE_DTYPES
from facecast.protocol.calibration import Calibrate, Calibrated
from facecast.protocol.control import (
    MAX_ERROR_MESSAGE,
    ChannelIdle,
    ChannelLive,
    Error,
    FaceLost,
    Ping,
    Pong,
)
from facecast.protocol.frames import Frame, Result
from facecast.protocol.handshake import (
    CHANNEL_OUTPUTS,
    KALMAN_ACCELERATION,
    MOVING_DTYPE,
    OUTPUTS,
    POINTS_DTYPES,
    READY_OUTPUTS,
    RESULT_DTYPES,
    SMOOTHING_FILTERS,
    SMOOTHING_TARGETS,
    WATCH_OUTPUTS,
    Hello,
    Ready,
    Smoothing,
)
from facecast.protocol.message import PROTOCOL_VERSION, Message

ClientMessage = Hello | Frame | Calibrate | Ping
ServerMessage = Ready | Result | Error | Pong | Calibrated | ChannelIdle | ChannelLive | FaceLost

CLIENT_MESSAGES: Final[dict[str, type[Message]]] = {
    cls.TYPE: cls for cls in (Hello, Frame, Calibrate, Ping)
}
SERVER_MESSAGES: Final[dict[str, type[Message]]] = {
    cls.TYPE: cls
    for cls in (Ready, Result, Error, Pong, Calibrated, ChannelIdle, ChannelLive, FaceLost)
}

__all__ = [
    "CHANNEL_OUTPUTS",
    "CLIENT_MESSAGES",
    "KALMAN_ACCELERATION",
    "MAX_ERROR_MESSAGE",
    "MOVING_DTYPE",
    "OUTPUTS",
    "POINTS_DTYPES",
    "PROTOCOL_VERSION",
    "READY_OUTPUTS",
    "RESULT_DTYPES",
    "SERVER_MESSAGES",
    "SMOOTHING_FILTERS",
    "SMOOTHING_TARGETS",
    "WATCH_OUTPUTS",
    "WIRE_DTYPES",
    "Calibrate",
    "Calibrated",
    "ChannelIdle",
    "ChannelLive",
    "ClientMessage",
    "Error",
    "FaceLost",
    "Frame",
    "Hello",
    "Message",
    "Ping",
    "Pong",
    "Ready",
    "Result",
    "ServerMessage",
    "Smoothing",
]
