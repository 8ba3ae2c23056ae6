"""GLB export of morph targets and weights, checked by re-reading with pygltflib and trimesh."""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facecast.rig.errors import ExampleSetError, InputError
from facecast.rig.io.gltf import export_glb, read_glb_morph_targets, vertex_normals

NAMES = ["neutral", "smile", "frown"]


def small_rig(seed: int = 0):
    """A 3x3 grid of vertices (8 triangles) with 3 morph targets, the first zero."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(3.0), np.arange(3.0))
    neutral = np.stack([xs.ravel(), ys.ravel(), rng.normal(scale=0.1, size=9)], axis=1)
    faces = []
    for r in range(2):
        for c in range(2):
            a = 3 * r + c
            faces += [[a, a + 1, a + 4], [a, a + 4, a + 3]]
    deltas = rng.normal(scale=0.2, size=(3, 9, 3))
    deltas[0] = 0.0
    return neutral, np.array(faces), deltas


def accessor_array(gltf: pygltflib.GLTF2, index: int, dtype, width: int) -> np.ndarray:
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    blob = gltf.binary_blob()
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    count = acc.count * width
    return np.frombuffer(blob, dtype=dtype, count=count, offset=start).reshape(acc.count, width)


def test_exported_glb_has_a_morph_target_per_example_but_the_zero_neutral():
    neutral, faces, deltas = small_rig()

    gltf = pygltflib.GLTF2.load_from_bytes(export_glb(neutral, faces, deltas, NAMES))

    (mesh,) = gltf.meshes
    (prim,) = mesh.primitives
    assert gltf.asset.version == "2.0"
    assert len(prim.targets) == 2
    assert mesh.extras["targetNames"] == NAMES[1:]
    assert mesh.weights == [0.0, 0.0]
    assert gltf.accessors[prim.indices].componentType == pygltflib.UNSIGNED_INT


def test_exported_position_accessors_have_counts_and_exact_min_max():
    neutral, faces, deltas = small_rig()

    gltf = pygltflib.GLTF2.load_from_bytes(export_glb(neutral, faces, deltas, NAMES))

    prim = gltf.meshes[0].primitives[0]
    position_accessors = [prim.attributes.POSITION] + [t["POSITION"] for t in prim.targets]
    for index in position_accessors:
        acc = gltf.accessors[index]
        values = accessor_array(gltf, index, np.float32, 3)
        assert acc.count == 9 and acc.type == "VEC3"
        assert acc.min == values.min(axis=0).tolist()
        assert acc.max == values.max(axis=0).tolist()


def test_applying_reread_morph_targets_reproduces_each_example():
    neutral, faces, deltas = small_rig()
    gltf = pygltflib.GLTF2.load_from_bytes(export_glb(neutral, faces, deltas, NAMES))
    prim = gltf.meshes[0].primitives[0]
    base = accessor_array(gltf, prim.attributes.POSITION, np.float32, 3)

    for i, target in enumerate(prim.targets, start=1):
        blended = base + accessor_array(gltf, target["POSITION"], np.float32, 3)

        np.testing.assert_allclose(blended, neutral + deltas[i], atol=1e-5)
    indices = accessor_array(gltf, prim.indices, np.uint32, 1).reshape(-1, 3)
    np.testing.assert_array_equal(indices, faces)


def test_exported_normals_are_unit_length_and_face_up_for_a_flat_up_facing_grid():
    neutral, faces, deltas = small_rig()
    neutral[:, 2] = 0.0
    gltf = pygltflib.GLTF2.load_from_bytes(export_glb(neutral, faces, deltas, NAMES))

    normals = accessor_array(gltf, gltf.meshes[0].primitives[0].attributes.NORMAL, np.float32, 3)

    np.testing.assert_allclose(normals, np.tile([0.0, 0.0, 1.0], (9, 1)), atol=1e-6)


def test_morph_target_normals_turn_the_flat_grid_into_the_tilted_examples():
    # A flat grid facing +z whose examples tilt it into planes z = slope * x: each example's
    # normals are (-slope, 0, 1) / |.|, what the base normal plus the target's must give.
    neutral, faces, _ = small_rig()
    neutral[:, 2] = 0.0
    slopes = [0.0, 0.5, -2.0]
    deltas = np.zeros((3, 9, 3))
    for i, slope in enumerate(slopes):
        deltas[i, :, 2] = slope * neutral[:, 0]
    gltf = pygltflib.GLTF2.load_from_bytes(export_glb(neutral, faces, deltas, NAMES))
    prim = gltf.meshes[0].primitives[0]
    base = accessor_array(gltf, prim.attributes.NORMAL, np.float32, 3)

    for slope, target in zip(slopes[1:], prim.targets, strict=True):
        normals = base + accessor_array(gltf, target["NORMAL"], np.float32, 3)

        expected = np.array([-slope, 0.0, 1.0]) / np.hypot(slope, 1.0)
        np.testing.assert_allclose(normals, np.tile(expected, (9, 1)), atol=1e-6)


def test_export_without_normals_writes_no_normal_attribute():
    neutral, faces, deltas = small_rig()

    gltf = pygltflib.GLTF2.load_from_bytes(export_glb(neutral, faces, deltas, NAMES, normals=False))

    prim = gltf.meshes[0].primitives[0]
    assert prim.attributes.NORMAL is None
    assert all("NORMAL" not in target for target in prim.targets)


def test_export_of_only_zero_deltas_writes_a_plain_mesh():
    neutral, faces, deltas = small_rig()

    gltf = pygltflib.GLTF2.load_from_bytes(
        export_glb(neutral, faces, deltas[:1], NAMES[:1], weights=np.ones((2, 1)))
    )

    assert gltf.meshes[0].primitives[0].targets in (None, [])
    assert not gltf.animations


def test_trimesh_loads_exported_glb_with_all_vertices():
    neutral, faces, deltas = small_rig()

    scene = trimesh.load(io.BytesIO(export_glb(neutral, faces, deltas, NAMES)), file_type="glb")

    (geometry,) = scene.geometry.values()
    assert len(geometry.vertices) == 9
    assert len(geometry.faces) == 8


def test_weights_become_a_linear_weights_animation_over_frame_times():
    neutral, faces, deltas = small_rig()
    weights = np.random.default_rng(5).random((4, 3))

    gltf = pygltflib.GLTF2.load_from_bytes(
        export_glb(neutral, faces, deltas, NAMES, weights=weights, fps=30.0)
    )

    (animation,) = gltf.animations
    (sampler,) = animation.samplers
    (channel,) = animation.channels
    times = accessor_array(gltf, sampler.input, np.float32, 1)[:, 0]
    values = accessor_array(gltf, sampler.output, np.float32, 1).reshape(4, 2)
    assert sampler.interpolation == "LINEAR"
    assert channel.target.path == "weights" and channel.target.node == 0
    np.testing.assert_allclose(times, np.arange(4) / 30.0, rtol=1e-6)
    assert gltf.accessors[sampler.input].min == [0.0]
    assert gltf.accessors[sampler.input].max == pytest.approx([3 / 30.0])
    # The neutral's column goes with its target: the animation drives the other two.
    np.testing.assert_allclose(values, weights[:, 1:], rtol=1e-6)


def test_glb_chunks_are_four_byte_aligned_and_length_matches():
    neutral, faces, deltas = small_rig()

    data = export_glb(neutral, faces, deltas, NAMES, weights=np.ones((3, 3)))

    magic, version, length = struct.unpack_from("<III", data)
    json_length, _ = struct.unpack_from("<II", data, 12)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    assert json_length % 4 == 0 and len(data) % 4 == 0


def test_read_glb_morph_targets_round_trips_export():
    neutral, faces, deltas = small_rig()

    got_neutral, got_faces, got_deltas, names = read_glb_morph_targets(
        export_glb(neutral, faces, deltas, NAMES)
    )

    np.testing.assert_allclose(got_neutral, neutral, atol=1e-6)
    np.testing.assert_array_equal(got_faces, faces)
    np.testing.assert_allclose(got_deltas, deltas[1:], atol=1e-6)
    assert names == NAMES[1:]


def test_read_glb_morph_targets_from_a_file_path(tmp_path):
    neutral, faces, deltas = small_rig()
    path = tmp_path / "face.glb"
    path.write_bytes(export_glb(neutral, faces, deltas, NAMES))

    _, _, got_deltas, names = read_glb_morph_targets(path)

    assert got_deltas.shape == (2, 9, 3) and names == NAMES[1:]


def _gltf_json_with_sparse_target(neutral, faces):
    """A .gltf (JSON, data URI) whose one morph target is a sparse accessor moving vertex 4."""
    positions = neutral.astype(np.float32).tobytes()
    indices = faces.astype(np.uint16).tobytes()
    sparse_index = np.array([4], dtype=np.uint16).tobytes() + b"\0\0"
    sparse_value = np.array([[0.0, 0.0, 1.0]], dtype=np.float32).tobytes()
    blob = positions + indices + sparse_index + sparse_value
    off_idx = len(positions)
    off_si = off_idx + len(indices)
    off_sv = off_si + len(sparse_index)
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [
            {
                "byteLength": len(blob),
                "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode(),
            }
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(positions)},
            {"buffer": 0, "byteOffset": off_idx, "byteLength": len(indices)},
            {"buffer": 0, "byteOffset": off_si, "byteLength": 2},
            {"buffer": 0, "byteOffset": off_sv, "byteLength": 12},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 9, "type": "VEC3"},
            {"bufferView": 1, "componentType": 5123, "count": faces.size, "type": "SCALAR"},
            {
                "componentType": 5126,
                "count": 9,
                "type": "VEC3",
                "sparse": {
                    "count": 1,
                    "indices": {"bufferView": 2, "componentType": 5123},
                    "values": {"bufferView": 3},
                },
            },
        ],
        "meshes": [
            {
                "primitives": [
                    {"attributes": {"POSITION": 0}, "indices": 1, "targets": [{"POSITION": 2}]}
                ],
                "extras": {"targetNames": ["puff"]},
            }
        ],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
    }
    return json.dumps(doc)


def test_read_gltf_json_with_uint16_indices_and_sparse_morph_target(tmp_path):
    neutral, faces, _ = small_rig()
    path = tmp_path / "sparse.gltf"
    path.write_text(_gltf_json_with_sparse_target(neutral, faces))

    got_neutral, got_faces, deltas, names = read_glb_morph_targets(path)

    expected = np.zeros((1, 9, 3))
    expected[0, 4] = [0, 0, 1]
    np.testing.assert_allclose(got_neutral, neutral, atol=1e-6)
    np.testing.assert_array_equal(got_faces, faces)
    np.testing.assert_array_equal(deltas, expected)
    assert names == ["puff"]


def test_read_rejects_garbage_bytes_with_a_code():
    with pytest.raises(ExampleSetError) as short:
        read_glb_morph_targets(b"glTF" + b"\x02\x00\x00\x00" + b"\xff" * 40)
    with pytest.raises(ExampleSetError) as garbage:
        read_glb_morph_targets(struct.pack("<4sIII4s", b"glTF", 2, 28, 8, b"JSON") + b"\xff" * 8)

    # The first header declares 4 GiB: the file is cut short, as an upload cut off is.
    assert short.value.code == "truncated_file"
    assert garbage.value.code == "bad_gltf"


def test_read_rejects_a_file_without_morph_targets_naming_it(tmp_path):
    box = trimesh.creation.box()
    path = tmp_path / "box.glb"
    path.write_bytes(trimesh.Scene(box).export(file_type="glb"))

    with pytest.raises(ExampleSetError, match=r"box.glb: no mesh with morph targets"):
        read_glb_morph_targets(path)


def test_read_missing_file_names_it(tmp_path):
    with pytest.raises(ExampleSetError, match=r"nothing.glb: file not found"):
        read_glb_morph_targets(tmp_path / "nothing.glb")


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"names": ["a", "b"]}, "2 names for 3 morph targets"),
        ({"deltas": np.zeros((3, 8, 3))}, "expected deltas of shape (M, 9, 3)"),
        ({"faces": np.array([[0, 1, 9]])}, "face indices must lie in [0, 9)"),
        ({"weights": np.zeros((2, 2))}, "expected weights of shape (F, 3)"),
        ({"weights": np.full((2, 3), np.nan)}, "NaN or Inf in weights"),
        ({"fps": 0.0}, "fps must be positive"),
    ],
)
def test_export_rejects_inconsistent_arguments(change, expected):
    neutral, faces, deltas = small_rig()
    kwargs = {"neutral": neutral, "faces": faces, "deltas": deltas, "names": NAMES} | change
    args = [kwargs.pop(k) for k in ("neutral", "faces", "deltas", "names")]

    with pytest.raises(InputError) as info:
        export_glb(*args, **kwargs)

    assert expected in str(info.value)


VALIDATE_JS = """
const validator = require('gltf-validator');
const data = new Uint8Array(require('fs').readFileSync(process.argv[1]));
validator.validateBytes(data).then((r) => console.log(JSON.stringify(r.issues)));
"""


# The Khronos validator is a devDependency of the viewer (scripts/setup runs npm ci there).
NODE_MODULES = Path(__file__).resolve().parents[2] / "client" / "viewer" / "node_modules"
NODE_ENV = {**os.environ, "NODE_PATH": str(NODE_MODULES)}


def _node_has_gltf_validator() -> bool:
    if shutil.which("node") is None:
        return False
    probe = subprocess.run(
        ["node", "-e", "require('gltf-validator')"], capture_output=True, timeout=30, env=NODE_ENV
    )
    return probe.returncode == 0


@pytest.mark.skipif(
    os.environ.get("CI") != "true" and not _node_has_gltf_validator(),
    reason="node with the npm package gltf-validator (npm ci in client/viewer) not available",
)
def test_exported_glb_passes_khronos_gltf_validator(tmp_path):
    neutral, faces, deltas = small_rig()
    path = tmp_path / "face.glb"
    path.write_bytes(export_glb(neutral, faces, deltas, NAMES, weights=np.ones((3, 3))))

    result = subprocess.run(
        ["node", "-e", VALIDATE_JS, str(path)],
        capture_output=True, text=True, timeout=60, env=NODE_ENV,
    )  # fmt: skip

    issues = json.loads(result.stdout)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]


THREE_JS = """
import { readFileSync } from 'node:fs';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
const data = readFileSync(process.argv[1]);
const buffer = data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength);
new GLTFLoader().parse(buffer, '', (gltf) => {
  let mesh = null;
  gltf.scene.traverse((node) => { if (!mesh && node.isMesh) mesh = node; });
  const g = mesh.geometry;
  console.log(JSON.stringify({
    names: mesh.userData.targetNames,
    influences: mesh.morphTargetInfluences.length,
    normal: Array.from(g.attributes.normal.array),
    morphPositions: (g.morphAttributes.position || []).map((a) => Array.from(a.array)),
    morphNormals: (g.morphAttributes.normal || []).map((a) => Array.from(a.array)),
    tracks: gltf.animations.flatMap((a) => a.tracks.map((t) => t.values.length)),
  }));
}, (err) => { console.error(String(err)); process.exit(1); });
"""
VIEWER = NODE_MODULES.parent


def _node_has_three() -> bool:
    return shutil.which("node") is not None and (NODE_MODULES / "three" / "package.json").is_file()


@pytest.mark.skipif(
    os.environ.get("CI") != "true" and not _node_has_three(),
    reason="node with the npm package three (npm ci in client/viewer) not available",
)
def test_three_js_loads_the_targets_with_their_normals_and_the_animation(tmp_path):
    neutral, faces, deltas = small_rig()
    path = tmp_path / "face.glb"
    path.write_bytes(export_glb(neutral, faces, deltas, NAMES, weights=np.ones((5, 3))))

    result = subprocess.run(
        ["node", "--input-type=module", "-e", THREE_JS, str(path)],
        capture_output=True, text=True, timeout=60, cwd=VIEWER,
    )  # fmt: skip

    assert result.returncode == 0, result.stderr
    loaded = json.loads(result.stdout)
    assert loaded["names"] == NAMES[1:] and loaded["influences"] == 2
    assert loaded["tracks"] == [5 * 2]
    base = np.reshape(loaded["normal"], (9, 3))
    for i, (moved, turned) in enumerate(
        zip(loaded["morphPositions"], loaded["morphNormals"], strict=True), start=1
    ):
        np.testing.assert_allclose(np.reshape(moved, (9, 3)), deltas[i], atol=1e-6)
        # The example's own unit normals, from the base plus the target's offsets.
        posed = base + np.reshape(turned, (9, 3))
        np.testing.assert_allclose(np.linalg.norm(posed, axis=1), 1.0, atol=1e-5)
        np.testing.assert_allclose(posed, vertex_normals(neutral + deltas[i], faces), atol=1e-6)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_reading_a_corrupted_glb_raises_only_example_set_error(data):
    neutral, faces, deltas = small_rig()
    glb = bytearray(export_glb(neutral, faces, deltas, NAMES))
    for _ in range(data.draw(st.integers(1, 8))):
        glb[data.draw(st.integers(0, len(glb) - 1))] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(12, len(glb)))

    try:
        result = read_glb_morph_targets(bytes(glb[:cut]))
    except ExampleSetError:
        return
    assert result[0].shape[1] == 3


ICT = Path(__file__).resolve().parents[3] / "shared" / "data" / "ict-facekit" / "ict_facekit.npz"


@pytest.mark.ict
@pytest.mark.skipif(not ICT.exists(), reason="needs ../shared/data/ict-facekit")
def test_ict_head_with_all_expressions_exports_and_reads_back():
    with np.load(ICT) as ict:
        neutral = ict["neutral"]
        faces = ict["faces"]
        deltas = ict["expressions"] - neutral
        names = [str(n) for n in ict["expression_names"]]

    data = export_glb(neutral, faces, deltas, names, weights=np.eye(len(names)))
    got_neutral, got_faces, got_deltas, got_names = read_glb_morph_targets(data)
    scene = trimesh.load(io.BytesIO(data), file_type="glb")

    assert got_names == names
    np.testing.assert_array_equal(got_faces, faces)
    np.testing.assert_allclose(got_neutral + got_deltas, ict_expressions_f32(neutral, deltas))
    assert len(next(iter(scene.geometry.values())).vertices) == len(neutral)


def ict_expressions_f32(neutral, deltas):
    return neutral.astype(np.float64) + deltas.astype(np.float32).astype(np.float64)


def edit_glb_json(data: bytes, edit) -> bytes:
    """Rewrite the JSON chunk of a GLB through ``edit(doc)``, keeping the binary chunk."""
    json_length = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20 : 20 + json_length])
    edit(doc)
    blob = data[20 + json_length + 8 :]
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    return (
        struct.pack("<III", 0x46546C67, 2, total)
        + struct.pack("<II", len(text), 0x4E4F534A)
        + text
        + struct.pack("<II", len(blob), 0x004E4942)
        + blob
    )


def test_primitives_sharing_positions_share_vertices_and_concatenate_faces():
    neutral, faces, deltas = small_rig()

    def duplicate_primitive(doc):
        doc["meshes"][0]["primitives"].append(dict(doc["meshes"][0]["primitives"][0]))

    data = edit_glb_json(export_glb(neutral, faces, deltas, NAMES), duplicate_primitive)
    got_neutral, got_faces, got_deltas, _ = read_glb_morph_targets(data)

    assert got_neutral.shape == (9, 3) and got_deltas.shape == (2, 9, 3)
    np.testing.assert_array_equal(got_faces, np.concatenate([faces, faces]))


def test_primitives_with_own_positions_are_appended_with_offset_faces():
    neutral, faces, deltas = small_rig()

    def second_primitive_with_copied_accessors(doc):
        prim = doc["meshes"][0]["primitives"][0]
        copy = {"attributes": {}, "indices": prim["indices"], "mode": 4, "targets": []}
        for key, index in prim["attributes"].items():
            doc["accessors"].append(dict(doc["accessors"][index]))
            copy["attributes"][key] = len(doc["accessors"]) - 1
        for target in prim["targets"]:
            doc["accessors"].append(dict(doc["accessors"][target["POSITION"]]))
            copy["targets"].append({"POSITION": len(doc["accessors"]) - 1})
        doc["meshes"][0]["primitives"].append(copy)

    data = edit_glb_json(
        export_glb(neutral, faces, deltas, NAMES), second_primitive_with_copied_accessors
    )
    got_neutral, got_faces, got_deltas, _ = read_glb_morph_targets(data)

    assert got_neutral.shape == (18, 3) and got_deltas.shape == (2, 18, 3)
    np.testing.assert_array_equal(got_faces, np.concatenate([faces, faces + 9]))


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (lambda doc: doc["meshes"][0]["primitives"][0].update(mode=0), "only triangles"),
        (lambda doc: doc["accessors"][0].update(count=7), "not a multiple of 3"),
        (lambda doc: [doc["accessors"][i].update(count=8) for i in range(1, 7)], "out of range"),
        (lambda doc: doc["accessors"][1].update(count=10**6), "runs past its bufferView"),
        (lambda doc: doc["accessors"][2].update(count=8), "NORMAL has a count unlike"),
        (lambda doc: doc["bufferViews"][1].update(byteLength=10), "runs past its bufferView"),
        (
            lambda doc: doc["meshes"][0]["primitives"][0].update(targets=[5, 5, 5]),
            "targets is not a list of objects",
        ),
    ],
    ids=[
        "points-mode",
        "index-count",
        "index-range",
        "huge-count",
        "target-size",
        "short-view",
        "wrong-type",
    ],
)
def test_malformed_glb_structure_is_reported_as_bad_gltf(edit, expected):
    neutral, faces, deltas = small_rig()
    data = edit_glb_json(export_glb(neutral, faces, deltas, NAMES), edit)

    with pytest.raises(ExampleSetError) as info:
        read_glb_morph_targets(data)

    assert expected in str(info.value) and info.value.code == "bad_gltf"
