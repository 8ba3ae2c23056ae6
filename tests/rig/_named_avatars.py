"""Avatars without ICT-FaceKit: one face mesh whose morph targets are named as each kind of
avatar names them, with the VRM 0.x / 1.0 blocks that kind carries.

A rig's weights depend only on the source side, so which names pair with the generic set
decides them; each morph here is a visible bump of its own (5 mm), except those a kind
exports as all zeros. Built with the standard library and numpy alone; ``avatar(kind)``
is cached for the session.
"""

from __future__ import annotations

import functools
import json
import struct
import zlib

import numpy as np

from facecast.rig.characters.expression_names import ARKIT_NAMES

#: The kinds, as tests.rig._avatars names its ICT-FaceKit variants of the same kind.
KINDS = (
    "arkit", "perfect_sync", "vrm0", "vrm1", "visemes", "fcl", "vrm0_presets", "vroid_sync",
)  # fmt: skip
_FCL = (
    "Fcl_ALL_Neutral", "Fcl_ALL_Joy", "Fcl_ALL_Angry", "Fcl_ALL_Sorrow", "Fcl_ALL_Fun",
    "Fcl_ALL_Surprised", "Fcl_MTH_A", "Fcl_MTH_I", "Fcl_MTH_U", "Fcl_MTH_E", "Fcl_MTH_O",
    "Fcl_EYE_Close", "Fcl_EYE_Close_L", "Fcl_EYE_Close_R", "Fcl_BRW_Fun", "Fcl_MTH_Large",
)  # fmt: skip
#: VRM 0.x presetName -> the morph VRoid binds it to.
_FCL_GROUPS = {
    "joy": "Fcl_ALL_Joy", "angry": "Fcl_ALL_Angry", "sorrow": "Fcl_ALL_Sorrow",
    "fun": "Fcl_ALL_Fun", "surprised": "Fcl_ALL_Surprised", "a": "Fcl_MTH_A", "i": "Fcl_MTH_I",
    "u": "Fcl_MTH_U", "e": "Fcl_MTH_E", "o": "Fcl_MTH_O", "blink": "Fcl_EYE_Close",
    "blink_l": "Fcl_EYE_Close_L", "blink_r": "Fcl_EYE_Close_R",
}  # fmt: skip
_VRM0_PRESETS = (
    "A", "I", "U", "E", "O", "Blink", "Blink_L", "Blink_R", "Joy", "Angry", "Sorrow", "Fun",
    "Surprised", "LookUp", "LookDown", "LookLeft", "LookRight",
)  # fmt: skip
_VISEMES = ("viseme_sil", "viseme_PP", "viseme_aa", "viseme_E", "viseme_I", "viseme_O", "viseme_U")
#: Presets of the vrm0 / vrm1 kinds, binding the ARKit morphs they mix (weight 0-1).
_PRESET_BINDS = {
    "aa": {"jawOpen": 0.6, "mouthLowerDownLeft": 0.3, "mouthLowerDownRight": 0.3},
    "blink": {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0},
    "happy": {"mouthSmileLeft": 0.8, "mouthSmileRight": 0.8, "cheekSquintLeft": 0.5},
    "lookLeft": {"eyeLookOutLeft": 1.0, "eyeLookInRight": 1.0},
}
_VRM0_NAME = {"aa": "a", "blink": "blink", "happy": "joy", "lookLeft": "lookleft"}
#: Perfect Sync shapes the vroid_sync kind exports as all zeros (a real VRoid export did).
STILL = ("JawOpen", "TongueOut")
_GRID = 24


def _morph_names(kind: str) -> list[str]:
    sync = [n[0].upper() + n[1:] for n in ARKIT_NAMES]
    return {
        "arkit": list(ARKIT_NAMES),
        "perfect_sync": sync,
        "vrm0": list(ARKIT_NAMES),
        "vrm1": list(ARKIT_NAMES),
        "visemes": [*ARKIT_NAMES, *_VISEMES],
        "fcl": list(_FCL),
        "vrm0_presets": list(_VRM0_PRESETS),
        "vroid_sync": [*_FCL, *sync],
    }[kind]


def _face() -> tuple[np.ndarray, np.ndarray]:
    """A 16 x 20 cm curved grid at head height, facing +z (metres) and its triangles."""
    u = np.linspace(0.0, 1.0, _GRID)
    uu, vv = np.meshgrid(u, u)
    x, y = (uu - 0.5) * 0.16, (vv - 0.5) * 0.2
    vertices = np.stack([x, y + 1.5, 0.06 - 3.0 * (x**2 + 0.5 * y**2)], axis=-1).reshape(-1, 3)
    i = np.arange(_GRID - 1)
    a = (i[:, None] * _GRID + i[None, :]).ravel()
    faces = np.concatenate(
        [np.stack([a, a + 1, a + _GRID + 1], 1), np.stack([a, a + _GRID + 1, a + _GRID], 1)]
    )
    return vertices.astype(np.float32), faces.astype(np.uint32)


def _bump(vertices: np.ndarray, name: str) -> np.ndarray:
    """A 5 mm bump of its own for ``name`` (its place and direction from the name's CRC)."""
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    centre = vertices[rng.integers(len(vertices))]
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    falloff = np.exp(-np.sum((vertices - centre) ** 2, axis=1) / 0.02**2)
    return (0.005 * falloff[:, None] * direction).astype(np.float32)


def _vrm_block(kind: str, names: list[str]) -> tuple[list[str], dict]:
    """(extensionsUsed, extensions) of ``kind``: its VRM 0.x or 1.0 block, or nothing."""
    index = {n: i for i, n in enumerate(names)}
    if kind == "vrm1":
        preset = {
            p: {"morphTargetBinds": [{"node": 0, "index": index[m], "weight": w} for m, w in b.items()]}
            for p, b in _PRESET_BINDS.items()
        }  # fmt: skip
        meta = {"name": "named test head", "authors": ["facecast tests"],
                "licenseUrl": "https://vrm.dev/licenses/1.0/", "allowRedistribution": True}  # fmt: skip
        return ["VRMC_vrm"], {
            "VRMC_vrm": {"specVersion": "1.0", "meta": meta, "expressions": {"preset": preset}}
        }
    if kind == "vrm0":
        groups = {
            _VRM0_NAME[p]: {m: 100 * w for m, w in b.items()} for p, b in _PRESET_BINDS.items()
        }
    elif kind in ("fcl", "vroid_sync"):
        groups = {preset: {clip: 100.0} for preset, clip in _FCL_GROUPS.items()}
    elif kind == "vrm0_presets":
        groups = {p.lower(): {p: 100.0} for p in _VRM0_PRESETS}
    else:
        return [], {}
    block = [
        {"name": preset, "presetName": preset, "isBinary": False,
         "binds": [{"mesh": 0, "index": index[m], "weight": w} for m, w in binds.items()]}
        for preset, binds in groups.items()
    ]  # fmt: skip
    meta = {"title": "named test head", "author": "facecast tests", "licenseName": "CC_BY"}
    return ["VRM"], {
        "VRM": {"specVersion": "0.0", "meta": meta, "blendShapeMaster": {"blendShapeGroups": block}}
    }


@functools.cache
def avatar(kind: str) -> bytes:
    """The ``kind`` avatar (one of ``KINDS``) as GLB bytes."""
    vertices, faces = _face()
    names = _morph_names(kind)
    deltas = [
        np.zeros_like(vertices) if kind == "vroid_sync" and n in STILL else _bump(vertices, n)
        for n in names
    ]
    chunks: list[bytes] = []
    views: list[dict] = []
    accessors: list[dict] = []

    def accessor(array: np.ndarray, kind_: str, component: int, minmax: bool = False) -> int:
        raw = array.tobytes()
        offset = sum(len(c) for c in chunks)
        chunks.append(raw + b"\0" * (-len(raw) % 4))
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(raw)})
        entry = {"bufferView": len(views) - 1, "componentType": component,
                 "count": len(array), "type": kind_}  # fmt: skip
        if minmax:
            entry |= {"min": array.min(axis=0).tolist(), "max": array.max(axis=0).tolist()}
        accessors.append(entry)
        return len(accessors) - 1

    position = accessor(vertices, "VEC3", 5126, minmax=True)
    indices = accessor(faces.reshape(-1), "SCALAR", 5125)
    targets = [{"POSITION": accessor(d, "VEC3", 5126, minmax=True)} for d in deltas]
    used, extensions = _vrm_block(kind, names)
    blob = b"".join(chunks)
    doc = {
        "asset": {"version": "2.0", "generator": "facecast tests/rig/_named_avatars.py"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"name": "face", "mesh": 0}],
        "meshes": [{
            "name": "face",
            "primitives": [{"attributes": {"POSITION": position}, "indices": indices,
                            "targets": targets}],
            "extras": {"targetNames": names},
        }],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(blob)}],
    }  # fmt: skip
    if used:
        doc |= {"extensionsUsed": used, "extensions": extensions}
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = (
        struct.pack("<I4s", len(text), b"JSON")
        + text
        + struct.pack("<I4s", len(blob), b"BIN\0")
        + blob
    )
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body
