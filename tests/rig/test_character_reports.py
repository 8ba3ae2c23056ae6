"""What the pairing report says of VRM expressions that move no morph target."""

from __future__ import annotations

import json
import struct

from facecast.rig.characters.character import character_example_set, load_character

from ..viewer._character import build_character


def _edited(glb: bytes, edit) -> bytes:
    length = struct.unpack_from("<I", glb, 12)[0]
    gltf = json.loads(glb[20 : 20 + length])
    edit(gltf)
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + glb[20 + length :]
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def test_expressions_that_move_no_morph_say_why():
    custom = {
        "Empty": {},
        "Tint": {"materialColorBinds": [{"material": 0, "type": "color", "targetValue": [1, 0, 0, 1]}]},
        "Still": {"morphTargetBinds": [{"node": 0, "index": 0, "weight": 0.0}]},
    }  # fmt: skip
    glb = _edited(
        build_character("vrm1").glb,
        lambda gltf: gltf["extensions"]["VRMC_vrm"]["expressions"].update(custom=custom),
    )
    _, report = character_example_set(load_character(glb, label="face.vrm"))
    reasons = {e.authored: e.reason for e in report.entries}

    assert reasons["Empty"].startswith("binds nothing (no morph target, no material)")
    assert reasons["Tint"] == "binds no morph target (material changes only)"
    assert reasons["Still"] == "its morph binds all have weight 0: it moves nothing"


def test_a_morph_of_its_own_name_moved_by_a_paired_vrm_expression_says_so():
    def rename(gltf):  # the jawOpen morphs (face, teeth) under a name of their own, which
        # VRM aa binds: no ARKit jawOpen left to drive that motion, so aa is paired
        for mesh in gltf["meshes"][:2]:
            mesh["extras"]["targetNames"][0] = "MouthOpenTalk"

    character = load_character(_edited(build_character("vrm1").glb, rename), label="face.vrm")
    entry = next(e for e in character.report.entries if e.authored == "MouthOpenTalk")
    other = next(e for e in character.report.entries if e.authored == "eyeBlinkLeft")

    assert not entry.paired
    assert "aa" in character.report.paired
    assert "moved through the paired VRM expression 'aa'" in entry.reason
    assert "moved through" not in other.reason
