"""What the pairing report says of VRM expressions that move no morph target."""

from __future__ import annotations

import json
import struct

from facecast.rig.characters.character import character_example_set, load_character

from ..viewer._character import build_character


def _with_custom_expressions(glb: bytes, custom: dict) -> bytes:
    length = struct.unpack_from("<I", glb, 12)[0]
    gltf = json.loads(glb[20 : 20 + length])
    gltf["extensions"]["VRMC_vrm"]["expressions"]["custom"] = custom
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + glb[20 + length :]
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def test_expressions_that_move_no_morph_say_why():
    glb = _with_custom_expressions(
        build_character("vrm1").glb,
        {
            "Empty": {},
            "Tint": {"materialColorBinds": [{"material": 0, "type": "color", "targetValue": [1, 0, 0, 1]}]},
            "Still": {"morphTargetBinds": [{"node": 0, "index": 0, "weight": 0.0}]},
        },
    )  # fmt: skip
    _, report = character_example_set(load_character(glb, label="face.vrm"))
    reasons = {e.authored: e.reason for e in report.entries}

    assert reasons["Empty"].startswith("binds nothing (no morph target, no material)")
    assert reasons["Tint"] == "binds no morph target (material changes only)"
    assert reasons["Still"] == "its morph binds all have weight 0: it moves nothing"
