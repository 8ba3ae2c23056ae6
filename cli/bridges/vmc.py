"""VMC out: a channel's weights as VMC protocol OSC messages for avatar apps (VSeeFace...).

Builds OSC bundles per frame (sans-I/O, python-osc's builders) and sends them over UDP;
it must not compute weights (the channel's server does) nor read the avatar.

Per frame, in this order (VMC protocol spec, Marionette side)::

    /VMC/Ext/OK        (int 1 loaded, int 3 calibrated, int 0 normal mode, int tracking)
    /VMC/Ext/T         (float seconds)
    /VMC/Ext/Bone/Pos  (str "Head", float p.x p.y p.z, float q.x q.y q.z q.w)  when given
    /VMC/Ext/Blend/Val (str name, float value)     one per expression
    /VMC/Ext/Blend/Apply

split over as many bundles as keep each datagram within ``max_datagram`` bytes (default
`SAFE_DATAGRAM`, under a 1500-byte Ethernet MTU so no IP fragment can be lost); only
the last carries ``Apply``, so a receiver applies whole frames.

Tracking: ``OK``'s last int is 1 while the channel has a live face, 0 from
``face_lost`` or ``channel_idle`` until ``channel_live``; the eased results the server
sends after ``face_lost`` (PROTOCOL.md §5.2.7) go out with tracking 0. A result's
``head`` (§5.3, the publisher's head pose) goes out as ``Bone/Pos "Head"`` with its
frame; results without one send no bone, so the receiver keeps the last. Weights are
clamped to [0, 1] (VRM expressions are 0..1; the cardinal weights may overshoot) unless
``clamp=False``; the neutral (example 0) is not sent. Names follow the receiver's
convention (`vmc_names`: ``vrm0``, ``vrm1``, ``perfectsync``).
"""

from __future__ import annotations

import asyncio
import logging
import socket
import struct
from collections.abc import AsyncIterable, Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message import OscMessage
from pythonosc.osc_message_builder import OscMessageBuilder

from facecast.protocol import (
    ChannelIdle,
    ChannelLive,
    Error,
    FaceLost,
    Head,
    Ready,
    Result,
    ServerMessage,
)

from .head_pose import Vector, unity_quaternion
from .vmc_names import DEFAULT_CONVENTION, vmc_names

__all__ = [
    "DEFAULT_VMC_PORT",
    "MIN_DATAGRAM",
    "SAFE_DATAGRAM",
    "VmcBridgeStats",
    "VmcFrameEncoder",
    "VmcSender",
    "head_bone_message",
    "head_pose_message",
    "run_vmc_bridge",
    "vmc_frame_datagrams",
    "vmc_head_bundle",
    "vmc_status_bundle",
]

log = logging.getLogger("facecast.bridges.vmc")

DEFAULT_VMC_PORT = 39539
#: Bytes of UDP payload that fit a 1500-byte MTU behind IPv6 (40) + UDP (8) headers,
#: with room to spare: the default bound on one VMC datagram.
SAFE_DATAGRAM = 1400
#: The smallest ``max_datagram`` accepted (IPv4's minimum reassembly size).
MIN_DATAGRAM = 576
_FLOAT32 = struct.Struct(">f")


def _message(address: str, *args: str | int | float) -> OscMessageBuilder:
    builder = OscMessageBuilder(address)
    for arg in args:
        if isinstance(arg, str):
            builder.add_arg(arg, OscMessageBuilder.ARG_TYPE_STRING)
        elif isinstance(arg, int):
            builder.add_arg(arg, OscMessageBuilder.ARG_TYPE_INT)
        else:
            builder.add_arg(float(arg), OscMessageBuilder.ARG_TYPE_FLOAT)
    return builder


def _status_messages(tracking: bool, t: float) -> list[OscMessage]:
    return [
        _message("/VMC/Ext/OK", 1, 3, 0, 1 if tracking else 0).build(),
        _message("/VMC/Ext/T", float(t)).build(),
    ]


#: An empty immediate bundle as python-osc writes it: "#bundle\0" + the time tag 1.
_BUNDLE_HEAD = OscBundleBuilder(IMMEDIATELY).build().dgram
_SIZE = struct.Struct(">i")


def _element(message: OscMessage) -> bytes:
    """A message as one bundle element: its int32 size, then its bytes (OSC 1.0)."""
    return _SIZE.pack(message.size) + message.dgram


def _bundle(elements: Sequence[bytes]) -> bytes:
    return _BUNDLE_HEAD + b"".join(elements)


def _split(elements: Sequence[bytes], max_datagram: int) -> list[bytes]:
    """Bundles of consecutive ``elements``, each at most ``max_datagram`` bytes.

    A single element bigger than the bound (a very long name with a small bound) goes
    alone in its bundle: it cannot be split, and dropping it silently would be worse.
    """
    datagrams: list[bytes] = []
    start, size = 0, len(_BUNDLE_HEAD)
    for i, element in enumerate(elements):
        if i > start and size + len(element) > max_datagram:
            datagrams.append(_bundle(elements[start:i]))
            start, size = i, len(_BUNDLE_HEAD)
        size += len(element)
    datagrams.append(_bundle(elements[start:]))
    return datagrams


def head_bone_message(angles: Vector, position: Vector = (0.0, 0.0, 0.0)) -> OscMessage:
    """``/VMC/Ext/Bone/Pos "Head"`` for head (yaw, pitch, roll) in radians.

    The rotation is `unity_quaternion` of the angles (the one ``--head-pose`` applies
    to the points, in Unity's frame), as the quaternion (x, y, z, w) the spec asks for.
    ``position`` is the bone's local position (metres, Unity frame); receivers that
    apply bone rotations only ignore it.
    """
    return _bone_message(unity_quaternion(angles), position)


def head_pose_message(head: Head) -> OscMessage:
    """``/VMC/Ext/Bone/Pos "Head"`` for a result's head pose (PROTOCOL.md §5.3).

    Its frame is VMC's, so rotation and position go out as they are; no position: 0, 0, 0.
    """
    position = (0.0, 0.0, 0.0) if head.position is None else head.position
    return _bone_message(head.rotation, position)


def _bone_message(quaternion: Vector, position: Vector) -> OscMessage:
    qx, qy, qz, qw = (float(v) for v in quaternion)
    px, py, pz = (float(v) for v in position)
    return _message("/VMC/Ext/Bone/Pos", "Head", px, py, pz, qx, qy, qz, qw).build()


def vmc_head_bundle(angles: Vector, position: Vector = (0.0, 0.0, 0.0)) -> bytes:
    """A datagram with only the head transform, for a tracker bridge beside ``bridge vmc``.

    No ``/VMC/Ext/OK`` nor ``T``: the expression sender owns the tracking state.
    """
    return _bundle([_element(head_bone_message(angles, position))])


def _check_max_datagram(max_datagram: int) -> None:
    if not MIN_DATAGRAM <= max_datagram <= 65507:
        raise ValueError(
            f"max_datagram must be in [{MIN_DATAGRAM}, 65507] bytes (one UDP datagram), "
            f"got {max_datagram}"
        )


class VmcFrameEncoder:
    """The datagrams of frames for a fixed list of names, fast enough for the event loop.

    python-osc encodes every message; its builders also parse back each message and
    bundle they build, ~1 ms for a 52-name frame. So each name's ``Blend/Val`` is encoded
    once, here, with python-osc, and a frame only replaces its last 4 bytes (the float32
    value, big-endian, as OSC writes it) and joins the elements into bundles (OSC 1.0
    framing: "#bundle", time tag, int32 size before each element). The tests check the
    bytes against python-osc's own builders.

    Parameters
    ----------
    names : sequence of N str
        VMC names, in the order of the weights.
    clamp : bool
        Clamp weights to [0, 1].
    max_datagram : int
        Bytes per datagram at most; a frame is split over bundles to fit, ``Apply`` in
        the last one.
    """

    def __init__(
        self, names: Sequence[str], *, clamp: bool = True, max_datagram: int = SAFE_DATAGRAM
    ) -> None:
        _check_max_datagram(max_datagram)
        for name in names:
            if "\x00" in name:
                raise ValueError(f"VMC name {name!r} contains NUL, where an OSC string ends")
            try:
                name.encode("utf-8")
            except UnicodeEncodeError:
                raise ValueError(f"VMC name {name!r} cannot be written as UTF-8") from None
        self.names = tuple(names)
        self.clamp = clamp
        self.max_datagram = max_datagram
        # Each name's element without its value: size, address, ",sf", name.
        self._value_heads = [
            _element(_message("/VMC/Ext/Blend/Val", name, 0.0).build())[:-4] for name in names
        ]
        self._apply = _element(_message("/VMC/Ext/Blend/Apply").build())
        self._ok = {
            tracking: _element(_message("/VMC/Ext/OK", 1, 3, 0, int(tracking)).build())
            for tracking in (False, True)
        }
        self._time_head = _element(_message("/VMC/Ext/T", 0.0).build())[:-4]

    def _status(self, tracking: bool, t: float) -> list[bytes]:
        return [self._ok[bool(tracking)], self._time_head + _FLOAT32.pack(t)]

    def datagrams(
        self,
        weights: np.ndarray,
        t: float,
        *,
        tracking: bool = True,
        head: OscMessage | None = None,
    ) -> list[bytes]:
        """The datagrams of one frame: OK, T, [Bone/Pos Head], one Blend/Val per name, Apply.

        Parameters
        ----------
        weights : (N,) float
        t : float
            Seconds, sent as ``/VMC/Ext/T``.
        tracking : bool
            ``/VMC/Ext/OK``'s tracking status.
        head : OscMessage, optional
            A `head_bone_message` to send with the frame.

        Returns
        -------
        list of bytes, in sending order

        Raises
        ------
        ValueError
            Weights of another shape, NaN/Inf, or beyond float32 (with ``clamp=False``).
        """
        values = np.asarray(weights, dtype=np.float64)
        if values.shape != (len(self.names),):
            raise ValueError(f"weights: expected shape ({len(self.names)},), got {values.shape}")
        if self.clamp:
            values = np.clip(values, 0.0, 1.0)
        with np.errstate(over="ignore"):
            wire = values.astype(">f4")
        if not np.isfinite(wire).all():
            raise ValueError("weights: NaN, Inf or beyond float32")
        raw = wire.tobytes()
        elements = self._status(tracking, t)
        if head is not None:
            elements.append(_element(head))
        elements += [
            value_head + raw[4 * i : 4 * i + 4] for i, value_head in enumerate(self._value_heads)
        ]
        elements.append(self._apply)
        return _split(elements, self.max_datagram)


def vmc_frame_datagrams(
    names: Sequence[str],
    weights: np.ndarray,
    t: float,
    *,
    tracking: bool = True,
    clamp: bool = True,
    head: OscMessage | None = None,
    max_datagram: int = SAFE_DATAGRAM,
) -> list[bytes]:
    """One frame's datagrams (`VmcFrameEncoder.datagrams`); for many frames keep an encoder."""
    encoder = VmcFrameEncoder(names, clamp=clamp, max_datagram=max_datagram)
    return encoder.datagrams(weights, t, tracking=tracking, head=head)


def vmc_status_bundle(tracking: bool, t: float, head: OscMessage | None = None) -> bytes:
    """The datagram saying the tracking state without weights: OK, T, [Bone/Pos Head]."""
    messages = _status_messages(tracking, t)
    if head is not None:
        messages.append(head)
    return _bundle([_element(m) for m in messages])


class VmcSender:
    """A UDP socket that sends VMC datagrams to (host, port); non-blocking sends.

    A send that fails (no receiver yet: ICMP "port unreachable"; a full socket buffer;
    no route) drops that datagram and never raises: the next frame is sent again. Each
    failure is counted (``failed``, ``last_error``) and logged: the first one, then at
    most once every ``log_every`` failures, and once more when sends work again.
    """

    def __init__(
        self, host: str = "127.0.0.1", port: int = DEFAULT_VMC_PORT, *, log_every: int = 1000
    ) -> None:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        family, _, _, _, address = infos[0]
        self.address = address
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._log_every = max(1, log_every)
        self._failing = False
        self.sent = 0
        self.failed = 0
        self.last_error: OSError | None = None

    def send(self, datagram: bytes) -> bool:
        """Send one datagram; False (counted, logged) when it could not be sent."""
        try:
            self._sock.sendto(datagram, self.address)
        except OSError as exc:  # BlockingIOError, ConnectionRefusedError, EMSGSIZE...
            self.failed += 1
            self.last_error = exc
            if not self._failing or self.failed % self._log_every == 0:
                log.warning(
                    "VMC send to %s failed (%s); %d failed so far",
                    self.address, exc, self.failed,
                )  # fmt: skip
            self._failing = True
            return False
        if self._failing:
            log.warning("VMC sends to %s work again (%d failed)", self.address, self.failed)
            self._failing = False
        self.sent += 1
        return True

    def send_all(self, datagrams: Sequence[bytes]) -> bool:
        """Send datagrams in order; True when every one went."""
        ok = True
        for datagram in datagrams:
            ok = self.send(datagram) and ok
        return ok

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> VmcSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class VmcBridgeStats:
    """What `run_vmc_bridge` did: frames and status bundles sent, and failures."""

    frames: int = 0
    status: int = 0
    errors: int = 0
    #: Frames at least one of whose datagrams could not be sent.
    failed_frames: int = 0


async def run_vmc_bridge(
    messages: AsyncIterable[ServerMessage],
    sender: VmcSender,
    *,
    convention: str = DEFAULT_CONVENTION,
    overrides: Mapping[str, str] | None = None,
    clamp: bool = True,
    max_datagram: int = SAFE_DATAGRAM,
    max_frames: int | None = None,
    clock: Callable[[], float] | None = None,
) -> VmcBridgeStats:
    """Turn a watch stream's messages into VMC datagrams.

    Parameters
    ----------
    messages : async iterable of server messages
        ``watch_channel(...)`` (or any stream of ``Ready`` then ``Result`` weights).
        A ``Ready`` fixes the names (again after a reconnection).
    sender : VmcSender
    convention : {"vrm0", "vrm1", "perfectsync"}
        The receiver's naming (`vmc_names`).
    overrides : mapping, optional
        Rig name -> VMC name, over the convention.
    clamp : bool
        Clamp weights to [0, 1].
    max_datagram : int
        Split each frame into bundles of at most this many bytes.
    max_frames : int, optional
        Return after this many frames were sent.
    clock : callable, optional
        Seconds for ``/VMC/Ext/T``; default the event loop's clock.

    Tracking (``/VMC/Ext/OK``) is on from ``ready`` until ``face_lost`` or
    ``channel_idle``, and on again at ``channel_live``; results in between (the
    server's ease to the neutral) are sent with tracking off. A result's ``head``
    goes out as the ``Head`` bone in its frame's first datagram (`head_pose_message`).
    """
    _check_max_datagram(max_datagram)
    vmc_names((), convention)  # an unknown convention fails before the first frame
    clock = clock or asyncio.get_running_loop().time
    stats = VmcBridgeStats()
    encoder: VmcFrameEncoder | None = None
    tracking = True
    async for message in messages:
        if isinstance(message, Ready):
            if message.output != "weights":
                raise ValueError("the VMC bridge needs output=weights")
            names = vmc_names(message.names[1:], convention, overrides)
            encoder = VmcFrameEncoder(names, clamp=clamp, max_datagram=max_datagram)
        elif isinstance(message, Result):
            if encoder is None or message.weights is None:
                continue
            head = None if message.head is None else head_pose_message(message.head)
            datagrams = encoder.datagrams(
                message.weights[1:], clock(), tracking=tracking, head=head
            )
            if not sender.send_all(datagrams):
                stats.failed_frames += 1
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
