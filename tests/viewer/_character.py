"""A small character made by the tests: face, teeth and eyes as separate skinned meshes.

The face is a textured shield (skin, red lips, dark brows painted in its texture) with
morph targets; the teeth sit behind it and come out in front with their own ``jawOpen``
(morphs on two meshes); the eyes carry a blue-iris colour. A Hips -> Head skeleton skins
all three. The same file with a VRM 0.x ``VRM`` or a VRM 1.0 ``VRMC_vrm`` block. Also the
record the server stores beside it and the example set its rig is fitted from, with
source points a test can stream to pose the face exactly (``source_points[i]``).
"""

from __future__ import annotations

import io
import json
import struct
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from PIL import Image

from facecast.rig.examples import ExampleSet

#: Expressions of the face (and which move the teeth): the rig's example names.
NAMES = ("neutral", "jawOpen", "eyeBlinkLeft", "mouthSmileLeft", "browInnerUp")
SKIN = (226, 160, 122)
LIPS = (200, 30, 60)
BROWS = (60, 35, 25)
TEETH = (250, 250, 250)
IRIS = (40, 90, 230)
GRID = 25  # face vertices per side
HEAD_Y = 1.5  # the Head joint's height (metres): a skeleton whose rest is not at the origin


@dataclass(frozen=True)
class TestCharacter:
    glb: bytes
    record: dict[str, Any]
    examples: ExampleSet


def _face() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    u = np.linspace(0.0, 1.0, GRID)
    uu, vv = np.meshgrid(u, u)
    x = (uu - 0.5) * 0.16
    y = (vv - 0.5) * 0.2
    z = 0.06 - 3.0 * (x**2 + 0.5 * y**2)
    vertices = np.stack([x, y + HEAD_Y, z], axis=-1).reshape(-1, 3)
    uv = np.stack([uu, 1.0 - vv], axis=-1).reshape(-1, 2)
    i = np.arange(GRID - 1)
    a = (i[:, None] * GRID + i[None, :]).ravel()
    faces = np.concatenate(
        [np.stack([a, a + 1, a + GRID + 1], 1), np.stack([a, a + GRID + 1, a + GRID], 1)]
    )
    return vertices, uv, faces


def _face_morphs(vertices: np.ndarray) -> dict[str, np.ndarray]:
    x = vertices[:, 0]
    y = vertices[:, 1] - HEAD_Y
    morphs = {}
    jaw = np.zeros_like(vertices)
    jaw[:, 1] = -0.03 * np.clip((-0.02 - y) / 0.08, 0, 1)
    morphs["jawOpen"] = jaw
    blink = np.zeros_like(vertices)
    near = np.exp(-(((x - 0.04) / 0.02) ** 2 + ((y - 0.03) / 0.015) ** 2))
    blink[:, 1] = -0.01 * near
    morphs["eyeBlinkLeft"] = blink
    smile = np.zeros_like(vertices)
    corner = np.exp(-(((x - 0.035) / 0.02) ** 2 + ((y + 0.05) / 0.02) ** 2))
    smile[:, 0] = 0.01 * corner
    smile[:, 1] = 0.012 * corner
    morphs["mouthSmileLeft"] = smile
    brow = np.zeros_like(vertices)
    brow[:, 1] = 0.012 * np.exp(-((x / 0.03) ** 2 + ((y - 0.06) / 0.02) ** 2))
    morphs["browInnerUp"] = brow
    return morphs


def _box(
    lo: tuple[float, float, float], hi: tuple[float, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    corners = np.array(
        [
            [(hi if k & 1 else lo)[0], (hi if k & 2 else lo)[1], (hi if k & 4 else lo)[2]]
            for k in range(8)
        ]
    )
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    faces = np.array([t for q in quads for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))])
    return corners, faces


def _texture() -> bytes:
    size = 64
    image = np.empty((size, size, 3), np.uint8)
    image[:] = SKIN
    rows = np.arange(size)[:, None]
    cols = np.arange(size)[None, :]
    # v = 1 - image row / size; the face's y runs up with v.
    lips = (rows > 0.72 * size) & (rows < 0.80 * size) & (abs(cols - size / 2) < 0.22 * size)
    image[lips] = LIPS
    brows = (
        (rows > 0.16 * size)
        & (rows < 0.22 * size)
        & (abs(abs(cols - size / 2) - 0.22 * size) < 0.1 * size)
    )
    image[brows] = BROWS
    out = io.BytesIO()
    Image.fromarray(image).save(out, format="PNG")
    return out.getvalue()


class _Writer:
    """Accumulates one binary buffer and its accessors and views."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        view: dict[str, Any] = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.blob.extend(data)
        self.views.append(view)
        return len(self.views) - 1

    def accessor(
        self, array: np.ndarray, kind: str, *, bounds: bool = False, index: bool = False
    ) -> int:
        component = {
            np.dtype(np.float32): 5126,
            np.dtype(np.uint32): 5125,
            np.dtype(np.uint16): 5123,
            np.dtype(np.uint8): 5121,
        }[array.dtype]
        accessor: dict[str, Any] = {
            "bufferView": self.view(
                array.tobytes(), 34963 if index else (None if kind == "MAT4" else 34962)
            ),
            "componentType": component,
            "count": int(array.shape[0]) if kind != "SCALAR" else int(array.size),
            "type": kind,
        }
        if bounds:
            accessor["min"] = array.min(axis=0).tolist()
            accessor["max"] = array.max(axis=0).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def _normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    normals = np.zeros_like(vertices)
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    for k in range(3):
        np.add.at(normals, faces[:, k], n)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def _primitive(
    w: _Writer,
    vertices: np.ndarray,
    faces: np.ndarray,
    material: int,
    *,
    uv: np.ndarray | None = None,
    morphs: list[np.ndarray] = (),
) -> dict[str, Any]:
    attributes = {
        "POSITION": w.accessor(vertices.astype(np.float32), "VEC3", bounds=True),
        "NORMAL": w.accessor(_normals(vertices, faces).astype(np.float32), "VEC3"),
        "JOINTS_0": w.accessor(
            np.tile(np.array([1, 0, 0, 0], np.uint8), (len(vertices), 1)), "VEC4"
        ),
        "WEIGHTS_0": w.accessor(
            np.tile(np.array([1, 0, 0, 0], np.float32), (len(vertices), 1)), "VEC4"
        ),
    }
    if uv is not None:
        attributes["TEXCOORD_0"] = w.accessor(uv.astype(np.float32), "VEC2")
    primitive: dict[str, Any] = {
        "attributes": attributes,
        "indices": w.accessor(faces.astype(np.uint32).ravel(), "SCALAR", index=True),
        "material": material,
    }
    if morphs:
        primitive["targets"] = [
            {"POSITION": w.accessor(m.astype(np.float32), "VEC3", bounds=True)} for m in morphs
        ]
    return primitive


def build_character(
    variant: Literal["gltf", "vrm0", "vrm1"] = "gltf", *, redistribution: bool = True
) -> TestCharacter:
    """The character as a GLB (``variant``: plain glTF, VRM 0.x or VRM 1.0), its record, its examples."""
    w = _Writer()
    face_v, face_uv, face_f = _face()
    face_morphs = _face_morphs(face_v)
    teeth_v, teeth_f = _box((-0.03, HEAD_Y - 0.06, 0.0), (0.03, HEAD_Y - 0.035, 0.012))
    teeth_open = np.zeros_like(teeth_v)
    teeth_open[:, 2] = 0.08  # in front of the face: seen only with the jaw open
    eyes = [
        _box((sx * 0.04 - 0.012, HEAD_Y + 0.02, 0.045), (sx * 0.04 + 0.012, HEAD_Y + 0.035, 0.06))
        for sx in (-1, 1)
    ]
    eyes_v = np.concatenate([eyes[0][0], eyes[1][0]])
    eyes_f = np.concatenate([eyes[0][1], eyes[1][1] + 8])

    examples = _examples(face_v, face_f, face_morphs)
    if variant == "vrm0":
        # VRM 0.x characters face -z (three-vrm turns them about y to face the camera).
        turn = np.array([-1.0, 1.0, -1.0])
        face_v, teeth_v, eyes_v, teeth_open = (
            a * turn for a in (face_v, teeth_v, eyes_v, teeth_open)
        )
        face_morphs = {n: d * turn for n, d in face_morphs.items()}
    else:
        turn = np.ones(3)
    image_view = w.view(_texture())
    face_names = list(face_morphs)
    meshes = [
        {
            "name": "Face",
            "primitives": [
                _primitive(
                    w, face_v, face_f, 0, uv=face_uv, morphs=[face_morphs[n] for n in face_names]
                )
            ],
            "extras": {"targetNames": face_names},
        },
        {
            "name": "Teeth",
            "primitives": [_primitive(w, teeth_v, teeth_f, 1, morphs=[teeth_open])],
            "extras": {"targetNames": ["jawOpen"]},
        },
        {"name": "Eyes", "primitives": [_primitive(w, eyes_v, eyes_f, 2)]},
    ]
    # A humanoid skeleton (VRM's required bones), the head at HEAD_Y: Hips -> ... -> Head.
    bones = [
        ("Hips", None, (0.0, 0.9, 0.0)),
        ("Spine", "Hips", (0.0, 0.1, 0.0)),
        ("Chest", "Spine", (0.0, 0.15, 0.0)),
        ("Neck", "Chest", (0.0, 0.2, 0.0)),
        ("Head", "Neck", (0.0, 0.15, 0.0)),
    ]
    for side, sx in (("Left", 1.0), ("Right", -1.0)):
        bones += [
            (f"{side}UpperArm", "Chest", (sx * 0.15, 0.12, 0.0)),
            (f"{side}LowerArm", f"{side}UpperArm", (sx * 0.25, 0.0, 0.0)),
            (f"{side}Hand", f"{side}LowerArm", (sx * 0.25, 0.0, 0.0)),
            (f"{side}UpperLeg", "Hips", (sx * 0.1, -0.05, 0.0)),
            (f"{side}LowerLeg", f"{side}UpperLeg", (0.0, -0.4, 0.0)),
            (f"{side}Foot", f"{side}LowerLeg", (0.0, -0.4, 0.0)),
        ]
    first = 3  # nodes 0-2 are the meshes
    index = {name: first + i for i, (name, _, _) in enumerate(bones)}
    nodes: list[dict[str, Any]] = [
        {"name": "Face", "mesh": 0, "skin": 0},
        {"name": "Teeth", "mesh": 1, "skin": 0},
        {"name": "Eyes", "mesh": 2, "skin": 0},
    ]
    for name, _, offset in bones:
        nodes.append({"name": name, "translation": (np.array(offset) * turn).tolist()})
    for name, parent, _ in bones:
        if parent is not None:
            nodes[index[parent]].setdefault("children", []).append(index[name])
    inverse_binds = np.stack([np.eye(4, dtype=np.float32)] * 2)
    inverse_binds[0, 1, 3] = -0.9  # Hips
    inverse_binds[1, 1, 3] = -HEAD_Y  # Head
    ibm = w.accessor(
        np.ascontiguousarray(inverse_binds.transpose(0, 2, 1).reshape(2, 16), np.float32), "MAT4"
    )
    humanoid = {name[0].lower() + name[1:]: index[name] for name, _, _ in bones}
    gltf: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "facecast tests"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2, index["Hips"]]}],
        "nodes": nodes,
        "skins": [
            {
                "joints": [index["Hips"], index["Head"]],
                "inverseBindMatrices": ibm,
                "skeleton": index["Hips"],
            }
        ],
        "meshes": meshes,
        "materials": [
            {
                "name": "Skin",
                "pbrMetallicRoughness": {
                    "baseColorTexture": {"index": 0},
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.8,
                },
            },
            {
                "name": "Teeth",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [1, 1, 1, 1],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.5,
                },
                "emissiveFactor": [0.6, 0.6, 0.6],
            },
            {
                "name": "Iris",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [c / 255 for c in IRIS] + [1],
                    "metallicFactor": 0.0,
                },
            },
        ],
        "textures": [{"source": 0, "sampler": 0}],
        "samplers": [{"magFilter": 9728, "minFilter": 9728}],
        "images": [{"bufferView": image_view, "mimeType": "image/png"}],
    }
    # Bindings by expression: (mesh, morph, weight); jawOpen moves the face and the teeth.
    bindings = {n: [[0, face_names.index(n), 1.0]] for n in face_names}
    bindings["jawOpen"].append([1, 0, 1.0])
    meta: dict[str, Any] = {}
    fmt = "gltf"
    if variant == "vrm1":
        fmt = "vrm1"
        gltf["extensionsUsed"] = ["VRMC_vrm", "VRMC_materials_mtoon"]
        # The skin as VRM authors make it: MToon, a toon ramp to a darker shade colour.
        gltf["materials"][0]["extensions"] = {
            "VRMC_materials_mtoon": {
                "specVersion": "1.0",
                "shadeColorFactor": [0.55, 0.35, 0.3],
                "shadingToonyFactor": 0.9,
                "shadingShiftFactor": 0.0,
            }
        }
        gltf["extensions"] = {
            "VRMC_vrm": {
                "specVersion": "1.0",
                "meta": {
                    "name": "Test Face",
                    "version": "1",
                    "authors": ["Facecast Tests"],
                    "licenseUrl": "https://vrm.dev/licenses/1.0/",
                    "avatarPermission": "onlyAuthor",
                    "allowRedistribution": redistribution,
                    "commercialUsage": "personalNonProfit",
                    "modification": "prohibited",
                },
                "humanoid": {
                    "humanBones": {bone: {"node": node} for bone, node in humanoid.items()}
                },
                "expressions": {
                    "preset": {
                        "aa": {
                            "morphTargetBinds": [
                                {"node": 0, "index": 0, "weight": 1.0},
                                {"node": 1, "index": 0, "weight": 1.0},
                            ]
                        },
                        "blinkLeft": {"morphTargetBinds": [{"node": 0, "index": 1, "weight": 1.0}]},
                    }
                },
            }
        }
        meta = {
            "name": "Test Face",
            "authors": ["Facecast Tests"],
            "licence": "VRM Public License 1.0",
            "licence_url": "https://vrm.dev/licenses/1.0/",
            "redistribution": redistribution,
            "commercial": "personalNonProfit",
        }
    elif variant == "vrm0":
        fmt = "vrm0"
        gltf["extensionsUsed"] = ["VRM"]
        gltf["extensions"] = {
            "VRM": {
                "exporterVersion": "facecast-tests",
                "specVersion": "0.0",
                "meta": {
                    "title": "Test Face 0",
                    "version": "1",
                    "author": "Facecast Tests",
                    "allowedUserName": "OnlyAuthor",
                    "violentUssageName": "Disallow",
                    "sexualUssageName": "Disallow",
                    "commercialUssageName": "Disallow",
                    "licenseName": "CC_BY" if redistribution else "Redistribution_Prohibited",
                },
                "humanoid": {
                    "humanBones": [{"bone": bone, "node": node} for bone, node in humanoid.items()]
                },
                "blendShapeMaster": {
                    "blendShapeGroups": [
                        {
                            "name": "A",
                            "presetName": "a",
                            "binds": [
                                {"mesh": 0, "index": 0, "weight": 100},
                                {"mesh": 1, "index": 0, "weight": 100},
                            ],
                        },
                        {
                            "name": "Blink_L",
                            "presetName": "blink_l",
                            "binds": [{"mesh": 0, "index": 1, "weight": 100}],
                        },
                    ]
                },
            }
        }
        meta = {
            "name": "Test Face 0",
            "authors": ["Facecast Tests"],
            "licence": "CC_BY" if redistribution else "Redistribution_Prohibited",
            "licence_url": None,
            "redistribution": redistribution,
            "commercial": "Disallow",
        }
    gltf["buffers"] = [{"byteLength": len(w.blob)}]
    gltf["bufferViews"] = w.views
    gltf["accessors"] = w.accessors
    glb = _pack_glb(gltf, bytes(w.blob))
    record = {"format": fmt, "meta": meta, "bindings": bindings}
    return TestCharacter(glb, record, examples)


def _pack_glb(gltf: dict[str, Any], blob: bytes) -> bytes:
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    chunks = (
        struct.pack("<I4s", len(text), b"JSON")
        + text
        + struct.pack("<I4s", len(blob), b"BIN\0")
        + blob
    )
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def _examples(vertices: np.ndarray, faces: np.ndarray, morphs: dict[str, np.ndarray]) -> ExampleSet:
    """The face's examples with 12 source points per example: sampled from the face itself.

    Points at fixed vertices (lips, brows, eyelids, jaw), so a frame of example i's points
    gives that example's weights exactly (the fit interpolates its examples).
    """
    picks = np.linspace(0, len(vertices) - 1, 12).astype(int)
    targets = np.stack([vertices] + [vertices + morphs[n] for n in NAMES[1:]])
    # Scaled to centimetres, as a tracker's feature points are.
    sources = (targets[:, picks] - vertices[picks].mean(axis=0)) * 100.0
    # A source motion for every example, even where the picked vertices barely move.
    for i in range(1, len(NAMES)):
        sources[i, i % 12, 2] += 0.8
    return ExampleSet(
        names=NAMES,
        source_points=sources,
        target_vertices=targets,
        target_faces=faces,
    )
