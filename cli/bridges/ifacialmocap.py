"""iFacialMocap / Facemotion3D in: parse the apps' UDP text, then publish like Live Link.

``parse_ifacialmocap_packet`` is sans-I/O (bytes in, a frame or a coded error out); the
receiver and the publishing loop are `tracker`'s. It must not compute cloning weights.

Both iPhone apps stream one UTF-8 text datagram per frame to port 49983 of the
computer (their developer pages), fields separated by ``|``::

    mouthSmile_R-0|eyeBlink_L-7|...|jawOpen-12|=head#-21.5,-6.0,-6.6,-0.03,-0.10,-0.66|rightEye#6.0,2.4,0.3|leftEye#6.0,-1.7,-0.2|

- a blend shape per field, ``name-value`` (iFacialMocap: ARKit names with ``_L`` /
  ``_R`` for Left / Right) or ``name&value`` (Facemotion3D: ARKit names as ARKit
  spells them, plus its own ``FM_...`` extras, ignored); the value an integer 0-100,
  read as weight value / 100;
- ``=head#`` Euler angles X, Y, Z in **degrees** then position X, Y, Z; ``rightEye#``
  and ``leftEye#`` Euler angles X, Y, Z in degrees. The head's X, Y, Z angles become
  facecast's pitch, yaw, roll in radians (``head``: yaw, pitch, roll as Live Link's).

ARKit shapes a packet does not name weigh 0 (``missing`` counts them). The apps start
streaming when sent a request string from the computer (`request_stream`): iFacialMocap
on the phone's port 49983, Facemotion3D on 49993; both answer to the sender's 49983.

A datagram that is not such text — over `MAX_PACKET_BYTES`, not UTF-8, no ARKit shape,
a field with no separator, a value not an integer in [0, 100], a name twice, a head or eye field
without its numbers, a non-finite number — raises `FacialMocapPacketError` with a
stable ``code``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from facecast.rig.sources.source_rig import ARKIT_NAMES, NUM_ARKIT

from .tracker import DatagramReceiver, TrackerPacketError, open_receiver

__all__ = [
    "APPS",
    "DEFAULT_PORT",
    "MAX_PACKET_BYTES",
    "FacialMocapFrame",
    "FacialMocapPacketError",
    "FacialMocapReceiver",
    "open_ifacialmocap_receiver",
    "parse_ifacialmocap_packet",
    "request_stream",
]

#: The computer's port both apps stream to.
DEFAULT_PORT = 49983
#: A frame is ~1.2 kB (52 shapes + head + eyes); the apps' own examples read 8192.
MAX_PACKET_BYTES = 8192
#: App -> (the phone's port for the request, the request string), from their pages.
APPS: dict[str, tuple[int, bytes]] = {
    "ifacialmocap": (49983, b"iFacialMocap_sahuasouryya9218sauhuiayeta91555dy3719"),
    "facemotion3d": (49993, b"FACEMOTION3D_OtherStreaming"),
}

_ARKIT_INDEX = {name.lower(): i for i, name in enumerate(ARKIT_NAMES)}
_SIDE = re.compile(r"_([lr])$", re.IGNORECASE)
_INTEGER = re.compile(r"[0-9]{1,3}")
#: The pose fields and how many numbers each carries.
_POSE_FIELDS = {"head": 6, "righteye": 3, "lefteye": 3}


class FacialMocapPacketError(TrackerPacketError):
    """A datagram that is not iFacialMocap / Facemotion3D text; ``code`` says why.

    Codes: ``too_large``, ``bad_text``, ``bad_field``, ``bad_value``,
    ``duplicate_name``, ``bad_pose``, ``non_finite``.
    """

    code: str = "bad_ifacialmocap_packet"


@dataclass(frozen=True, eq=False)
class FacialMocapFrame:
    """One decoded iFacialMocap / Facemotion3D frame.

    Attributes
    ----------
    app : str
        "ifacialmocap" (``name-value``) or "facemotion3d" (``name&value``).
    weights : (52,) float64
        ARKit weights in ``ARKIT_NAMES`` order, value / 100.
    head : (3,) float64 or None
        Head yaw, pitch, roll in radians (the packet's Y, X, Z degrees); None when the
        packet has no ``head#`` field.
    head_position : (3,) float64 or None
        The packet's head position X, Y, Z as sent.
    right_eye, left_eye : (3,) float64 or None
        Eye Euler angles X, Y, Z in radians.
    missing : int
        ARKit shapes the packet did not name (their weight is 0).
    ignored : tuple of str
        Names that are no ARKit shape (Facemotion3D's ``FM_...``), skipped.
    received : float
        ``time.monotonic()`` when the receiver got it (0 from the parser alone).
    """

    app: str
    weights: np.ndarray
    head: np.ndarray | None = None
    head_position: np.ndarray | None = None
    right_eye: np.ndarray | None = None
    left_eye: np.ndarray | None = None
    missing: int = 0
    ignored: tuple[str, ...] = ()
    received: float = 0.0


def _arkit_index(name: str) -> int | None:
    """``eyeBlink_L`` / ``eyeBlinkLeft`` / any case -> its ARKit index; None if no shape."""
    key = _SIDE.sub(lambda m: "left" if m.group(1).lower() == "l" else "right", name).lower()
    return _ARKIT_INDEX.get(key)


def _numbers(field: str, name: str, text: str) -> np.ndarray:
    count = _POSE_FIELDS[name]
    parts = text.split(",")
    if len(parts) != count:
        raise FacialMocapPacketError(
            "bad_pose", f"{field!r}: {name} carries {count} numbers, got {len(parts)}"
        )
    try:
        values = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise FacialMocapPacketError("bad_pose", f"{field!r}: not numbers") from None
    if not np.isfinite(values).all():
        raise FacialMocapPacketError("non_finite", f"{field!r}: NaN or Inf")
    return values


def parse_ifacialmocap_packet(data: bytes) -> FacialMocapFrame:
    """Decode one iFacialMocap / Facemotion3D UDP datagram (format in the module docstring).

    Raises
    ------
    FacialMocapPacketError
    """
    if len(data) > MAX_PACKET_BYTES:
        raise FacialMocapPacketError(
            "too_large", f"{len(data)} bytes; a frame is at most {MAX_PACKET_BYTES}"
        )
    try:
        text = bytes(data).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FacialMocapPacketError("bad_text", f"not UTF-8 (byte {exc.start})") from None
    weights = np.zeros(NUM_ARKIT, dtype=np.float64)
    seen = np.zeros(NUM_ARKIT, dtype=bool)
    pose: dict[str, np.ndarray] = {}
    ignored: list[str] = []
    app: str | None = None
    for field in text.strip().split("|"):
        if not field:
            continue  # the trailing "|"
        if "#" in field:
            name, _, numbers = field.lstrip("=").partition("#")
            key = name.lower()
            if key not in _POSE_FIELDS:
                raise FacialMocapPacketError("bad_field", f"{field!r}: unknown pose field")
            if key in pose:
                raise FacialMocapPacketError("duplicate_name", f"{name!r} twice")
            pose[key] = _numbers(field, key, numbers)
            continue
        separator = "&" if "&" in field else "-"
        name, sep, value = field.rpartition(separator)
        if not sep or not name:
            raise FacialMocapPacketError(
                "bad_field", f"{field!r}: expected name-value (or name&value)"
            )
        if app is None:
            app = "facemotion3d" if separator == "&" else "ifacialmocap"
        if not _INTEGER.fullmatch(value) or int(value) > 100:
            raise FacialMocapPacketError(
                "bad_value", f"{field!r}: the value must be an integer in [0, 100]"
            )
        index = _arkit_index(name)
        if index is None:
            ignored.append(name)
            continue
        if seen[index]:
            raise FacialMocapPacketError(
                "duplicate_name", f"{name!r}: shape {ARKIT_NAMES[index]} named twice"
            )
        seen[index] = True
        weights[index] = int(value) / 100.0
    if not seen.any():
        raise FacialMocapPacketError("bad_field", "no ARKit blend shape in the packet")
    head = pose.get("head")
    return FacialMocapFrame(
        app=app or "ifacialmocap",
        weights=weights,
        # degrees X (pitch), Y (yaw), Z (roll) -> radians (yaw, pitch, roll)
        head=None if head is None else np.radians(head[[1, 0, 2]]),
        head_position=None if head is None else head[3:],
        right_eye=None if "righteye" not in pose else np.radians(pose["righteye"]),
        left_eye=None if "lefteye" not in pose else np.radians(pose["lefteye"]),
        missing=int(NUM_ARKIT - seen.sum()),
        ignored=tuple(ignored),
    )


class FacialMocapReceiver(DatagramReceiver[FacialMocapFrame]):
    """Receives iFacialMocap / Facemotion3D datagrams; keeps the newest ``max_queue``.

    `DatagramReceiver` with `parse_ifacialmocap_packet`. Build with
    `open_ifacialmocap_receiver`.
    """

    def __init__(self, max_queue: int = 4) -> None:
        super().__init__(parse_ifacialmocap_packet, max_queue, what="iFacialMocap")


async def open_ifacialmocap_receiver(
    host: str = "0.0.0.0", port: int = DEFAULT_PORT, *, max_queue: int = 4
) -> FacialMocapReceiver:
    """Bind a UDP socket on (host, port) and receive the apps' frames on it."""
    receiver = FacialMocapReceiver(max_queue)
    await open_receiver(receiver, host, port)
    return receiver


def request_stream(
    receiver: DatagramReceiver[Any], phone: str, app: str = "ifacialmocap", port: int | None = None
) -> None:
    """Ask the app on ``phone`` to stream to this receiver's port (sent from its socket).

    ``port`` defaults to the app's (`APPS`). Raises ``ValueError`` for an unknown app.
    """
    if app not in APPS:
        raise ValueError(f"unknown app {app!r}; expected one of {', '.join(APPS)}")
    app_port, request = APPS[app]
    receiver.send(request, (phone, app_port if port is None else port))
