"""Raw wire maps and packing of hostile input, for the protocol tests.

A module of its own (not conftest) so tests import it by a name no other test folder uses.
"""

from __future__ import annotations

import copy
from typing import Any

import msgpack
from _protocol_samples import SAMPLES


def _materialise(value: Any) -> Any:
    # serialize() hands array bytes over as memoryviews; tests edit plain bytes.
    if isinstance(value, memoryview):
        return value.tobytes()
    if isinstance(value, dict):
        return {k: _materialise(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_materialise(v) for v in value]
    return value


def raw(name: str) -> dict[str, Any]:
    """A fresh, editable wire map of the sample message ``name``."""
    return copy.deepcopy(_materialise(SAMPLES[name].serialize()))


def pack(obj: Any) -> bytes:
    """msgpack bytes of ``obj`` exactly as given, valid or not."""
    return msgpack.packb(obj, use_bin_type=True)
