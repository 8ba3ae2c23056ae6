"""Live Link Face in: parse the app's UDP packets, turn weights into points, publish them.

``parse_livelink_packet`` is sans-I/O (bytes in, a frame or a coded error out); the
receiver is a thin asyncio datagram endpoint and the bridge loop feeds a
`FramePublisher`. It must not compute cloning weights: the server does.

Packet layout ``livelinkface`` (Unreal's Apple ARKit Live Link remote publisher, as
the Live Link Face app sends it, packet version 6), all multi-byte numbers big-endian,
no padding::

    offset  size  field
    0       1     uint8    packet version, 6
    1       4     int32    N1, length in bytes of the device id
    5       N1    UTF-8    device id (the app sends a 36-character UUID)
    5+N1    4     int32    N2, length in bytes of the subject name
    9+N1    N2    UTF-8    subject name (e.g. "iPhone")
    then the frame time (FQualifiedFrameTime), 16 bytes:
            4     int32    frame number
            4     float32  sub-frame, a fraction of a frame in [0, 1)
            4     int32    frame-rate numerator (e.g. 60)
            4     int32    frame-rate denominator (e.g. 1)
    then    1     uint8    value count, 61
            244   float32  x 61 values: the 52 ARKit weights in Live Link order
                           (``ARKIT_NAMES``: eyeBlinkLeft ... tongueOut), then head yaw,
                           pitch, roll and left/right eye yaw, pitch, roll

A packet of 1 + 4 + 36 + 4 + 6 + 16 + 1 + 244 = 312 bytes for a UUID and "iPhone".
A packet that ends right after the subject name carries no face (some senders use it
when tracking is lost): it parses to a frame whose ``weights`` are None.

Layout ``pylivelinkface`` (the PyLiveLinkFace library's encoder, JimWest): the same
but for its start and the name's length::

    0       4     uint32 little-endian packet version, 6  (06 00 00 00)
    4       N1    UTF-8    "$" + device id, with no length before it
    4+N1    4     int32    N2, big-endian, the subject name's length in *characters*
    8+N1    ...   UTF-8    subject name, then frame time, count and values as above

Its bytes for a 36-character UUID and an ASCII name are exactly an app packet's (the
app's length 36 is the byte 0x24, "$"), and are read as one (device id without the
"$"). Other ids have no length to read: the parser tries the app's layout first and, when that does not
fit a packet starting ``06 00 00 00 24``, finds where the id ends from the packet's
total length (the subject name and the 261 bytes after it must fill it exactly).
`LiveLinkFrame.layout` says which layout was read.

Units: the weights are 0..1. The app sends head and eye angles in radians; the
PyLiveLinkFace encoder documents them as -1..1 and clamps them there. facecast reads
both as radians (`facecast.rig.sources.source_rig.head_rotation`), so such a sender's 1 is a
57° turn.

Anything else — another version, a truncated packet, a string length out of
[0, 256], invalid UTF-8, a count other than 61, NaN/Inf values, bytes after the
values — raises `LiveLinkPacketError` with a stable ``code``; when neither layout
fits, its message says what each layout found.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from facecast.client.channel import FramePublisher
from facecast.rig.sources.source_rig import NUM_ARKIT, SourceRig

from .tracker import (
    BridgeStats,
    DatagramReceiver,
    HeadSink,
    TrackerPacketError,
    open_receiver,
    run_tracker_bridge,
)

__all__ = [
    "DEFAULT_PORT",
    "LIVELINK_VALUE_COUNT",
    "LIVELINK_VERSION",
    "MAX_PACKET_BYTES",
    "BridgeStats",
    "LiveLinkFrame",
    "LiveLinkPacketError",
    "LiveLinkReceiver",
    "open_livelink_receiver",
    "parse_livelink_packet",
    "run_livelink_bridge",
]

LIVELINK_VERSION = 6
LIVELINK_VALUE_COUNT = 61
DEFAULT_PORT = 11111
MAX_STRING_BYTES = 256
#: Bytes after the subject name in a packet with a face: frame time, count, values.
_FACE_BYTES = 16 + 1 + 4 * LIVELINK_VALUE_COUNT
#: The largest valid packet (two 256-byte strings, PyLiveLinkFace's 4-byte version);
#: anything longer is refused unread.
MAX_PACKET_BYTES = 4 + 4 + MAX_STRING_BYTES + 4 + MAX_STRING_BYTES + _FACE_BYTES
#: How a PyLiveLinkFace packet starts: version 6 as a little-endian uint32, then "$".
_PYLIVELINKFACE_START = struct.pack("<I", LIVELINK_VERSION) + b"$"

_INT32 = struct.Struct(">i")
_FRAME_TIME = struct.Struct(">ifii")
_VALUES = struct.Struct(f">B{LIVELINK_VALUE_COUNT}f")


class LiveLinkPacketError(TrackerPacketError):
    """A UDP packet that is not a valid Live Link Face packet; ``code`` says why.

    Codes: ``too_large``, ``truncated``, ``unsupported_version``, ``bad_string``,
    ``bad_value_count``, ``non_finite``, ``trailing_bytes``. When neither known layout
    fits, the code is the app layout's and the message adds PyLiveLinkFace's reason.
    """

    code: str = "bad_livelink_packet"


@dataclass(frozen=True, eq=False)
class LiveLinkFrame:
    """One decoded Live Link Face packet.

    Attributes
    ----------
    version : int
    layout : str
        "livelinkface" (the app's) or "pylivelinkface" (module docstring).
    device_id, subject : str
    frame_number : int
    sub_frame : float
    rate_numerator, rate_denominator : int
    weights : (52,) float64 or None
        ARKit weights in ``ARKIT_NAMES`` order; None for a packet without a face.
    head : (9,) float64 or None
        Head yaw/pitch/roll, left eye and right eye yaw/pitch/roll, radians (what a
        PyLiveLinkFace sender means by its -1..1 is read as radians too).
    received : float
        ``time.monotonic()`` when the receiver got it (0 from the parser alone).
    """

    version: int
    device_id: str
    subject: str
    layout: str = "livelinkface"
    frame_number: int = 0
    sub_frame: float = 0.0
    rate_numerator: int = 0
    rate_denominator: int = 0
    weights: np.ndarray | None = None
    head: np.ndarray | None = None
    received: float = 0.0

    @property
    def has_face(self) -> bool:
        return self.weights is not None

    @property
    def time(self) -> float | None:
        """The frame time in seconds, or None without a valid frame rate."""
        if self.rate_numerator <= 0 or self.rate_denominator <= 0:
            return None
        return (self.frame_number + self.sub_frame) * self.rate_denominator / self.rate_numerator


def _string(data: bytes, offset: int, what: str) -> tuple[str, int]:
    """A string with its int32 byte length before it, and the offset after it."""
    if len(data) < offset + 4:
        raise LiveLinkPacketError("truncated", f"packet ends before the {what} length")
    (length,) = _INT32.unpack_from(data, offset)
    if not 0 <= length <= MAX_STRING_BYTES:
        raise LiveLinkPacketError(
            "bad_string", f"{what} length {length} is outside [0, {MAX_STRING_BYTES}] bytes"
        )
    start = offset + 4
    if len(data) < start + length:
        raise LiveLinkPacketError(
            "truncated", f"packet ends inside the {what} ({length} bytes announced)"
        )
    return _utf8(data[start : start + length], what), start + length


def _utf8(raw: bytes, what: str) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise LiveLinkPacketError(
            "bad_string", f"{what} is not valid UTF-8 (byte {exc.start} of {len(raw)})"
        ) from None


def _face(data: bytes, offset: int, head: dict[str, Any]) -> LiveLinkFrame:
    """The frame from ``offset`` (just after the subject name) to the packet's end."""
    if offset == len(data):
        return LiveLinkFrame(**head)
    if len(data) < offset + _FRAME_TIME.size + 1:
        raise LiveLinkPacketError("truncated", "packet ends inside the frame time")
    frame_number, sub_frame, numerator, denominator = _FRAME_TIME.unpack_from(data, offset)
    offset += _FRAME_TIME.size
    count = data[offset]
    if count != LIVELINK_VALUE_COUNT:
        raise LiveLinkPacketError(
            "bad_value_count",
            f"{count} values announced; Live Link Face sends {LIVELINK_VALUE_COUNT}",
        )
    if len(data) < offset + _VALUES.size:
        raise LiveLinkPacketError(
            "truncated", f"packet ends inside the {LIVELINK_VALUE_COUNT} values"
        )
    if len(data) > offset + _VALUES.size:
        raise LiveLinkPacketError(
            "trailing_bytes", f"{len(data) - offset - _VALUES.size} bytes after the values"
        )
    values = np.frombuffer(data, dtype=">f4", count=LIVELINK_VALUE_COUNT, offset=offset + 1)
    values = values.astype(np.float64)
    if not (np.isfinite(values).all() and math.isfinite(sub_frame)):
        raise LiveLinkPacketError("non_finite", "NaN or Inf among the values")
    return LiveLinkFrame(
        **head,
        frame_number=frame_number,
        sub_frame=sub_frame,
        rate_numerator=numerator,
        rate_denominator=denominator,
        weights=values[:NUM_ARKIT],
        head=values[NUM_ARKIT:],
    )


def _parse_app(data: bytes) -> LiveLinkFrame:
    device_id, offset = _string(data, 1, "device id")
    subject, offset = _string(data, offset, "subject name")
    head = {"version": data[0], "device_id": device_id, "subject": subject}
    return _face(data, offset, head)


def _parse_pylivelinkface(data: bytes) -> LiveLinkFrame:
    """PyLiveLinkFace's layout: no length before the id, so its end is found by fit.

    An id end ``e`` fits when the int32 at ``e`` announces the subject name that,
    with nothing or a whole face after it, ends the packet exactly; the name may be
    counted in bytes or (as PyLiveLinkFace does) in characters.
    """
    last_end = min(len(_PYLIVELINKFACE_START) - 1 + MAX_STRING_BYTES, len(data) - 4)
    for end in range(len(_PYLIVELINKFACE_START), last_end + 1):
        (announced,) = _INT32.unpack_from(data, end)
        start = end + 4
        for name_bytes in (len(data) - start - _FACE_BYTES, len(data) - start):
            if not 0 <= name_bytes <= MAX_STRING_BYTES or announced > name_bytes:
                continue
            try:
                subject = data[start : start + name_bytes].decode("utf-8")
                device_id = data[4:end].decode("utf-8")
            except UnicodeDecodeError:
                continue
            if announced not in (name_bytes, len(subject)):
                continue
            head = {
                "version": LIVELINK_VERSION,
                "device_id": device_id,
                "subject": subject,
                "layout": "pylivelinkface",
            }
            return _face(data, start + name_bytes, head)
    raise LiveLinkPacketError(
        "bad_string",
        "no end of the device id leaves a subject name (its int32 length in bytes or "
        "characters) and nothing or a whole face filling the packet",
    )


def parse_livelink_packet(data: bytes) -> LiveLinkFrame:
    """Decode one Live Link Face UDP packet, in either known layout (module docstring).

    Raises
    ------
    LiveLinkPacketError
    """
    data = bytes(data)
    if len(data) > MAX_PACKET_BYTES:
        raise LiveLinkPacketError(
            "too_large", f"{len(data)} bytes; a Live Link Face packet is at most {MAX_PACKET_BYTES}"
        )
    if not data:
        raise LiveLinkPacketError("truncated", "empty packet")
    version = data[0]
    if version != LIVELINK_VERSION:
        raise LiveLinkPacketError(
            "unsupported_version", f"packet version {version}; only {LIVELINK_VERSION} is known"
        )
    try:
        return _parse_app(data)
    except LiveLinkPacketError as app_error:
        if not data.startswith(_PYLIVELINKFACE_START):
            raise
        try:
            return _parse_pylivelinkface(data)
        except LiveLinkPacketError as variant_error:
            if variant_error.code != "bad_string":
                raise  # the layout fitted; what follows the name is what is wrong
            raise LiveLinkPacketError(
                app_error.code,
                f"{app_error} (as the Live Link Face app's layout); as PyLiveLinkFace's "
                f"(version 06 00 00 00, '$' + device id without a length): {variant_error}",
            ) from None


class LiveLinkReceiver(DatagramReceiver[LiveLinkFrame]):
    """Receives Live Link Face packets; keeps the newest ``max_queue`` frames.

    `DatagramReceiver` with `parse_livelink_packet`. Build with `open_livelink_receiver`.
    """

    def __init__(self, max_queue: int = 4) -> None:
        super().__init__(parse_livelink_packet, max_queue, what="Live Link")


async def open_livelink_receiver(
    host: str = "127.0.0.1", port: int = DEFAULT_PORT, *, max_queue: int = 4
) -> LiveLinkReceiver:
    """Bind a UDP socket on (host, port) and receive Live Link Face packets on it."""
    receiver = LiveLinkReceiver(max_queue)
    await open_receiver(receiver, host, port)
    return receiver


async def run_livelink_bridge(
    receiver: LiveLinkReceiver,
    source_rig: SourceRig,
    publisher: FramePublisher,
    *,
    head_pose: bool = False,
    subject: str | None = None,
    on_head: HeadSink | None = None,
    max_frames: int | None = None,
) -> BridgeStats:
    """Receive frames, turn them into points, publish them; until cancelled or ``max_frames``.

    `run_tracker_bridge` for Live Link frames; ``subject``: only frames of this Live
    Link subject (default every subject). ``on_head`` gets each published frame's head
    yaw, pitch, roll (radians), e.g. to send them on as VMC.
    """
    accept = None if subject is None else (lambda frame: frame.subject == subject)
    return await run_tracker_bridge(
        receiver,
        source_rig,
        publisher,
        head_pose=head_pose,
        accept=accept,
        on_head=on_head,
        max_frames=max_frames,
    )
