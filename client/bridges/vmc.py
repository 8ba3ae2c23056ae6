"""VMC out: a channel's weights as VMC protocol OSC messages for avatar apps (VSeeFace...).

Builds one OSC bundle per frame (sans-I/O, python-osc's builders) and sends it over UDP;
it must not compute weights (the channel's server does) nor read the avatar.

Per frame, in this order, in one bundle::

    /VMC/Ext/OK        (int 1 loaded, int 3 calibrated, int 0 normal mode, int tracking)
    /VMC/Ext/T         (float seconds)
    /VMC/Ext/Blend/Val (str name, float value)     one per expression
    /VMC/Ext/Blend/Apply

When the channel loses its face or its publisher, a bundle with only ``/VMC/Ext/OK``
(tracking 0) and ``/VMC/Ext/T`` tells the app. Weights are clamped to [0, 1] (VRM
expressions are 0..1; the cardinal weights may overshoot) unless ``clamp=False``; the
neutral (example 0) is not sent — VRM has no weight for "the rest".
"""

from __future__ import annotations

import asyncio
import logging
import socket
from collections.abc import AsyncIterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder

from facecast.protocol import ChannelIdle, ChannelLive, Error, FaceLost, Ready, Result

__all__ = [
    "DEFAULT_VMC_PORT",
    "VRM_PRESETS",
    "VmcBridgeStats",
    "VmcSender",
    "run_vmc_bridge",
    "vmc_frame_bundle",
    "vmc_names",
    "vmc_status_bundle",
]

log = logging.getLogger("facecast.bridges.vmc")

DEFAULT_VMC_PORT = 39539

#: facecast / VRM 1.0 expression names -> VRM 0.x blend shape presets (matched
#: case-insensitively). The demo's emotions and visemes, VRM 1.0 preset names, and the
#: presets themselves; names not listed pass through unchanged (custom clips,
#: ARKit "perfect sync" names).
VRM_PRESETS: dict[str, str] = {
    # vowels / visemes
    "aa": "A", "a": "A",
    "ih": "I", "i": "I", "ee": "E", "e": "E",
    "ou": "U", "u": "U", "oo": "U",
    "oh": "O", "o": "O",
    # emotions
    "happy": "Joy", "joy": "Joy",
    "angry": "Angry", "anger": "Angry",
    "sad": "Sorrow", "sorrow": "Sorrow",
    "relaxed": "Fun", "fun": "Fun",
    "surprised": "Surprised", "surprise": "Surprised",
    # eyes
    "blink": "Blink",
    "blinkleft": "Blink_L", "blink_l": "Blink_L",
    "blinkright": "Blink_R", "blink_r": "Blink_R",
    "lookup": "LookUp", "lookdown": "LookDown", "lookleft": "LookLeft", "lookright": "LookRight",
    "neutral": "Neutral",
}  # fmt: skip


def vmc_names(names: Sequence[str], overrides: Mapping[str, str] | None = None) -> tuple[str, ...]:
    """The VMC blend shape name for each rig expression name.

    ``overrides`` (exact rig name -> VMC name) win; then `VRM_PRESETS`, case-insensitive;
    otherwise the name itself.
    """
    overrides = dict(overrides or {})
    return tuple(overrides.get(n) or VRM_PRESETS.get(n.lower(), n) for n in names)


def _message(address: str, *args) -> OscMessageBuilder:
    builder = OscMessageBuilder(address)
    for arg in args:
        if isinstance(arg, str):
            builder.add_arg(arg, OscMessageBuilder.ARG_TYPE_STRING)
        elif isinstance(arg, int):
            builder.add_arg(arg, OscMessageBuilder.ARG_TYPE_INT)
        else:
            builder.add_arg(float(arg), OscMessageBuilder.ARG_TYPE_FLOAT)
    return builder


def _status(builder: OscBundleBuilder, tracking: bool, t: float) -> None:
    builder.add_content(_message("/VMC/Ext/OK", 1, 3, 0, 1 if tracking else 0).build())
    builder.add_content(_message("/VMC/Ext/T", float(t)).build())


def vmc_frame_bundle(
    names: Sequence[str], weights: np.ndarray, t: float, *, clamp: bool = True
) -> bytes:
    """The datagram of one frame: OK (tracking), T, one Blend/Val per name, Apply.

    Parameters
    ----------
    names : sequence of N str
        VMC names, in the order of ``weights``.
    weights : (N,) float
    t : float
        Seconds, sent as ``/VMC/Ext/T``.
    """
    values = np.asarray(weights, dtype=np.float64)
    if values.shape != (len(names),):
        raise ValueError(f"weights: expected shape ({len(names)},), got {values.shape}")
    if clamp:
        values = np.clip(values, 0.0, 1.0)
    builder = OscBundleBuilder(IMMEDIATELY)
    _status(builder, True, t)
    for name, value in zip(names, values.tolist(), strict=True):
        builder.add_content(_message("/VMC/Ext/Blend/Val", name, value).build())
    builder.add_content(_message("/VMC/Ext/Blend/Apply").build())
    return builder.build().dgram


def vmc_status_bundle(tracking: bool, t: float) -> bytes:
    """The datagram saying the tracking state without weights: OK, T."""
    builder = OscBundleBuilder(IMMEDIATELY)
    _status(builder, tracking, t)
    return builder.build().dgram


class VmcSender:
    """A UDP socket that sends VMC datagrams to (host, port); non-blocking sends.

    A VMC receiver that is not running yet is normal: ICMP "port unreachable" errors
    are ignored (and counted), the next frame is simply sent again.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_VMC_PORT) -> None:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        family, _, _, _, address = infos[0]
        self.address = address
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self.sent = 0
        self.failed = 0

    def send(self, datagram: bytes) -> bool:
        try:
            self._sock.sendto(datagram, self.address)
        except (BlockingIOError, ConnectionRefusedError, OSError) as exc:
            # A full socket buffer or an absent receiver: drop this frame, keep going.
            self.failed += 1
            if self.failed == 1 or self.failed % 1000 == 0:
                log.warning("VMC send to %s failed (%s); %d so far", self.address, exc, self.failed)
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> VmcSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class VmcBridgeStats:
    frames: int = 0
    status: int = 0
    errors: int = 0


async def run_vmc_bridge(
    messages: AsyncIterable,
    sender: VmcSender,
    *,
    overrides: Mapping[str, str] | None = None,
    clamp: bool = True,
    max_frames: int | None = None,
    clock=None,
) -> VmcBridgeStats:
    """Turn a watch stream's messages into VMC datagrams.

    Parameters
    ----------
    messages : async iterable of server messages
        ``watch_channel(...)`` (or any stream of ``Ready`` then ``Result`` weights).
        A ``Ready`` fixes the names (again after a reconnection).
    sender : VmcSender
    overrides : mapping, optional
        Rig name -> VMC name, over `VRM_PRESETS`.
    clamp : bool
        Clamp weights to [0, 1].
    max_frames : int, optional
        Return after this many frames were sent.
    clock : callable, optional
        Seconds for ``/VMC/Ext/T``; default the event loop's clock.
    """
    clock = clock or asyncio.get_running_loop().time
    stats = VmcBridgeStats()
    names: tuple[str, ...] | None = None
    async for message in messages:
        if isinstance(message, Ready):
            if message.output != "weights":
                raise ValueError("the VMC bridge needs output=weights")
            names = vmc_names(message.names[1:], overrides)
        elif isinstance(message, Result):
            if names is None or message.weights is None:
                continue
            sender.send(vmc_frame_bundle(names, message.weights[1:], clock(), clamp=clamp))
            stats.frames += 1
            if max_frames is not None and stats.frames >= max_frames:
                break
        elif isinstance(message, FaceLost | ChannelIdle | ChannelLive):
            tracking = isinstance(message, ChannelLive)
            sender.send(vmc_status_bundle(tracking, clock()))
            stats.status += 1
        elif isinstance(message, Error):
            stats.errors += 1
            log.warning("channel error: %s", message.message)
    return stats
