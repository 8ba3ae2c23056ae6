"""Character files' small parts: the name table, image headers, the generic source set, and
hostile files that must only ever raise ExampleSetError (no ICT needed but where marked)."""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facecast.rig.characters.character import load_character
from facecast.rig.characters.expression_names import ARKIT_NAMES, half_of, normalise_name
from facecast.rig.characters.generic import VRM_COMPOSITIONS, generic_sources
from facecast.rig.errors import ExampleSetError
from facecast.rig.io.gltf import export_glb, pack_glb
from facecast.rig.io.image_headers import image_size


@pytest.mark.parametrize(
    ("authored", "expected", "rule"),
    [
        ("jawOpen", "jawOpen", "ARKit name"),
        ("JawOpen", "jawOpen", "Perfect Sync capitals"),
        ("EyeBlinkLeft", "eyeBlinkLeft", "Perfect Sync capitals"),
        ("eyeBlink_L", "eyeBlinkLeft", "_L/_R suffix"),
        ("mouthSmile_R", "mouthSmileRight", "_L/_R suffix"),
        ("blendShape1.jawOpen", "jawOpen", "prefix dropped"),
        ("Fcl_MTH_A", "aa", "VRoid Fcl_ clip"),
        ("Fcl_EYE_Close_L", "blinkLeft", "VRoid Fcl_ clip"),
        ("Fcl_ALL_Joy", "happy", "VRoid Fcl_ clip"),
        ("A", "aa", "VRM 0.x preset"),
        ("Joy", "happy", "VRM 0.x preset"),
        ("Blink_R", "blinkRight", "VRM 0.x preset"),
        ("lookUp", "lookUp", "VRM 1.0 preset"),
        ("Fcl_BRW_Fun", None, "without an ARKit or VRM preset twin"),
        ("browInnerUp_L", None, "one side"),
        ("grin", None, "not an ARKit, Perfect Sync"),
    ],
)
def test_name_normalisation_table(authored, expected, rule):
    match = normalise_name(authored)

    assert match.name == expected and rule in match.how


def test_every_arkit_name_survives_capitals_and_side_suffixes():
    for name in ARKIT_NAMES:
        capital = name[0].upper() + name[1:]
        suffixed = name.replace("Left", "_L").replace("Right", "_R")
        assert normalise_name(capital).name == name
        assert normalise_name(suffixed).name == name


def test_halves_of_side_less_shapes_are_recognised():
    assert half_of("BrowInnerUp_L") == ("browInnerUp", "left")
    assert half_of("cheekPuffRight") == ("cheekPuff", "right")
    assert half_of("jawOpen") is None


# -- image headers -----------------------------------------------------------------------


def _png_header(width: int, height: int) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    body = b"IHDR" + ihdr
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + body + struct.pack(">I", zlib.crc32(body))


def _jpeg_header(width: int, height: int) -> bytes:
    app0 = b"\xff\xe0" + struct.pack(">H", 16) + b"JFIF\0" + b"\0" * 9
    sof = b"\xff\xc2" + struct.pack(">HBHHB", 11, 8, height, width, 1) + b"\x01\x11\x00"
    return b"\xff\xd8" + app0 + sof


@pytest.mark.parametrize("make", [_png_header, _jpeg_header])
def test_image_size_reads_the_header_only(make):
    assert image_size(make(60000, 123), "img") == (60000, 123)


def test_webp_lossless_size():
    bits = (300 - 1) | ((200 - 1) << 14)
    data = b"RIFF" + b"\0" * 4 + b"WEBPVP8L" + b"\0" * 4 + b"\x2f" + struct.pack("<I", bits)

    assert image_size(data, "img") == (300, 200)


@pytest.mark.parametrize("data", [b"", b"\x89PNG\r\n\x1a\n\0\0", b"\xff\xd8\xff", b"GIF89a"])
def test_unreadable_image_header_is_bad_image(data):
    with pytest.raises(ExampleSetError) as info:
        image_size(data, "img")

    assert info.value.code == "bad_image"


# -- the generic source set --------------------------------------------------------------


def test_generic_set_has_the_arkit_shapes_but_tongue_out_and_composes_vrm_presets():
    generic = generic_sources()

    assert generic.names[0] == "neutral"
    assert set(generic.names[1:]) == set(ARKIT_NAMES) - {"tongueOut"}
    assert generic.points.shape == (52, 26, 3) and generic.stable_points.tolist() == [
        2,
        3,
        7,
        9,
        10,
    ]
    neutral = generic.points[0]
    for preset, composition in VRM_COMPOSITIONS.items():
        expected = neutral + sum(
            w * (generic.source_points(s) - neutral) for s, w in composition.items()
        )
        np.testing.assert_allclose(generic.source_points(preset), expected)


@pytest.mark.ict
def test_generic_set_is_what_the_script_makes_from_ict():
    import importlib.util
    from pathlib import Path

    from facecast.rig.sources.ict import locate_ict

    archive = locate_ict()
    if archive is None:
        pytest.skip("needs ../shared/data/ict-facekit")
    script = Path(__file__).resolve().parents[2] / "scripts" / "make_generic_sources.py"
    spec = importlib.util.spec_from_file_location("make_generic_sources", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    # The eyes come from the generic face rendered and tracked (724 frames, minutes): the
    # set keeps the tracked keys they were taken from, and the script's arithmetic on them
    # and on ICT must give the shipped points.
    with np.load(module.OUT) as shipped:
        seen = dict(zip(shipped["names"].tolist(), shipped["tracked"], strict=True))
    arrays = module.generic_arrays(archive, seen)

    generic = generic_sources()
    assert tuple(arrays["names"]) == generic.names
    np.testing.assert_array_equal(arrays["points"], generic.points)
    np.testing.assert_array_equal(arrays["stable_points"], generic.stable_points)


# -- hostile files -----------------------------------------------------------------------


def _tiny_vrm() -> tuple[dict, bytes]:
    """A four-vertex face with two ARKit morphs and a VRM 1.0 block binding them."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    deltas = np.zeros((2, 4, 3))
    deltas[0, 0, 1] = -0.2
    deltas[1, 2, 2] = 0.1
    glb = export_glb(vertices, faces, deltas, ["jawOpen", "EyeBlinkLeft"])
    length = int.from_bytes(glb[12:16], "little")
    doc = json.loads(glb[20 : 20 + length])
    blob = glb[20 + length + 8 :]
    doc["extensionsUsed"] = ["VRMC_vrm"]
    doc["extensions"] = {
        "VRMC_vrm": {
            "specVersion": "1.0",
            "meta": {
                "name": "tiny",
                "authors": ["me"],
                "licenseUrl": "https://vrm.dev/licenses/1.0/",
            },
            "expressions": {
                "preset": {"aa": {"morphTargetBinds": [{"node": 0, "index": 0, "weight": 0.5}]}}
            },
        }
    }
    return doc, blob


def test_tiny_vrm_loads():
    doc, blob = _tiny_vrm()

    character = load_character(pack_glb(doc, blob))

    assert set(character.expressions) == {"jawOpen", "eyeBlinkLeft", "aa"}


def _paths(value, prefix=()):
    yield prefix
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _paths(item, (*prefix, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from _paths(item, (*prefix, index))


_JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-5, 10**12)
    | st.floats(allow_nan=False)
    | st.text(max_size=5),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3)
    ),
    max_leaves=5,
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_any_mutated_field_is_an_example_set_error_or_loads(data):
    doc, blob = _tiny_vrm()
    paths = [p for p in _paths(doc) if p]
    path = data.draw(st.sampled_from(paths))
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    parent[path[-1]] = data.draw(_JSON)

    try:
        load_character(pack_glb(doc, blob), label="fuzz.vrm")
    except ExampleSetError as exc:
        assert exc.code and "fuzz.vrm" in str(exc)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2000), st.binary(min_size=1, max_size=8))
def test_cut_or_overwritten_bytes_are_an_example_set_error_or_load(at, noise):
    doc, blob = _tiny_vrm()
    data = bytearray(pack_glb(doc, blob))
    at = at % len(data)

    for candidate in (bytes(data[:at]), bytes(data[:at] + noise + data[at + len(noise) :])):
        try:
            load_character(candidate)
        except ExampleSetError as exc:
            assert exc.code
