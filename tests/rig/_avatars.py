"""Test avatars of the kind people have, built from ICT-FaceKit with pygltflib.

Face, teeth and eyes as separate skinned meshes on a VRM humanoid skeleton (hips to head,
arms, legs, eye bones the eyeballs hang on, a hair chain), a textured skin (a generated
PNG with painted brows and lips; its UV seam split), a blue-iris eye texture, ARKit-named
morph targets (jawOpen on the face AND the teeth), in metres, and its variants: VRM 1.0
and 0.x blocks (0.x facing -z) with presets binding several morphs on several meshes, a
bone look-at and spring bones on the hair, Perfect Sync capitals, VRoid ``Fcl_`` clips,
the teeth mesh first, a neutral-only file.
``avatar(variant)`` is cached for the session; the ICT archive is read once.
"""

from __future__ import annotations

import functools
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pygltflib

from facecast.rig.characters.generic import VRM_COMPOSITIONS
from facecast.rig.io.gltf import vertex_normals
from facecast.rig.sources.ict import locate_ict
from facecast.rig.sources.source_rig import arkit_from_ict

VARIANTS = (
    "arkit", "teeth_first", "perfect_sync", "vrm0", "vrm1", "fcl", "neutral_only",
    "vrm0_presets", "vroid_sync", "visemes",
)  # fmt: skip
#: The variants that are VRM 0.x files (facing -z).
VRM0_VARIANTS = ("vrm0", "fcl", "vrm0_presets", "vroid_sync")
#: Skin, brow and lip colours painted into the skin texture (RGB), the iris colour.
SKIN, BROW, LIPS, IRIS = (224, 172, 140), (60, 36, 20), (190, 40, 60), (40, 90, 220)
#: ICT's teeth region moves in these shapes only (its README): the teeth's morphs.
TEETH_SHAPES = ("jawForward", "jawLeft", "jawOpen", "jawRight")
#: The VRoid clips the Fcl_ variant carries: the preset ones and two without a twin.
FCL_CLIPS = {
    "Fcl_ALL_Joy": "happy", "Fcl_ALL_Angry": "angry", "Fcl_ALL_Sorrow": "sad",
    "Fcl_ALL_Fun": "relaxed", "Fcl_ALL_Surprised": "surprised",
    "Fcl_MTH_A": "aa", "Fcl_MTH_I": "ih", "Fcl_MTH_U": "ou", "Fcl_MTH_E": "ee", "Fcl_MTH_O": "oh",
    "Fcl_EYE_Close": "blink", "Fcl_EYE_Close_L": "blinkLeft", "Fcl_EYE_Close_R": "blinkRight",
}  # fmt: skip
FCL_UNPAIRED = ("Fcl_BRW_Fun", "Fcl_MTH_Large")
#: The presets-only VRM 0.x variant: a morph per VRM 0.x preset, named as the preset (as
#: UniVRM exports of hand-made avatars often are), look-at by blend shapes included.
VRM0_PRESET_MORPHS = {
    "A": "aa", "I": "ih", "U": "ou", "E": "ee", "O": "oh",
    "Blink": "blink", "Blink_L": "blinkLeft", "Blink_R": "blinkRight",
    "Joy": "happy", "Angry": "angry", "Sorrow": "sad", "Fun": "relaxed", "Surprised": "surprised",
    "LookUp": "lookUp", "LookDown": "lookDown", "LookLeft": "lookLeft", "LookRight": "lookRight",
}  # fmt: skip
#: Perfect Sync shapes the VRoid-style ``vroid_sync`` variant exports as all zeros, as a
#: real VRoid export did (its jawOpen moved nothing: issue 32).
STILL_SHAPES = ("JawOpen", "TongueOut")
#: The Oculus visemes of the ``visemes`` variant (ARKit shapes besides, as Ready Player Me
#: writes them): the vowels as the VRM presets they stand for, silence as all zeros.
VISEMES = {
    "viseme_sil": None, "viseme_aa": "aa", "viseme_E": "ee", "viseme_I": "ih",
    "viseme_O": "oh", "viseme_U": "ou",
}  # fmt: skip

_CM = 0.01
_HEAD_Y = 1.45  # metres: the ICT head's origin placed at a standing character's head height
_FACE = (0, 14062)  # face, head and neck, mouth socket, eye sockets
_TEETH = (14062, 21451)  # gums, tongue, teeth
_EYES = (21451, 24591)  # both eyeballs
#: The skeleton, in a +z-facing frame (+x the character's left), metres: name, parent,
#: position. VRM's humanoid: its required bones (hips, spine, head, arms, legs) and chest,
#: neck and the eyes (at the eyeballs' centres, from the mesh); a hair chain behind the
#: head for the spring bones. VRM 0.x variants turn it to face -z with the meshes.
_BONES = (
    ("Hips", None, (0.0, 0.95, 0.0)),
    ("Spine", "Hips", (0.0, 1.10, 0.0)),
    ("Chest", "Spine", (0.0, 1.25, 0.0)),
    ("Neck", "Chest", (0.0, 1.40, 0.0)),
    ("Head", "Neck", (0.0, 1.50, 0.0)),
    ("LeftEye", "Head", (0.0309, 1.4861, 0.0799)),
    ("RightEye", "Head", (-0.0309, 1.4861, 0.0799)),
    ("HairRoot", "Head", (0.0, 1.52, -0.10)),
    ("Hair1", "HairRoot", (0.0, 1.45, -0.12)),
    ("Hair2", "Hair1", (0.0, 1.38, -0.13)),
    ("LeftUpperArm", "Chest", (0.18, 1.33, 0.0)),
    ("LeftLowerArm", "LeftUpperArm", (0.45, 1.33, 0.0)),
    ("LeftHand", "LeftLowerArm", (0.70, 1.33, 0.0)),
    ("RightUpperArm", "Chest", (-0.18, 1.33, 0.0)),
    ("RightLowerArm", "RightUpperArm", (-0.45, 1.33, 0.0)),
    ("RightHand", "RightLowerArm", (-0.70, 1.33, 0.0)),
    ("LeftUpperLeg", "Hips", (0.10, 0.90, 0.0)),
    ("LeftLowerLeg", "LeftUpperLeg", (0.10, 0.50, 0.0)),
    ("LeftFoot", "LeftLowerLeg", (0.10, 0.08, 0.0)),
    ("RightUpperLeg", "Hips", (-0.10, 0.90, 0.0)),
    ("RightLowerLeg", "RightUpperLeg", (-0.10, 0.50, 0.0)),
    ("RightFoot", "RightLowerLeg", (-0.10, 0.08, 0.0)),
)
#: The bones that skin the meshes (the skin's joints, in this order).
_SKIN_JOINTS = ("Hips", "Spine", "Chest", "Neck", "Head", "LeftEye", "RightEye")
#: The hair chain the spring bones move, root first; the head's sphere collider (offset
#: from the Head bone, radius) keeps it out of the skull.
_HAIR = ("HairRoot", "Hair1", "Hair2")
_HEAD_COLLIDER = ((0.0, -0.03, 0.02), 0.08)
#: Bone nodes are 1.. in _BONES order (node 0 the armature); the mesh nodes follow.
_NODE = {name: 1 + i for i, (name, _, _) in enumerate(_BONES)}
_FIRST_MESH_NODE = 1 + len(_BONES)


def require_ict() -> Path:
    import pytest

    archive = locate_ict()
    if archive is None:
        pytest.skip("needs ../shared/data/ict-facekit (or FACECAST_ICT)")
    return archive


@functools.cache
def ict_parts() -> dict[str, Any]:
    """ICT's neutral and ARKit shapes (metres, on a standing body), its faces, landmarks."""
    with np.load(require_ict(), allow_pickle=False) as ict:
        neutral = ict["neutral"].astype(np.float64)
        names = [str(n) for n in ict["expression_names"]]
        arkit, meshes = arkit_from_ict(names, neutral, ict["expressions"].astype(np.float64))
        faces = ict["faces"].astype(np.int64)
        landmarks = ict["landmarks68"].astype(np.int64)
    place = np.array([0.0, _HEAD_Y, 0.0])
    return {
        "neutral": neutral * _CM + place,
        "shapes": {n: (m - neutral) * _CM for n, m in zip(arkit[1:], meshes[1:], strict=True)},
        "faces": faces,
        "landmarks": landmarks,
    }


def png(pixels: np.ndarray) -> bytes:
    """An RGB PNG of ``pixels`` (H, W, 3) uint8."""
    height, width, _ = pixels.shape
    raw = b"".join(b"\0" + pixels[row].tobytes() for row in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw, 6))
        + chunk(b"IEND", b"")
    )


def _front_uv(vertices: np.ndarray) -> np.ndarray:
    low, high = vertices[:, :2].min(axis=0), vertices[:, :2].max(axis=0)
    uv = (vertices[:, :2] - low) / (high - low)
    uv[:, 1] = 1.0 - uv[:, 1]
    return uv.astype(np.float32)


def _polyline(points: np.ndarray, closed: bool, steps: int = 8) -> np.ndarray:
    """Points along the polyline through ``points`` (P, 2), ``steps`` per segment."""
    ends = np.vstack([points[1:], points[:1]]) if closed else points[1:]
    t = np.linspace(0.0, 1.0, steps, endpoint=False)[None, :, None]
    starts = points[: len(ends)]
    return (starts[:, None] + t * (ends - starts)[:, None]).reshape(-1, 2)


#: Where the skin texture is plain skin: the UV of every triangle the front projection
#: does not fit.
_PLAIN_SKIN_UV = (0.02, 0.02)


def _split_uv_seam(
    vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain skin for the triangles turned away from the front projection (sides, back,
    nape: it would repeat the face's brows there, or stretch them across the triangles
    that straddle the two), with a seam of duplicated vertices between the two kinds, so
    no triangle interpolates a face UV to the plain-skin corner (a smeared streak).

    Returns ``source`` (V',) int: the original vertex each vertex copies (duplicates
    appended after the originals, which keep their index), the re-indexed faces and UVs.
    """
    corners = vertices[faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    facing = normal[:, 2] / np.maximum(np.linalg.norm(normal, axis=1), 1e-12)
    back = facing < 0.3  # steeper than ~73 degrees from the view: the projection stretches
    count = vertices.shape[0]
    shared = np.intersect1d(faces[back], faces[~back])
    remap = np.arange(count)
    remap[shared] = count + np.arange(shared.size)
    faces = faces.copy()
    faces[back] = remap[faces[back]]
    source = np.concatenate([np.arange(count), shared])
    uv = uv[source]
    uv[np.unique(faces[back])] = _PLAIN_SKIN_UV
    return source, faces, uv


def _skin_texture(uv: np.ndarray, landmarks: np.ndarray, size: int = 256) -> bytes:
    """Skin colour with brows (Multi-PIE 17-21, 22-26) and lips (48-59) painted at their
    landmarks' UVs: strokes along each brow and around the lips' outer ring."""
    grid = (np.stack(np.meshgrid(np.arange(size), np.arange(size)), axis=-1) + 0.5) / size
    image = np.empty((size, size, 3), dtype=np.uint8)
    image[:] = SKIN
    strokes = (
        (_polyline(uv[landmarks[17:22]], False), BROW, 0.025),
        (_polyline(uv[landmarks[22:27]], False), BROW, 0.025),
        (_polyline(uv[landmarks[48:60]], True), LIPS, 0.03),
    )
    for points, colour, radius in strokes:
        near = np.min(np.linalg.norm(grid[:, :, None, :] - points[None, None], axis=-1), axis=-1)
        image[near < radius] = colour
    return png(image)


def _eye_texture(size: int = 128) -> bytes:
    grid = (np.stack(np.meshgrid(np.arange(size), np.arange(size)), axis=-1) + 0.5) / size
    radius = np.linalg.norm(grid - 0.5, axis=-1)
    image = np.full((size, size, 3), 245, dtype=np.uint8)
    image[radius < 0.22] = IRIS
    image[radius < 0.08] = (10, 10, 10)
    return png(image)


@functools.cache
def face_mesh() -> dict[str, Any]:
    """The face mesh of every variant (+z-facing): ``vertices`` (V, 3), ``faces``, ``uv``,
    ``normals``, ``ict`` (V,) the ICT vertex each vertex is (the UV seam's duplicates come
    after ICT's own, which keep their order) and the skin ``texture`` (PNG bytes)."""
    parts = ict_parts()
    vertices, faces, ict = _part(parts, _FACE)
    uv = _front_uv(vertices)
    texture = _skin_texture(uv, parts["landmarks"])
    normals = vertex_normals(vertices, faces)
    source, faces, uv = _split_uv_seam(vertices, faces, uv)
    return {
        "vertices": vertices[source], "faces": faces, "uv": uv, "normals": normals[source],
        "ict": ict[source], "texture": texture,
    }  # fmt: skip


def _part(
    parts: dict[str, Any], span: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertex range ``span``: its vertices, its triangles (re-indexed) and their indices."""
    start, stop = span
    faces = parts["faces"]
    inside = ((faces >= start) & (faces < stop)).all(axis=1)
    return parts["neutral"][start:stop], faces[inside] - start, np.arange(start, stop)


class _Writer:
    """Buffer views and accessors appended to one binary blob (4-byte aligned)."""

    def __init__(self, gltf: pygltflib.GLTF2) -> None:
        self.gltf = gltf
        self.parts: list[bytes] = []
        self.size = 0

    def view(self, raw: bytes, target: int | None = None) -> int:
        self.gltf.bufferViews.append(
            pygltflib.BufferView(buffer=0, byteOffset=self.size, byteLength=len(raw), target=target)
        )
        self.parts.append(raw + b"\0" * ((-len(raw)) % 4))
        self.size += len(raw) + (-len(raw)) % 4
        return len(self.gltf.bufferViews) - 1

    def accessor(
        self, array: np.ndarray, kind: str, *, target: int | None = None, minmax=False
    ) -> int:
        array = np.ascontiguousarray(array)
        component = {
            np.dtype(np.float32): pygltflib.FLOAT,
            np.dtype(np.uint32): pygltflib.UNSIGNED_INT,
            np.dtype(np.uint8): pygltflib.UNSIGNED_BYTE,
        }[array.dtype]
        width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[kind]
        rows = array.reshape(-1, width)
        self.gltf.accessors.append(
            pygltflib.Accessor(
                bufferView=self.view(array.tobytes(), target),
                componentType=component,
                count=rows.shape[0],
                type=kind,
                min=rows.min(axis=0).tolist() if minmax else None,
                max=rows.max(axis=0).tolist() if minmax else None,
            )
        )
        return len(self.gltf.accessors) - 1

    def blob(self) -> bytes:
        return b"".join(self.parts)


def _morphs(
    variant: str, parts: dict[str, Any], index: np.ndarray, teeth: bool
) -> dict[str, np.ndarray]:
    """Morph name -> (V, 3) deltas of the part ``index`` for ``variant``."""
    shapes = parts["shapes"]
    if variant == "neutral_only":
        return {}

    def composed(preset: str) -> np.ndarray:
        return sum(w * shapes[s][index] for s, w in VRM_COMPOSITIONS[preset].items())

    if variant == "vrm0_presets":
        made = {name: composed(preset) for name, preset in VRM0_PRESET_MORPHS.items()}
        return {n: d for n, d in made.items() if not teeth or np.abs(d).max() > 1e-6}
    if variant in ("fcl", "vroid_sync"):
        clips = {}
        for clip, preset in FCL_CLIPS.items():
            delta = composed(preset)
            if not teeth or np.abs(delta).max() > 1e-6:
                clips[clip] = delta
        if not teeth:
            clips["Fcl_BRW_Fun"] = (
                0.5 * (shapes["browOuterUpLeft"] + shapes["browOuterUpRight"])[index]
            )
            clips["Fcl_MTH_Large"] = 1.0 * shapes["jawOpen"][index]
        if variant == "vroid_sync":  # Perfect Sync shapes added to VRoid's clips
            names = TEETH_SHAPES if teeth else (*shapes, "tongueOut")
            for name in names:
                sync = name[0].upper() + name[1:]
                still = sync in STILL_SHAPES
                clips[sync] = np.zeros((len(index), 3)) if still else shapes[name][index]
        return clips
    names = TEETH_SHAPES if teeth else tuple(shapes)
    rename = (lambda n: n[0].upper() + n[1:]) if variant == "perfect_sync" else (lambda n: n)
    morphs = {rename(n): shapes[n][index] for n in names}
    if variant == "visemes":
        for viseme, preset in VISEMES.items():
            delta = np.zeros((len(index), 3)) if preset is None else composed(preset)
            if not teeth or np.abs(delta).max() > 1e-6:
                morphs[viseme] = delta
    return morphs


def _mesh(
    writer: _Writer, name: str, vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray,
    morphs: dict[str, np.ndarray], material: int, skin_joints: np.ndarray, skin_weights: np.ndarray,
    normals: np.ndarray,
) -> pygltflib.Mesh:  # fmt: skip
    attributes = pygltflib.Attributes(
        POSITION=writer.accessor(
            vertices.astype(np.float32), "VEC3", target=pygltflib.ARRAY_BUFFER, minmax=True
        ),
        NORMAL=writer.accessor(normals.astype(np.float32), "VEC3", target=pygltflib.ARRAY_BUFFER),
        TEXCOORD_0=None
        if uv is None
        else writer.accessor(uv, "VEC2", target=pygltflib.ARRAY_BUFFER),
        JOINTS_0=writer.accessor(skin_joints, "VEC4", target=pygltflib.ARRAY_BUFFER),
        WEIGHTS_0=writer.accessor(skin_weights, "VEC4", target=pygltflib.ARRAY_BUFFER),
    )
    targets = [
        {
            "POSITION": writer.accessor(
                d.astype(np.float32), "VEC3", target=pygltflib.ARRAY_BUFFER, minmax=True
            )
        }
        for d in morphs.values()
    ]
    primitive = pygltflib.Primitive(
        attributes=attributes,
        indices=writer.accessor(
            faces.astype(np.uint32).reshape(-1), "SCALAR", target=pygltflib.ELEMENT_ARRAY_BUFFER
        ),
        material=material,
        targets=targets or None,
    )
    return pygltflib.Mesh(
        name=name,
        primitives=[primitive],
        weights=[0.0] * len(targets) if targets else None,
        extras={"targetNames": list(morphs)} if targets else {},
    )


def _skin_weights(vertices: np.ndarray, eyes: bool) -> tuple[np.ndarray, np.ndarray]:
    """The head on Head; the neck blends Neck into Head over 10 cm below the jaw; each
    eyeball on its eye bone (the look-at turns them). In the +z-facing frame."""
    joints = np.zeros((vertices.shape[0], 4), dtype=np.uint8)
    weights = np.zeros((vertices.shape[0], 4), dtype=np.float32)
    if eyes:
        joints[:, 0] = np.where(
            vertices[:, 0] > 0, _SKIN_JOINTS.index("LeftEye"), _SKIN_JOINTS.index("RightEye")
        )
        weights[:, 0] = 1.0
        return joints, weights
    joints[:, 0], joints[:, 1] = _SKIN_JOINTS.index("Head"), _SKIN_JOINTS.index("Neck")
    weights[:, 0] = np.clip((vertices[:, 1] - (_HEAD_Y - 0.12)) / 0.10, 0.0, 1.0)
    weights[:, 1] = 1.0 - weights[:, 0]
    joints[weights == 0] = 0  # glTF: a joint with no weight is written as 0
    return joints, weights


def _build(variant: str, *, redistribution: bool) -> bytes:
    parts = ict_parts()
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="facecast tests/rig/_avatars.py"),
        scene=0, scenes=[pygltflib.Scene(nodes=[0])],  # meshes added below
        nodes=[], meshes=[], accessors=[], bufferViews=[], materials=[], textures=[],
        images=[], samplers=[pygltflib.Sampler(magFilter=9729, minFilter=9729)], skins=[],
    )  # fmt: skip
    writer = _Writer(gltf)
    face = face_mesh()
    face_v, face_f, face_i, face_uv = face["vertices"], face["faces"], face["ict"], face["uv"]
    face_normals, skin_png = face["normals"], face["texture"]
    for number, (image, name) in enumerate(((skin_png, "skin"), (_eye_texture(), "eyes"))):
        gltf.images.append(
            pygltflib.Image(name=name, mimeType="image/png", bufferView=writer.view(image))
        )
        gltf.textures.append(pygltflib.Texture(sampler=0, source=number))
        gltf.materials.append(
            pygltflib.Material(
                name=name,
                pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                    baseColorTexture=pygltflib.TextureInfo(index=number),
                    metallicFactor=0.0,
                    roughnessFactor=0.8,
                ),
            )
        )
    gltf.materials.append(
        pygltflib.Material(
            name="teeth",
            pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                baseColorFactor=[0.95, 0.93, 0.85, 1.0], metallicFactor=0.0
            ),
        )
    )
    teeth_v, teeth_f, teeth_i = _part(parts, _TEETH)
    eyes_v, eyes_f, _ = _part(parts, _EYES)
    eyes_uv = np.empty((eyes_v.shape[0], 2), dtype=np.float32)
    for side in (eyes_v[:, 0] > 0, eyes_v[:, 0] <= 0):  # each eyeball its own front projection
        eyes_uv[side] = _front_uv(eyes_v[side])
    meshes = [
        ("face", face_v, face_f, face_uv, _morphs(variant, parts, face_i, False), 0),
        ("teeth", teeth_v, teeth_f, None, _morphs(variant, parts, teeth_i, True), 2),
        ("eyes", eyes_v, eyes_f, eyes_uv, {}, 1),
    ]
    # The face's normals are the unsplit surface's: its UV seam is no crease in the light.
    normals = {
        "face": face_normals,
        "teeth": vertex_normals(teeth_v, teeth_f),
        "eyes": vertex_normals(eyes_v, eyes_f),
    }
    skinning = {name: _skin_weights(v, name == "eyes") for name, v, *_ in meshes}
    if variant == "teeth_first":
        meshes = [meshes[1], meshes[0], meshes[2]]
    # VRM 0.x characters face -z (three-vrm's rotateVRM0 turns them round): meshes,
    # morphs and bones turned half a turn about y.
    turn = np.array([-1.0, 1.0, -1.0]) if variant in VRM0_VARIANTS else np.ones(3)
    meshes = [
        (n, v * turn, f, uv, {k: d * turn for k, d in m.items()}, mat)
        for n, v, f, uv, m, mat in meshes
    ]
    # Nodes: 0 the armature, then its bones (_NODE), then one root node per skinned mesh
    # (the validator wants skinned meshes at the root: parents would not move them anyway).
    position = {name: np.array(at) * turn for name, _, at in _BONES}
    gltf.nodes.append(pygltflib.Node(name="Armature", children=[_NODE["Hips"]]))
    for name, parent, _ in _BONES:
        offset = position[name] - (position[parent] if parent else 0.0)
        children = [_NODE[child] for child, up, _ in _BONES if up == name]
        gltf.nodes.append(
            pygltflib.Node(name=name, translation=offset.tolist(), children=children or None)
        )
    gltf.scenes[0].nodes += list(range(_FIRST_MESH_NODE, _FIRST_MESH_NODE + len(meshes)))
    inverse = np.zeros((len(_SKIN_JOINTS), 4, 4), dtype=np.float32)
    for number, joint in enumerate(_SKIN_JOINTS):
        matrix = np.eye(4, dtype=np.float32)
        matrix[:3, 3] = -position[joint]
        inverse[number] = matrix.T  # glTF matrices are column-major
    gltf.skins.append(
        pygltflib.Skin(
            name="body",
            joints=[_NODE[j] for j in _SKIN_JOINTS],
            skeleton=_NODE["Hips"],
            inverseBindMatrices=writer.accessor(inverse.reshape(-1), "MAT4"),
        )
    )
    for name, vertices, faces, uv, morphs, material in meshes:
        joints, weights = skinning[name]
        gltf.meshes.append(
            _mesh(
                writer, name, vertices, faces, uv, morphs, material, joints, weights,
                normals[name] * turn,
            )
        )  # fmt: skip
        gltf.nodes.append(pygltflib.Node(name=name, mesh=len(gltf.meshes) - 1, skin=0))
    mesh_index = {m[0]: i for i, m in enumerate(meshes)}
    morph_index = {m[0]: {n: j for j, n in enumerate(m[4])} for m in meshes}
    if variant == "vrm1":
        _vrm1(gltf, mesh_index, morph_index, redistribution)
    elif variant in VRM0_VARIANTS:
        clips = {"fcl": FCL_CLIPS, "vroid_sync": FCL_CLIPS, "vrm0_presets": VRM0_PRESET_MORPHS}
        _vrm0(gltf, mesh_index, morph_index, redistribution, clips=clips.get(variant))
    blob = writer.blob()
    gltf.buffers = [pygltflib.Buffer(byteLength=len(blob))]
    gltf.set_binary_blob(blob)
    return b"".join(gltf.save_to_bytes())


#: VRM presets of the VRM variants: which ARKit morphs (weight) on which meshes they bind.
VRM_BINDS = {
    "aa": {("face", "jawOpen"): 0.6, ("teeth", "jawOpen"): 0.6, ("face", "mouthLowerDownLeft"): 0.3, ("face", "mouthLowerDownRight"): 0.3},
    "blink": {("face", "eyeBlinkLeft"): 1.0, ("face", "eyeBlinkRight"): 1.0},
    "happy": {("face", "mouthSmileLeft"): 0.8, ("face", "mouthSmileRight"): 0.8, ("face", "cheekSquintLeft"): 0.5, ("face", "cheekSquintRight"): 0.5},
    "surprised": {("face", "browInnerUp"): 0.8, ("face", "eyeWideLeft"): 0.8, ("face", "eyeWideRight"): 0.8, ("face", "jawOpen"): 0.4, ("teeth", "jawOpen"): 0.4},
}  # fmt: skip
_VRM0_PRESET = {"aa": "a", "blink": "blink", "happy": "joy", "surprised": "surprised"}


def _binds(
    binds: dict[tuple[str, str], float], mesh_index, morph_index
) -> list[tuple[int, int, float]]:
    return [(mesh_index[mesh], morph_index[mesh][morph], w) for (mesh, morph), w in binds.items()]


def _vrm1(gltf, mesh_index, morph_index, redistribution: bool) -> None:
    node_of = {mesh: _FIRST_MESH_NODE + index for mesh, index in mesh_index.items()}
    preset = {
        name: {
            "morphTargetBinds": [
                {"node": node_of[gltf.meshes[m].name], "index": t, "weight": w}
                for m, t, w in _binds(b, mesh_index, morph_index)
            ]
        }
        for name, b in VRM_BINDS.items()
    }
    preset["neutral"] = {}
    custom = {"Wink": {"morphTargetBinds": [{"node": node_of["face"], "index": morph_index["face"]["eyeBlinkLeft"], "weight": 1.0}, {"node": node_of["face"], "index": morph_index["face"]["mouthSmileLeft"], "weight": 0.5}]}}  # fmt: skip
    gltf.extensionsUsed = ["VRMC_vrm", "VRMC_springBone"]
    gltf.extensions = {
        "VRMC_vrm": {
            "specVersion": "1.0",
            "meta": {
                "name": "ICT test head",
                "version": "1",
                "authors": ["facecast tests", "ICT-FaceKit (USC ICT)"],
                "licenseUrl": "https://vrm.dev/licenses/1.0/",
                "avatarPermission": "everyone",
                "commercialUsage": "personalNonProfit",
                "allowRedistribution": redistribution,
                "modification": "prohibited",
                "creditNotation": "required",
            },
            "humanoid": {"humanBones": {bone: {"node": node} for bone, node in _humanoid()}},
            "firstPerson": {
                "meshAnnotations": [
                    {"node": node, "type": "auto"} for node in sorted(node_of.values())
                ]
            },
            # Eye bones turned by up to 10 degrees (the spec's defaults, written out).
            "lookAt": {
                "offsetFromHeadBone": [0.0, -0.014, 0.08],
                "type": "bone",
                **{
                    f"rangeMap{side}": {"inputMaxValue": 90.0, "outputScale": 10.0}
                    for side in ("HorizontalInner", "HorizontalOuter", "VerticalDown", "VerticalUp")
                },
            },
            "expressions": {"preset": preset, "custom": custom},
        },
        "VRMC_springBone": {
            "specVersion": "1.0",
            "colliders": [
                {
                    "node": _NODE["Head"],
                    "shape": {
                        "sphere": {"offset": list(_HEAD_COLLIDER[0]), "radius": _HEAD_COLLIDER[1]}
                    },
                }
            ],
            "colliderGroups": [{"name": "head", "colliders": [0]}],
            "springs": [
                {
                    "name": "hair",
                    "joints": [
                        {
                            "node": _NODE[joint],
                            "hitRadius": 0.02,
                            "stiffness": 1.0,
                            "gravityPower": 0.2,
                            "gravityDir": [0.0, -1.0, 0.0],
                            "dragForce": 0.4,
                        }
                        for joint in _HAIR
                    ],
                    "colliderGroups": [0],
                }
            ],
        },
    }


def _vrm0(gltf, mesh_index, morph_index, redistribution: bool, *, clips=None) -> None:
    """VRM 0.x blocks; ``clips`` (morph name -> VRM 1.0 preset): a group per clip binding
    that morph at 100 on each mesh having it, else ``VRM_BINDS``'s presets."""
    if clips is not None:
        groups = [
            {"name": preset, "presetName": {"aa": "a", "ih": "i", "ou": "u", "ee": "e", "oh": "o", "happy": "joy", "sad": "sorrow", "relaxed": "fun", "blinkLeft": "blink_l", "blinkRight": "blink_r"}.get(preset, preset.lower()),
             "binds": [{"mesh": mesh_index[mesh], "index": morph_index[mesh][clip], "weight": 100} for mesh in ("face", "teeth") if clip in morph_index[mesh]], "isBinary": False}
            for clip, preset in clips.items()
        ]  # fmt: skip
    else:
        groups = [
            {"name": name, "presetName": _VRM0_PRESET[name], "binds": [{"mesh": m, "index": t, "weight": 100 * w} for m, t, w in _binds(b, mesh_index, morph_index)], "isBinary": False}
            for name, b in VRM_BINDS.items()
        ]  # fmt: skip
    groups.append({"name": "Neutral", "presetName": "neutral", "binds": [], "isBinary": False})
    gltf.extensionsUsed = ["VRM"]
    gltf.extensions = {
        "VRM": {
            "exporterVersion": "facecast tests",
            "specVersion": "0.0",
            "meta": {
                "title": "ICT test head",
                "version": "1",
                "author": "facecast tests",
                "allowedUserName": "Everyone",
                "commercialUssageName": "Disallow",
                "licenseName": "CC_BY" if redistribution else "Redistribution_Prohibited",
            },
            "humanoid": {
                "humanBones": [
                    {"bone": bone, "node": node, "useDefaultValues": True}
                    for bone, node in _humanoid()
                ],
                "armStretch": 0.05,
                "legStretch": 0.05,
                "upperArmTwist": 0.5,
                "lowerArmTwist": 0.5,
                "upperLegTwist": 0.5,
                "lowerLegTwist": 0.5,
                "feetSpacing": 0.0,
                "hasTranslationDoF": False,
            },
            "firstPerson": {
                "firstPersonBone": _NODE["Head"],
                # 0.x writes the offset in Unity's frame (z mirrored): eyes 8 cm in front.
                "firstPersonBoneOffset": {"x": 0.0, "y": -0.014, "z": 0.08},
                "meshAnnotations": [
                    {"mesh": mesh, "firstPersonFlag": "Auto"}
                    for mesh in sorted(mesh_index.values())
                ],
                "lookAtTypeName": "Bone",
                **{
                    f"lookAt{side}": {"curve": [0, 0, 0, 1, 1, 1, 1, 0], "xRange": 90, "yRange": 10}
                    for side in ("HorizontalInner", "HorizontalOuter", "VerticalDown", "VerticalUp")
                },
            },
            "blendShapeMaster": {"blendShapeGroups": groups},
            "secondaryAnimation": {
                "boneGroups": [
                    {
                        "comment": "hair",
                        "stiffiness": 1.0,
                        "gravityPower": 0.2,
                        "gravityDir": {"x": 0.0, "y": -1.0, "z": 0.0},
                        "dragForce": 0.4,
                        "center": -1,
                        "hitRadius": 0.02,
                        "bones": [_NODE[_HAIR[0]]],
                        "colliderGroups": [0],
                    }
                ],
                "colliderGroups": [
                    {
                        "node": _NODE["Head"],
                        "colliders": [
                            {
                                "offset": dict(zip("xyz", _HEAD_COLLIDER[0], strict=True)),
                                "radius": _HEAD_COLLIDER[1],
                            }
                        ],
                    }
                ],
            },
            "materialProperties": [],
        }
    }


def _humanoid() -> list[tuple[str, int]]:
    """VRM humanoid bone names (leftUpperArm, ...) and their nodes: every bone but hair."""
    return [(name[0].lower() + name[1:], _NODE[name]) for name, _, _ in _BONES if name not in _HAIR]


@functools.cache
def avatar(variant: str, *, redistribution: bool = True) -> bytes:
    """The test avatar ``variant`` (one of ``VARIANTS``) as GLB bytes, built once a session."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown avatar variant {variant!r}")
    return _build(variant, redistribution=redistribution)
