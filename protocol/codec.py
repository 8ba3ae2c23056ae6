"""Bytes <-> messages: one msgpack map per WebSocket binary message (PROTOCOL.md §2-3).

Decoding treats its input as hostile: size-bounded, and nothing but ProtocolError ever
escapes. No session state here (see connection.py) and no I/O.
"""

from __future__ import annotations

import struct
import threading
from typing import Any, NoReturn

import msgpack

from facecast.protocol.arrays import array_to_wire
from facecast.protocol.errors import ErrorCode, ProtocolError
from facecast.protocol.fastframe import decode_frame
from facecast.protocol.fields import MAX_UINT64
from facecast.protocol.limits import Limits
from facecast.protocol.messages import (
    CLIENT_MESSAGES,
    PROTOCOL_VERSION,
    SERVER_MESSAGES,
    ClientMessage,
    Message,
    ServerMessage,
)

DEFAULT_LIMITS = Limits()

# One Packer per thread: a Packer is not thread-safe (servers encode from worker
# threads), and a reused one keeps its grown buffer, which makes encoding a (V, 3) result
# ~30x faster than msgpack.packb, whose fresh buffer grows step by step on every call.
_local = threading.local()


def encode(message: Message) -> bytes:
    """The wire bytes of ``message``: one msgpack map (§3).

    On the server's per-frame path for `Result`: one dict of a few keys, array bytes
    passed as a memoryview, a single pack call.
    """
    packer = getattr(_local, "packer", None)
    if packer is None:
        packer = _local.packer = msgpack.Packer(use_bin_type=True, autoreset=True)
    # msgpack is untyped; Packer.pack returns bytes.
    data: bytes = packer.pack(message.serialize())
    return data


def encode_result(
    seq: int, ts: float, output: str, values: Any, proc_us: int, dropped: int
) -> bytes:
    """The wire bytes of ``Result(seq=seq, ts=ts, <output>=values, ...)`` (§5.2.2).

    For results the sender built itself (a server's per-frame path): the same bytes as
    `encode` of that `Result`, without constructing and re-checking the dataclass, which
    costs as much as the encoding. ``values`` must already be a valid array for ``output``
    ("weights" (M,), "vertices" (V, 3) or "points" (K, 3), float16/32/64); ints are
    unsigned, as a `Result` requires.

    Laid out here as msgpack lays it out (keys in §5.2.2's order, the smallest int
    format, ``ts`` a float64): the bytes from the array's key to its bin header depend
    only on the output, dtype and shape, so they are built once per layout (a session
    sends one) and the result is one join of nine parts with the array's own bytes, one
    copy (msgpack's Packer copies them twice, and builds the map every time). Ints
    outside uint64, and arrays not little-endian and contiguous, take the Packer.
    """
    layout = _RESULT_LAYOUTS.get((output, values.dtype, values.shape))
    if layout is None:
        layout = _result_layout(output, values)
    if (
        layout is not None
        and values.flags.c_contiguous
        and type(seq) is int
        and type(proc_us) is int
        and type(dropped) is int
        and 0 <= seq <= MAX_UINT64
        and 0 <= proc_us <= MAX_UINT64
        and 0 <= dropped <= MAX_UINT64
    ):
        return b"".join(
            (
                _RESULT_HEAD,
                _uint(seq),
                _TS_KEY,
                _F64.pack(0xCB, ts),
                layout,
                values.data,
                _PROC_US_KEY,
                _uint(proc_us),
                _DROPPED_KEY,
                _uint(dropped),
            )
        )
    return _pack_result(seq, ts, output, values, proc_us, dropped)


def _result_layout(output: str, values: Any) -> bytes | None:
    """The bytes of ``output``'s key, its dtype and shape, up to its bin header; cached.

    None (not cached) for an array whose dtype is not a wire dtype in little-endian
    order: the Packer path converts or refuses it.
    """
    key = (output, values.dtype, values.shape)
    wire = array_to_wire(values)
    if wire["data"].obj is not values or len(_RESULT_LAYOUTS) >= _MAX_LAYOUTS:
        return None  # converted (byte order), or too many layouts to keep
    shape = wire["shape"]
    layout = b"".join(
        (
            _ARRAY_KEYS.get(output) or _key(output) + b"\x83" + _key("dtype"),
            _key(wire["dtype"]),
            _SHAPE_KEY,
            bytes((0x90 | len(shape),)),
            *map(_uint, shape),
            _DATA_KEY,
            _bin_header(values.nbytes),
        )
    )
    _RESULT_LAYOUTS[key] = layout
    return layout


def _pack_result(
    seq: int, ts: float, output: str, values: Any, proc_us: int, dropped: int
) -> bytes:
    """``encode_result`` through msgpack's Packer (ints that the fast layout does not take)."""
    packer = getattr(_local, "packer", None)
    if packer is None:
        packer = _local.packer = msgpack.Packer(use_bin_type=True, autoreset=True)
    data: bytes = packer.pack(
        {
            "v": PROTOCOL_VERSION,
            "type": "result",
            "seq": seq,
            "ts": float(ts),
            output: array_to_wire(values),
            "proc_us": proc_us,
            "dropped": dropped,
        }
    )
    return data


def _key(name: str) -> bytes:
    """A short map key as msgpack writes it (fixstr: at most 31 bytes)."""
    raw = name.encode()
    return bytes((0xA0 | len(raw),)) + raw


def _uint(value: int) -> bytes:
    """A non-negative int (at most uint64) in msgpack's smallest format."""
    if value < 0x80:
        return _FIXINT[value]
    if value <= 0xFF:
        return _UINT8.pack(0xCC, value)
    if value <= 0xFFFF:
        return _UINT16.pack(0xCD, value)
    if value <= 0xFFFFFFFF:
        return _UINT32.pack(0xCE, value)
    return _UINT64.pack(0xCF, value)


def _bin_header(size: int) -> bytes:
    if size <= 0xFF:
        return _UINT8.pack(0xC4, size)
    if size <= 0xFFFF:
        return _UINT16.pack(0xC5, size)
    return _UINT32.pack(0xC6, size)


#: ``encode_result``'s layouts by (output, dtype, shape); shapes come from rigs, so few.
_RESULT_LAYOUTS: dict[tuple[str, Any, tuple[int, ...]], bytes] = {}
_MAX_LAYOUTS = 4096
_FIXINT = tuple(bytes((i,)) for i in range(0x80))
_UINT8 = struct.Struct(">BB")
_UINT16 = struct.Struct(">BH")
_UINT32 = struct.Struct(">BI")
_UINT64 = struct.Struct(">BQ")
_F64 = struct.Struct(">Bd")
# A 7-key map: "v", "type", "seq", "ts", the array, "proc_us", "dropped" (§5.2.2).
_RESULT_HEAD = b"\x87" + _key("v") + _uint(PROTOCOL_VERSION) + _key("type") + _key("result")
_RESULT_HEAD += _key("seq")
_TS_KEY = _key("ts")
_ARRAY_KEYS = {name: _key(name) + b"\x83" + _key("dtype") for name in ("weights", "vertices")}
_SHAPE_KEY = _key("shape")
_DATA_KEY = _key("data")
_PROC_US_KEY = _key("proc_us")
_DROPPED_KEY = _key("dropped")


def _pairs_to_map(pairs: list[tuple[Any, Any]]) -> dict[Any, Any]:
    result = dict(pairs)
    if len(result) != len(pairs):
        # Two readers could otherwise disagree on which duplicate counts.
        raise ProtocolError(ErrorCode.INVALID_MESSAGE, "a map repeats a key")
    return result


#: ``Limits.unpack_kwargs`` results by (limits, max_bytes): building the dict is a tenth of
#: a small frame's decode. Entries keep their Limits alive, so an id is never reused while
#: cached; bounded by clearing (peers use one or two Limits).
_KWARGS_CACHE_SIZE = 16
_kwargs_cache: dict[tuple[int, int], tuple[Limits, dict[str, Any]]] = {}


def _unpack_kwargs(limits: Limits, max_bytes: int) -> dict[str, Any]:
    key = (id(limits), max_bytes)
    cached = _kwargs_cache.get(key)
    if cached is not None and cached[0] is limits:
        return cached[1]
    kwargs = limits.unpack_kwargs(max_bytes)
    if len(_kwargs_cache) >= _KWARGS_CACHE_SIZE:
        _kwargs_cache.clear()
    _kwargs_cache[key] = (limits, kwargs)
    return kwargs


def _unpack(data: Any, max_bytes: int, limits: Limits) -> Any:
    if isinstance(data, str):
        reject_text(data)
    if isinstance(data, memoryview):
        data = data.cast("B") if data.c_contiguous else data.tobytes()
    elif not isinstance(data, bytes | bytearray):
        raise ProtocolError(
            ErrorCode.MALFORMED, f"expected bytes, got {type(data).__name__}", fatal=True
        )
    if len(data) > max_bytes:
        raise ProtocolError(
            ErrorCode.MESSAGE_TOO_LARGE,
            f"message is {len(data)} bytes, more than the limit {max_bytes}",
        )
    try:
        return msgpack.unpackb(
            data, object_pairs_hook=_pairs_to_map, **_unpack_kwargs(limits, max_bytes)
        )
    except ProtocolError:
        raise
    except ValueError as exc:
        # msgpack reports its size bounds as ValueError("... exceeds max_..._len(...)");
        # every other ValueError (incl. ExtraData, FormatError, StackError, bad UTF-8,
        # non-string map keys) means the bytes are not one well-formed msgpack value.
        text = str(exc)
        if "exceeds max_" in text and "max_ext_len" not in text:
            raise ProtocolError(ErrorCode.MESSAGE_TOO_LARGE, text) from None
        reason = text or type(exc).__name__
        raise ProtocolError(ErrorCode.MALFORMED, f"not a msgpack message: {reason}") from None
    except Exception as exc:
        # The decoder promises nothing but ProtocolError to its caller; msgpack can also
        # raise TypeError (unhashable key) or its own UnpackException on hostile input.
        raise ProtocolError(
            ErrorCode.MALFORMED, f"not a msgpack message: {type(exc).__name__}: {exc}"
        ) from None


def _peek_seq(obj: dict[Any, Any]) -> int | None:
    seq = obj.get("seq")
    return seq if type(seq) is int and 0 <= seq < 1 << 64 else None


def _decode(
    data: Any, max_bytes: int, limits: Limits, table: dict[str, type[Message]], other: str
) -> Any:
    obj = _unpack(data, max_bytes, limits)
    if type(obj) is not dict:
        raise ProtocolError(ErrorCode.INVALID_MESSAGE, "a message must be a msgpack map")
    version = obj.get("v")
    if type(version) is not int:
        raise ProtocolError(
            ErrorCode.INVALID_MESSAGE, "a message needs an integer protocol version 'v'"
        )
    if version != PROTOCOL_VERSION:
        raise ProtocolError(
            ErrorCode.UNSUPPORTED_VERSION,
            f"protocol version {version} is not supported; this peer speaks {PROTOCOL_VERSION}",
        )
    kind = obj.get("type")
    if type(kind) is not str:
        raise ProtocolError(ErrorCode.INVALID_MESSAGE, "a message needs a string 'type'")
    cls = table.get(kind)
    if cls is None:
        shown = kind if len(kind) <= 40 else kind[:40] + "…"
        raise ProtocolError(ErrorCode.UNKNOWN_TYPE, f"unknown {other} message type {shown!r}")
    try:
        return cls.parse(obj, limits)
    except ProtocolError as exc:
        raise exc.evolve(seq=_peek_seq(obj)) from None


def decode_client(data: bytes, limits: Limits = DEFAULT_LIMITS) -> ClientMessage:
    """Decode one client->server message (§5.1) from untrusted bytes.

    Raises
    ------
    ProtocolError
        For anything that is not exactly one valid client message within ``limits``;
        ``seq`` is set when the message carried a readable one.
    """
    # Most client messages are frames, most frames are laid out as `encode` writes them.
    frame = decode_frame(data, limits)
    if frame is not None:
        return frame
    # The table holds client message classes only, so the message is a ClientMessage.
    message: ClientMessage = _decode(
        data, limits.max_message_bytes, limits, CLIENT_MESSAGES, "client->server"
    )
    return message


def decode_server(data: bytes, limits: Limits = DEFAULT_LIMITS) -> ServerMessage:
    """Decode one server->client message (§5.2); like `decode_client` otherwise."""
    message: ServerMessage = _decode(
        data, limits.max_server_message_bytes, limits, SERVER_MESSAGES, "server->client"
    )
    return message


def reject_text(text: str | None = None) -> NoReturn:
    """Raise the TEXT_NOT_SUPPORTED error for a WebSocket text message (§2).

    A server calls this when its WebSocket hands it ``str`` instead of ``bytes``.
    """
    raise ProtocolError(
        ErrorCode.TEXT_NOT_SUPPORTED,
        "text WebSocket messages are not supported; send msgpack in binary messages",
    )
