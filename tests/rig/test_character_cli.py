"""`facecast fit` on character files, and characters paired with a source folder."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facecast.cli.main import main
from facecast.rig.characters.character import load_character
from facecast.rig.characters.character_examples import character_example_set
from facecast.rig.characters.generic import CHARACTER_FIT_DEFAULTS, generic_sources
from facecast.rig.characters.loaders import load_example_set
from facecast.rig.errors import ExampleSetError
from facecast.rig.rigfile import load_rig

from ._avatars import avatar

pytestmark = pytest.mark.ict


def test_fit_a_vrm_prints_the_pairing_report_and_writes_the_rig(tmp_path, capsys):
    path = tmp_path / "avatar.vrm"
    path.write_bytes(avatar("vrm1"))

    assert main(["fit", str(path), "-o", str(tmp_path / "avatar.rig")]) == 0

    out = capsys.readouterr().out
    assert "43 expressions paired; face mesh (vertex outputs) 'face'" in out
    assert "unpaired VRM 1.0 expression 'Wink'" in out
    assert load_rig(tmp_path / "avatar.rig").num_examples == 44
    assert str(tmp_path) not in out.split("wrote")[0]


def test_fit_json_carries_the_pairing(tmp_path, capsys):
    path = tmp_path / "avatar.glb"
    path.write_bytes(avatar("perfect_sync"))

    main(["fit", str(path), "-o", str(tmp_path / "a.rig"), "--json"])

    payload = json.loads(capsys.readouterr().out)
    jaw = next(e for e in payload["pairing"]["entries"] if e["authored"] == "JawOpen")
    assert jaw == {
        "authored": "JawOpen",
        "origin": "morph target",
        "meshes": ["face", "teeth"],
        "expression": "jawOpen",
        "paired": True,
        "reason": jaw["reason"],
    }
    assert "Perfect Sync capitals" in jaw["reason"]
    # No --noise: fitted for a live tracker, as PUT /v1/characters/{id} fits it.
    report = payload["fit_report"]
    assert (report["noise"], report["clamp"]) == (
        CHARACTER_FIT_DEFAULTS["noise"],
        CHARACTER_FIT_DEFAULTS["clamp"],
    )


def test_fit_a_neutral_only_glb_says_what_is_possible(tmp_path, capsys):
    path = tmp_path / "plain.glb"
    path.write_bytes(avatar("neutral_only"))

    status = main(["fit", str(path), "-o", str(tmp_path / "a.rig")])

    error = capsys.readouterr().err
    assert status != 0 and not (tmp_path / "a.rig").exists()
    assert "plain.glb has no expressions" in error and "facecast expressions" in error
    assert str(tmp_path) not in error


def _imported_source(root):
    """A folder as `facecast import ict-facekit` writes it: facecast.toml with the stable
    points, source/<ICT-style name>.npy (the generic points, saved under ICT's spelling)."""
    generic = generic_sources()
    source = root / "source"
    source.mkdir(parents=True)
    for name, points in zip(generic.names, generic.points, strict=True):
        spelled = name.replace("Left", "_L").replace("Right", "_R")
        np.save(source / f"{spelled}.npy", points)
    (root / "facecast.toml").write_text(
        '[source]\nneutral = "source/neutral.npy"\n'
        f"stable_points = {generic.stable_points.tolist()}\n"
    )
    return source


def test_teeth_first_glb_with_an_imported_source_folder_keeps_face_and_stable_points(tmp_path):
    source = _imported_source(tmp_path / "ict")
    path = tmp_path / "avatar.glb"
    path.write_bytes(avatar("teeth_first"))

    example_set = load_example_set(path, source=source)

    face = load_character(avatar("teeth_first")).face_vertices
    assert example_set.num_vertices == face.shape[0]
    assert example_set.stable_points.tolist() == generic_sources().stable_points.tolist()
    assert "eyeBlinkLeft" in example_set.names and len(example_set.names) == 52


def test_character_example_set_with_a_source_folder_normalises_file_names(tmp_path):
    source = _imported_source(tmp_path / "ict")
    character = load_character(avatar("vrm1"))

    example_set, report = character_example_set(character, source)

    assert set(report.paired) == set(generic_sources().names[1:])
    assert example_set.stable_points.tolist() == generic_sources().stable_points.tolist()
    reasons = {e.authored: e.reason for e in report.unpaired}
    assert "no file of this name" in reasons["aa"]


def test_unpaired_morph_with_a_source_folder_names_the_rules_tried(tmp_path):
    source = _imported_source(tmp_path / "ict")
    (source / "jawOpen.npy").unlink()
    path = tmp_path / "avatar.glb"
    path.write_bytes(avatar("perfect_sync"))

    with pytest.raises(ExampleSetError) as info:
        load_example_set(path, source=source)

    assert info.value.code == "unpaired_example"
    assert "'JawOpen'" in str(info.value) and "Perfect Sync" in str(info.value)
