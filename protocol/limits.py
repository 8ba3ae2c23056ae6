"""Size limits a decoder enforces on untrusted bytes (PROTOCOL.md §7).

Only the numbers and how they map onto msgpack's own unpacker bounds; no decoding here.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any


@dataclass(frozen=True)
class Limits:
    """Upper bounds on everything a peer can make the decoder allocate.

    Every bound is inclusive: a value equal to the limit is accepted, one more is refused
    with ``MESSAGE_TOO_LARGE``.

    Attributes
    ----------
    max_message_bytes : int
        Largest client->server message (bytes), checked by `decode_client`.
    max_server_message_bytes : int
        Largest server->client message (bytes), checked by `decode_server`; large enough
        for a ``result`` carrying ``max_vertices`` float64 vertices.
    max_points : int
        Largest K (feature points per frame).
    max_vertices : int
        Largest V in a ``result``'s vertices and in ``ready``.
    max_string : int
        Longest string, in characters (rig ids, names, messages, session ids).
    max_names : int
        Most entries in any array (blendshape names, so also the largest M).
    max_keys : int
        Most keys in any map.
    """

    max_message_bytes: int = 1 << 20
    max_server_message_bytes: int = 64 << 20
    max_points: int = 4096
    max_vertices: int = 2_000_000
    max_string: int = 256
    max_names: int = 4096
    max_keys: int = 64

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            if type(value) is not int or value < 1:
                raise ValueError(f"Limits.{field.name} must be a positive int, got {value!r}")

    def unpack_kwargs(self, max_bytes: int) -> dict[str, Any]:
        """Keyword arguments for `msgpack.unpackb`, bounding each container and string.

        (``max_buffer_size`` is an `Unpacker` option; for one-shot ``unpackb`` the codec
        checks ``len(data) <= max_bytes`` itself before unpacking.)

        msgpack counts string lengths in UTF-8 bytes; 4 bytes per character is the UTF-8
        maximum, and the exact character count is checked after decoding.
        """
        return {
            "raw": False,
            "strict_map_key": True,
            "use_list": True,
            "max_bin_len": max_bytes,
            "max_str_len": 4 * self.max_string,
            # Shapes need 2 entries even when a caller sets max_names lower.
            "max_array_len": max(self.max_names, 2),
            "max_map_len": self.max_keys,
            "max_ext_len": 0,
        }
