"""Compressed glTF read as its uncompressed twin: the ICT test avatar as meshopt, quantised
(KHR_mesh_quantization) and Draco files made at test time (tests/rig/_compressed.py), read by
``load_character`` and ``read_glb_morph_targets``; a file that does not decode, or declares
more than the reader's bounds, is a named error before anything is decoded."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.rig.characters.character import Character, load_character
from facecast.rig.characters.expression_names import ARKIT_NAMES
from facecast.rig.errors import ExampleSetError
from facecast.rig.io.gltf import export_glb, pack_glb, read_glb_morph_targets
from facecast.rig.io.gltf_check import GltfLimits, max_decoded_bytes
from facecast.rig.io.gltf_read import BufferReader, load_document
from tests.hostile._glb import glb, grid_face, meshopt_zeros, split

from . import _avatars
from ._compressed import GLTFPACK_MISSING, KINDS, compressed, gltfpack, split_glb
from ._memory import traced_peak

MiB = 1 << 20


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
    start = ext["byteOffset"] + 1  # past the codec's header byte
    blob[start : start + ext["byteLength"] - 1] = b"\xff" * (ext["byteLength"] - 1)


def _meshopt_bad_filter(doc, blob) -> None:
    _face_position_view(doc)["extensions"]["EXT_meshopt_compression"]["filter"] = "ZIP"


def _meshopt_codec_v1(doc, blob) -> None:
    blob[_face_position_view(doc)["extensions"]["EXT_meshopt_compression"]["byteOffset"]] = 0xA1


def _meshopt_color(doc, blob) -> None:
    _face_position_view(doc)["extensions"]["EXT_meshopt_compression"]["filter"] = "COLOR"


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
        ("meshopt", _meshopt_codec_v1, "version 1 is KHR_meshopt_compression's"),
        ("meshopt", _meshopt_color, "'COLOR'"),
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


def test_meshopt_views_decode_within_the_accessor_values_limit_at_it_and_one_past():
    # 100 rows of 16 bytes decoded: 1,600 bytes, 4 for each of 400 accessor values.
    data = meshopt_zeros(1_600)
    at_limit = GltfLimits(accessor_values=400)
    one_past = GltfLimits(accessor_values=399)

    character = load_character(data, label="avatar.glb", limits=at_limit)
    with pytest.raises(ExampleSetError) as info:
        load_character(data, label="avatar.glb", limits=one_past)

    assert list(character.expressions) == ["jawOpen"]
    assert info.value.code == "gltf_exceeds_limits"
    assert "1600 bytes of meshopt views" in str(info.value)
    assert "max_gltf_accessor_values" in str(info.value)


@pytest.mark.parametrize("read_rows", [99, 0], ids=["one-row-short", "unread"])
def test_a_meshopt_view_decoding_more_than_its_accessors_read_is_refused(read_rows):
    # 100 rows of 16 bytes: an accessor reading the first byte of all 100 needs them all
    # (16 x 99 + 1 bytes, to a whole row); reading 99 (16 x 98 + 1) leaves a row no one reads, and a
    # view no accessor names decodes for nothing. Refused by the check, before decoding.
    needed = meshopt_zeros(1_600, read_rows=100)
    data = meshopt_zeros(1_600, read_rows=read_rows)

    character = load_character(needed, label="avatar.glb")
    with pytest.raises(ExampleSetError) as info:
        load_document(data, "avatar.glb", GltfLimits())

    assert list(character.expressions) == ["jawOpen"]
    assert info.value.code == "bad_compression"
    read = "its accessors read 1569 of them" if read_rows else "no accessor reads it"
    assert f"bufferView 2 decodes to 1600 bytes (EXT_meshopt_compression), but {read}" in str(
        info.value
    )


def test_the_reader_decodes_no_more_than_its_limits_allow_whatever_the_check_allowed():
    # The reader's bound is the limits' (max_decoded_bytes), not a constant of its own: a
    # document checked under looser limits is refused by a reader given tighter ones,
    # before the decoder runs.
    document = load_document(meshopt_zeros(1_600), "avatar.glb", GltfLimits(accessor_values=400))
    tight = GltfLimits(accessor_values=399)

    with pytest.raises(ExampleSetError) as info:
        BufferReader(document, "avatar.glb", tight).decode_all()
    BufferReader(document, "avatar.glb", GltfLimits(accessor_values=400)).decode_all()

    assert max_decoded_bytes(tight) == 1_596  # 4 bytes a value: a float32 or uint32
    assert info.value.code == "too_large"
    assert "100 x 16 bytes, more than the reader's limit of 1596" in str(info.value)


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


def small_glb() -> bytes:
    """A 12 x 12 grid with a jawOpen morph target, one accessor a view (no ICT needed)."""
    side = 12
    u, v = np.meshgrid(np.arange(side, dtype=np.float32), np.arange(side, dtype=np.float32))
    positions = np.stack([u.ravel(), v.ravel(), np.zeros(side * side, np.float32)], axis=1) / side
    corners = np.arange(side * side).reshape(side, side)[:-1, :-1].ravel()
    faces = np.concatenate([np.stack([corners, corners + 1, corners + side], 1),
                            np.stack([corners + 1, corners + side + 1, corners + side], 1)])  # fmt: skip
    jaw = np.zeros_like(positions)
    jaw[: side * 3, 1] = -0.05
    arrays = [positions, jaw, faces.astype(np.uint32).reshape(-1, 1)]
    blob, views, accessors = b"", [], []
    for array, kind in zip(arrays, ("VEC3", "VEC3", "SCALAR"), strict=True):
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": array.nbytes})
        accessor = {"bufferView": len(views) - 1, "count": len(array), "type": kind,
                    "componentType": 5125 if kind == "SCALAR" else 5126}  # fmt: skip
        if array is positions:
            accessor.update(min=positions.min(0).tolist(), max=positions.max(0).tolist())
        accessors.append(accessor)
        blob += array.tobytes()
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": views,
        "accessors": accessors,
        "meshes": [
            {
                "primitives": [
                    {"attributes": {"POSITION": 0}, "indices": 2, "targets": [{"POSITION": 1}]}
                ],
                "extras": {"targetNames": ["jawOpen"]},
            }
        ],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
    }
    return pack_glb(doc, blob)


@functools.cache
def small(kind: str) -> bytes:
    return compressed(small_glb(), kind)


@functools.cache
def small_twin() -> Character:
    return load_character(small_glb(), label="twin.glb")


@pytest.mark.parametrize("kind", ["meshopt", "draco"])
@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_mutated_compressed_bytes_are_read_or_refused_by_name_never_crash(kind, data):
    glb = bytearray(small(kind))
    twin = small_twin()
    chunk = int.from_bytes(glb[12:16], "little")
    start = 20 + chunk + 8  # the BIN chunk: the compressed streams
    for _ in range(data.draw(st.integers(1, 8))):
        at = data.draw(st.integers(start, len(glb) - 1))
        glb[at] = data.draw(st.integers(0, 255))

    try:
        character = load_character(bytes(glb), label="mutated.glb")
    except ExampleSetError as exc:
        assert exc.code in ("bad_compression", "bad_gltf", "too_large", "non_finite"), exc
    else:  # decoded: then to what its accessors declare
        assert character.face_vertices.shape == twin.face_vertices.shape
        assert character.face_faces.shape == twin.face_faces.shape
        assert np.isfinite(character.face_vertices).all()
        assert all(np.isfinite(e.face_displacement).all() for e in character.expressions.values())


# meshopt carries a NaN position through; Draco leaves morph targets as float accessors
# (meshopt's exponential filter would turn a NaN offset into a number).
@pytest.mark.parametrize(("where", "kind"), [("positions", "meshopt"), ("morph target", "draco")])
def test_a_decoded_nan_is_non_finite_not_a_face(where, kind):
    doc, blob = split_glb(small_glb())
    blob = bytearray(blob)
    view = doc["bufferViews"][0 if where == "positions" else 1]
    blob[view["byteOffset"] + 4 : view["byteOffset"] + 8] = np.float32(np.nan).tobytes()
    data = compressed(pack_glb(doc, bytes(blob)), kind)

    with pytest.raises(ExampleSetError) as info:
        load_character(data, label="avatar.glb")

    assert info.value.code == "non_finite" and "NaN or Inf" in str(info.value)


def test_khr_meshopt_compression_is_refused_by_name_as_the_pages_cannot_show_it():
    def khr(doc, blob):
        doc["extensionsRequired"] = ["KHR_meshopt_compression"]
        doc["extensionsUsed"] = ["KHR_meshopt_compression"]

    with pytest.raises(ExampleSetError) as info:
        load_character(edited(small_glb(), khr), label="avatar.glb")

    assert info.value.code == "unsupported_extension"
    assert "EXT_meshopt_compression" in str(info.value)


def test_meshopt_views_decoding_to_more_than_the_accessor_bound_exceed_the_limits():
    # The small grid's accessors hold 1,590 values; its position view now declares twice
    # the rows it has, 8,088 decoded bytes in all: past 4 bytes a value allowed, refused by
    # gltf_check before anything is decoded, though every accessor fits its bound.
    def doubled(doc, blob):
        view = doc["bufferViews"][0]
        view["extensions"]["EXT_meshopt_compression"]["count"] *= 2
        view["byteLength"] *= 2

    data = edited(small("meshopt"), doubled)
    doc, _ = split_glb(data)
    values = sum(a["count"] * {"VEC3": 3, "SCALAR": 1}[a["type"]] for a in doc["accessors"])
    assert values == 1590

    with pytest.raises(ExampleSetError) as info:
        load_character(data, label="avatar.glb", limits=GltfLimits(accessor_values=values))

    assert info.value.code == "gltf_exceeds_limits"
    assert "8088 bytes of meshopt views" in str(info.value)


def _with_a_second_mesh(face_glb: bytes, vertices: int) -> tuple[bytes, bytes]:
    """``face_glb`` with a grid mesh of about ``vertices`` vertices and no morph targets
    beside its face (a body no expression moves); and that grid alone as a GLB."""
    doc, blob = split(face_glb)
    grid, triangles = grid_face(vertices)
    body = export_glb(grid, triangles, np.zeros((1, len(grid), 3)), ["still"], normals=False)
    positions = grid.astype("<f4").tobytes()
    corners = triangles.astype("<u4").tobytes()
    views, accessors = len(doc["bufferViews"]), len(doc["accessors"])
    doc["bufferViews"] += [
        {"buffer": 0, "byteOffset": len(blob), "byteLength": len(positions)},
        {"buffer": 0, "byteOffset": len(blob) + len(positions), "byteLength": len(corners)},
    ]
    doc["accessors"] += [
        {"bufferView": views, "componentType": 5126, "count": len(grid), "type": "VEC3",
         "min": grid.min(0).tolist(), "max": grid.max(0).tolist()},
        {"bufferView": views + 1, "componentType": 5125, "count": triangles.size,
         "type": "SCALAR"},
    ]  # fmt: skip
    doc["meshes"].append(
        {"name": "body", "primitives": [{"attributes": {"POSITION": accessors},
                                         "indices": accessors + 1}]}
    )  # fmt: skip
    doc["nodes"].append({"mesh": len(doc["meshes"]) - 1})
    doc["buffers"][0]["byteLength"] = len(blob) + len(positions) + len(corners)
    return glb(doc, blob + positions + corners), body


def _peak_of_reading(data: bytes) -> int:
    """The most bytes numpy and Python hold at once while ``load_character`` reads ``data``
    (read once before, so that imports and caches are not counted)."""
    load_character(data)
    return traced_peak(lambda: load_character(data))


def test_a_draco_mesh_no_expression_moves_is_decoded_checked_and_let_go():
    # A face of 16 morph targets beside a 250,000-vertex Draco body no expression moves:
    # the body is decoded (a part that does not decode is refused at upload), but its
    # decoded positions (float64) and corners (int64), 17 MiB, are not kept while the face
    # is read. Kept, they added to the face's read: 49 MiB against the face's 32 MiB and
    # the body's 34 (read as a character of its own).
    neutral, triangles = grid_face(100_000)
    rng = np.random.default_rng(0)
    shape = np.sin(neutral[None, :, :1] * rng.uniform(5, 40, (16, 1, 1)))
    names = [n for n in ARKIT_NAMES if not n.startswith("eyeLook")][:16]
    deltas = rng.normal(0, 0.003, (16, 1, 3)) * shape
    face = export_glb(neutral, triangles, deltas, names, normals=False)
    both, body = _with_a_second_mesh(face, 250_000)

    face_alone = _peak_of_reading(compressed(face, "draco"))
    body_alone = _peak_of_reading(compressed(body, "draco"))
    with_body = _peak_of_reading(compressed(both, "draco"))

    assert load_character(compressed(both, "draco")).face_mesh == 0
    assert with_body <= max(face_alone, body_alone) + 2 * MiB, (
        with_body / MiB, face_alone / MiB, body_alone / MiB,
    )  # fmt: skip
