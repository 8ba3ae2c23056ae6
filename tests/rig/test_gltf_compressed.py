"""Compressed glTF read as its uncompressed twin: the ICT test avatar as meshopt, quantised
(KHR_mesh_quantization) and Draco files made at test time (tests/rig/_compressed.py), read by
``load_character`` and ``read_glb_morph_targets``; a file that does not decode, or declares
more than the reader's bounds, is a named error before anything is decoded."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from facecast.rig.characters.character import load_character
from facecast.rig.errors import ExampleSetError
from facecast.rig.io.gltf import pack_glb, read_glb_morph_targets
from facecast.rig.io.gltf_read import MAX_DECODED_BYTES

from . import _avatars
from ._compressed import GLTFPACK_MISSING, KINDS, compressed, gltfpack, split_glb


@functools.cache
def twin_and(kind: str) -> tuple[bytes, bytes]:
    twin = _avatars.avatar("arkit")
    return twin, compressed(twin, kind)


def edited(data: bytes, edit) -> bytes:
    doc, blob = split_glb(data)
    blob = bytearray(blob)
    edit(doc, blob)
    return pack_glb(doc, bytes(blob))


def canonical(faces: np.ndarray) -> np.ndarray:
    """Each triangle rotated to start at its smallest index (meshopt's index codec rotates
    triangles, keeping their winding), rows sorted."""
    turn = np.argmin(faces, axis=1)
    rows = np.stack([np.roll(f, -t) for f, t in zip(faces, turn, strict=True)])
    return rows[np.lexsort(rows.T[::-1])]


@pytest.mark.parametrize("kind", KINDS)
def test_a_compressed_character_reads_as_its_uncompressed_twin(kind):
    _avatars.require_ict()
    twin_bytes, data = twin_and(kind)
    assert len(data) < len(twin_bytes)

    twin = load_character(twin_bytes, label="twin.glb")
    character = load_character(data, label=f"{kind}.glb")

    assert character.glb == data  # kept as uploaded: what is served stays compressed
    assert character.report.paired == twin.report.paired
    assert list(character.expressions) == list(twin.expressions)
    vertices, jaw = character.face_vertices, character.expressions["jawOpen"].face_displacement
    twin_jaw = twin.expressions["jawOpen"].face_displacement
    if kind == "quantized":
        # Read in the file's quantised mesh space: integers, one scale and offset away.
        assert np.array_equal(vertices, np.round(vertices))
        scale = np.ptp(twin.face_vertices, axis=0).max() / np.ptp(vertices, axis=0).max()
        offset = (twin.face_vertices - scale * vertices).mean(axis=0)
        vertices, jaw = scale * vertices + offset, scale * jaw
        assert scale == pytest.approx(0.35 / 65000, rel=0.1)
    tolerance = {"meshopt": 1e-9, "quantized": 1e-5, "draco": 1e-5}[kind]  # metres
    np.testing.assert_allclose(vertices, twin.face_vertices, atol=tolerance)
    assert np.abs(twin_jaw).max() > 0.005  # jawOpen moves the chin by millimetres
    np.testing.assert_allclose(jaw, twin_jaw, atol=max(tolerance, 2e-6))
    if kind == "meshopt":
        assert np.array_equal(canonical(character.face_faces), canonical(twin.face_faces))
    else:
        assert np.array_equal(character.face_faces, twin.face_faces)


@pytest.mark.parametrize("kind", KINDS)
def test_the_morph_target_reader_decodes_compressed_files_too(kind):
    _avatars.require_ict()
    twin_bytes, data = twin_and(kind)

    neutral, faces, deltas, names = read_glb_morph_targets(data)
    twin_neutral, _, twin_deltas, twin_names = read_glb_morph_targets(twin_bytes)

    assert names == twin_names and deltas.shape == twin_deltas.shape
    assert neutral.shape == twin_neutral.shape and faces.max() < len(neutral)
    if kind == "quantized":  # the quantised integers, spread over int16's range
        assert np.array_equal(neutral, np.round(neutral)) and np.ptp(neutral) > 60000
    else:
        np.testing.assert_allclose(neutral, twin_neutral, atol=1e-5)
        np.testing.assert_allclose(deltas, twin_deltas, atol=2e-6)


def _face_position_view(doc) -> dict:
    return doc["bufferViews"][doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]["bufferView"]]  # fmt: skip


def _draco_of_face(doc) -> dict:
    return doc["meshes"][0]["primitives"][0]["extensions"]["KHR_draco_mesh_compression"]


def _meshopt_cut(doc, blob) -> None:
    _face_position_view(doc)["extensions"]["EXT_meshopt_compression"]["byteLength"] = 40


def _meshopt_scrambled(doc, blob) -> None:
    ext = _face_position_view(doc)["extensions"]["EXT_meshopt_compression"]
    start = ext["byteOffset"]
    blob[start : start + ext["byteLength"]] = b"\xff" * ext["byteLength"]


def _meshopt_bad_filter(doc, blob) -> None:
    _face_position_view(doc)["extensions"]["EXT_meshopt_compression"]["filter"] = "ZIP"


def _meshopt_miscounted(doc, blob) -> None:
    _face_position_view(doc)["extensions"]["EXT_meshopt_compression"]["count"] -= 1


def _meshopt_octahedral_positions(doc, blob) -> None:
    _face_position_view(doc)["extensions"]["EXT_meshopt_compression"]["filter"] = "OCTAHEDRAL"


def _draco_scrambled(doc, blob) -> None:
    view = doc["bufferViews"][_draco_of_face(doc)["bufferView"]]
    start = view["byteOffset"] + 16
    blob[start : start + 64] = bytes(range(64))


def _draco_miscounted(doc, blob) -> None:
    # Every attribute one vertex short (a count unlike POSITION's is refused before Draco).
    prim = doc["meshes"][0]["primitives"][0]
    for index in {*prim["attributes"].values(), *(t["POSITION"] for t in prim["targets"])}:
        doc["accessors"][index]["count"] -= 1


def _draco_missing_attribute(doc, blob) -> None:
    _draco_of_face(doc)["attributes"]["POSITION"] = 77


@pytest.mark.parametrize(
    ("kind", "edit", "words"),
    [
        ("meshopt", _meshopt_cut, "does not decode"),
        ("meshopt", _meshopt_scrambled, "does not decode"),
        ("meshopt", _meshopt_bad_filter, "'ZIP'"),
        ("meshopt", _meshopt_miscounted, "its bufferView holds"),
        ("meshopt", _meshopt_octahedral_positions, "filtered OCTAHEDRAL has byteStride 12"),
        ("draco", _draco_scrambled, "does not decode"),
        ("draco", _draco_miscounted, "its accessor declares 15344"),
        ("draco", _draco_missing_attribute, "no attribute 77"),
    ],
    ids=lambda v: getattr(v, "__name__", v),
)
def test_compressed_data_that_does_not_decode_is_bad_compression(kind, edit, words):
    _avatars.require_ict()
    data = edited(twin_and(kind)[1], edit)

    with pytest.raises(ExampleSetError) as info:
        load_character(data, label="avatar.glb")

    assert info.value.code == "bad_compression", info.value
    assert words in str(info.value) and "avatar.glb" in str(info.value)


def test_a_broken_compressed_mesh_other_than_the_face_is_refused_too():
    # The teeth are not the face mesh the fit reads: still decoded, so a viewer never gets
    # a file the server could not read.
    _avatars.require_ict()

    def teeth(doc, blob):
        position = doc["meshes"][1]["primitives"][0]["attributes"]["POSITION"]
        view = doc["bufferViews"][doc["accessors"][position]["bufferView"]]
        view["extensions"]["EXT_meshopt_compression"]["byteLength"] = 40

    with pytest.raises(ExampleSetError) as info:
        load_character(edited(twin_and("meshopt")[1], teeth), label="avatar.glb")

    assert info.value.code == "bad_compression"


def test_a_meshopt_view_declaring_more_than_the_bound_is_refused_before_decoding():
    _avatars.require_ict()
    count = MAX_DECODED_BYTES // 12 + 1  # one row past the bound

    def huge(doc, blob):  # consistent: the view (and its fallback buffer) as the count says
        view = _face_position_view(doc)
        view["extensions"]["EXT_meshopt_compression"]["count"] = count
        view["byteLength"] = count * 12
        doc["buffers"][view["buffer"]]["byteLength"] = view.get("byteOffset", 0) + count * 12

    with pytest.raises(ExampleSetError) as info:
        load_character(edited(twin_and("meshopt")[1], huge), label="avatar.glb")

    assert info.value.code == "too_large"
    assert f"{count} x 12 bytes" in str(info.value)


def test_a_draco_primitive_declaring_more_than_the_bound_is_refused_before_decoding():
    _avatars.require_ict()

    def huge(doc, blob):
        prim = doc["meshes"][2]["primitives"][0]  # the eyes: no morph target to mismatch
        doc["accessors"][prim["attributes"]["POSITION"]]["count"] = 33_333_334  # 10^8 values

    with pytest.raises(ExampleSetError) as info:
        load_character(edited(twin_and("draco")[1], huge), label="avatar.glb")

    # Refused by the document check (gltf_check), before Draco decodes anything.
    assert info.value.code == "gltf_exceeds_limits"
    assert "max_gltf_accessor_values" in str(info.value)


def test_a_meshopt_gltf_folder_is_packed_with_its_fallback_buffer_and_reads_as_the_glb(tmp_path):
    # gltfpack's .gltf output: the compressed bytes in a .bin, a fallback buffer without
    # one; packing moves the compressed bytes and keeps the fallback a buffer of its own.
    _avatars.require_ict()
    twin_bytes, data = twin_and("meshopt")
    doc, blob = split_glb(data)
    doc["buffers"][0]["uri"] = "avatar.bin"
    (tmp_path / "avatar.bin").write_bytes(blob)
    # A buffer before it, so that packing has offsets to move.
    doc["buffers"].insert(0, {"uri": "pad.bin", "byteLength": 100})
    (tmp_path / "pad.bin").write_bytes(b"\xee" * 100)
    for view in doc["bufferViews"]:
        view["buffer"] += 1
        if "extensions" in view:
            view["extensions"]["EXT_meshopt_compression"]["buffer"] += 1
    (tmp_path / "avatar.gltf").write_text(json.dumps(doc))

    character = load_character(tmp_path / "avatar.gltf", label="avatar.gltf")
    packed, _ = split_glb(character.glb)
    again = load_character(character.glb, label="packed.glb")

    assert packed["buffers"][1] == doc["buffers"][2]  # the fallback, after the BIN chunk
    twin = load_character(twin_bytes, label="twin.glb")
    for read in (character, again):
        np.testing.assert_allclose(read.face_vertices, twin.face_vertices, atol=1e-9)
        assert read.report.paired == twin.report.paired


def test_a_plain_view_in_a_fallback_buffer_is_bad_gltf_not_the_binary_chunk_read():
    _avatars.require_ict()

    def plain(doc, blob):
        del _face_position_view(doc)["extensions"]  # now a plain view in buffer 1

    with pytest.raises(ExampleSetError) as info:
        load_character(edited(twin_and("meshopt")[1], plain), label="avatar.glb")

    assert info.value.code == "bad_gltf" and "lies in a meshopt fallback buffer" in str(info.value)


@pytest.mark.skipif(GLTFPACK_MISSING is not None, reason=str(GLTFPACK_MISSING))
def test_a_file_packed_by_gltfpack_reads_with_its_twins_expressions_at_its_own_scale():
    # The real tool: vertices reordered for the GPU, meshopt filters over 14-bit quantised
    # positions, the dequantisation in the node transforms.
    _avatars.require_ict()
    twin_bytes = _avatars.avatar("arkit")
    data = gltfpack(twin_bytes)
    doc, _ = split_glb(data)
    assert {"EXT_meshopt_compression", "KHR_mesh_quantization"} <= set(doc["extensionsRequired"])

    twin = load_character(twin_bytes, label="twin.glb")
    character = load_character(data, label="packed.glb")

    assert character.glb == data
    assert character.report.paired == twin.report.paired
    assert character.face_vertices.shape == twin.face_vertices.shape
    assert character.face_faces.shape == twin.face_faces.shape
    # One scale from the twin's metres to the file's integers, for the mesh and its morphs.
    scale = np.ptp(character.face_vertices, axis=0).max() / np.ptp(twin.face_vertices, axis=0).max()
    for name in ("jawOpen", "eyeBlinkLeft", "mouthSmileLeft"):
        ours = np.abs(character.expressions[name].face_displacement).max()
        theirs = np.abs(twin.expressions[name].face_displacement).max()
        assert ours == pytest.approx(scale * theirs, rel=0.01), name
