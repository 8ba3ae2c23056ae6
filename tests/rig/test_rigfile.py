"""The rig file refuses truncated, tampered and unknown-version files with a clear error."""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest

from facecast.rig import RigFileError, fit, load_rig, rig_from_bytes

from .test_fit import make_set


@pytest.fixture(scope="module")
def rig_bytes():
    return fit(make_set()).to_bytes()


def _rewrite(data: bytes, change) -> bytes:
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    change(arrays)
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue()


def test_loads_without_pickles(rig_bytes):
    with np.load(io.BytesIO(rig_bytes), allow_pickle=False) as npz:
        assert "meta" in npz.files


@pytest.mark.parametrize("cut", [0, 10, 100, 1000, -200, -1])
def test_truncated_file_is_refused(rig_bytes, cut):
    with pytest.raises(RigFileError):
        rig_from_bytes(rig_bytes[:cut])


def test_tampered_array_fails_the_checksum(rig_bytes):
    def change(arrays):
        arrays["linear_coeffs"] = arrays["linear_coeffs"] * 1.0001

    with pytest.raises(RigFileError, match="checksum") as info:
        rig_from_bytes(_rewrite(rig_bytes, change))
    assert info.value.code == "checksum_mismatch"


def test_unknown_version_is_refused(rig_bytes):
    def change(arrays):
        meta = json.loads(arrays["meta"].tobytes())
        meta["format_version"] = 99
        arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)

    with pytest.raises(RigFileError, match="version 99") as info:
        rig_from_bytes(_rewrite(rig_bytes, change))
    assert info.value.code == "unsupported_version"


def test_not_a_rig_file_is_refused(tmp_path):
    path = tmp_path / "x.npz"
    np.savez(path, a=np.zeros(3))
    with pytest.raises(RigFileError, match="not a facecast rig file"):
        load_rig(path)


def test_missing_file_names_the_path(tmp_path):
    with pytest.raises(RigFileError, match=r"nothing-here\.npz"):
        load_rig(tmp_path / "nothing-here.npz")


def test_zip_bomb_is_refused_before_reading(rig_bytes):
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("meta.npy", b"\0" * (2 << 20))
    with pytest.raises(RigFileError, match="over the limit") as info:
        rig_from_bytes(buffer.getvalue(), max_bytes=1 << 20)
    assert info.value.code == "rig_too_large"


def test_garbage_bytes_are_refused():
    with pytest.raises(RigFileError):
        rig_from_bytes(b"\x00\x01garbage" * 50)


@pytest.mark.parametrize(
    "spoil",
    [
        lambda rig: rig._blend_basis.__setitem__((1, 0), np.nan),
        lambda rig: rig.model.linear_coeffs.__setitem__((0, 1), np.inf),
        lambda rig: rig.model.radial_coeffs.__setitem__((1, 1), -np.inf),
        lambda rig: rig.model.source_neutral.__setitem__((0, 0), np.nan),
    ],
    ids=["nan-basis", "inf-linear", "inf-radial", "nan-neutral"],
)
def test_non_finite_records_are_refused_even_with_a_valid_checksum(spoil):
    # Anyone can write a file whose checksum matches; NaN would then stream as vertices.
    rig = fit(make_set())
    spoil(rig)
    data = rig.to_bytes()

    with pytest.raises(RigFileError, match="NaN or Inf") as info:
        rig_from_bytes(data)
    assert info.value.code == "rig_not_finite"


@pytest.mark.parametrize("kind", ["glb", "gltf"])
def test_a_character_file_given_as_a_rig_says_how_to_upload_or_fit_it(kind):
    from facecast.rig.io.gltf import export_glb

    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=float)
    glb = export_glb(vertices, np.array([[0, 1, 2]]), np.ones((1, 3, 3)), ["jawOpen"])
    data = glb if kind == "glb" else b'{"asset": {"version": "2.0"}, "meshes": []}'

    with pytest.raises(RigFileError) as info:
        rig_from_bytes(data, source="rig 'avatar'")

    assert info.value.code == "character_not_rig"
    assert "facecast rigs put" in str(info.value) and "facecast fit" in str(info.value)
