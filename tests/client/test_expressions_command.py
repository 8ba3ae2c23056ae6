"""``facecast expressions`` and the example-set folder it writes: ready for ``fit``, an
artist's example kept, nothing written on failure, a clear word when ICT is missing."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.cli.main import main
from facecast.rig import fit
from facecast.rig.characters.loaders import load_example_set
from facecast.rig.errors import ExampleSetError
from facecast.rig.io.meshio import read_obj_vertices, write_obj
from facecast.rig.sources.ict import locate_ict
from facecast.rig.transfer import (
    GeneratedExpressions,
    identity_correspondence,
    write_expression_set,
)

ARCHIVE = locate_ict()
needs_ict = pytest.mark.skipif(
    ARCHIVE is None, reason="ICT-FaceKit not found (../shared/data/ict-facekit or $FACECAST_ICT)"
)


def _square() -> tuple[np.ndarray, np.ndarray]:
    x, y = np.meshgrid(np.linspace(0, 1, 5), np.linspace(0, 1, 5))
    vertices = np.stack([x.ravel(), y.ravel(), 0.1 * np.sin(3 * x.ravel())], axis=1)
    index = np.arange(25).reshape(5, 5)
    a, b, c, d = (
        index[:-1, :-1].ravel(),
        index[:-1, 1:].ravel(),
        index[1:, 1:].ravel(),
        index[1:, :-1].ravel(),
    )
    return vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _generated(names=("neutral", "jawOpen", "eyeBlinkLeft")) -> GeneratedExpressions:
    vertices, faces = _square()
    rng = np.random.default_rng(1)
    m = len(names)
    shapes = vertices + np.concatenate(
        [np.zeros((1, 25, 3)), 0.05 * rng.normal(size=(m - 1, 25, 3))]
    )
    points = rng.normal(size=(m, 4, 3))
    return GeneratedExpressions(
        names=tuple(names),
        target_vertices=shapes,
        target_faces=faces,
        source_points=points,
        stable_points=(0, 1, 2),
        correspondence=identity_correspondence(vertices, faces, vertices, faces),
    )


# -- the folder ---------------------------------------------------------------------------


def test_written_folder_loads_as_the_same_example_set(tmp_path):
    generated = _generated()
    written = write_expression_set(tmp_path / "examples", generated)
    loaded = load_example_set(tmp_path / "examples")
    assert written.written == ("jawOpen", "eyeBlinkLeft")
    assert loaded.names == generated.names
    np.testing.assert_allclose(loaded.target_vertices, generated.target_vertices, atol=1e-12)
    np.testing.assert_allclose(loaded.source_points, generated.source_points, atol=1e-12)
    np.testing.assert_array_equal(loaded.target_faces, generated.target_faces)
    assert loaded.stable_points.tolist() == [0, 1, 2]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["examples"]  # no staging left


def test_an_artists_target_example_is_kept_unless_overwrite(tmp_path):
    folder = tmp_path / "examples"
    write_expression_set(folder, _generated())
    edited = read_obj_vertices(folder / "target" / "jawOpen.obj") + 0.5
    write_obj(folder / "target" / "jawOpen.obj", edited, _square()[1])
    (folder / "notes.txt").write_text("the artist's")

    again = write_expression_set(folder, _generated())
    assert again.kept == ("jawOpen", "eyeBlinkLeft")
    np.testing.assert_allclose(read_obj_vertices(folder / "target" / "jawOpen.obj"), edited)
    assert (folder / "notes.txt").read_text() == "the artist's"

    replaced = write_expression_set(folder, _generated(), overwrite=True)
    assert replaced.written == ("jawOpen", "eyeBlinkLeft")
    np.testing.assert_allclose(
        read_obj_vertices(folder / "target" / "jawOpen.obj"), _generated().target_vertices[1]
    )


def test_examples_added_by_hand_stay_listed(tmp_path):
    folder = tmp_path / "examples"
    write_expression_set(folder, _generated())
    write_obj(folder / "target" / "happy.obj", _square()[0] + 0.2, _square()[1])
    (folder / "source" / "happy.csv").write_text("x,y,z\n" + "0.5,0.5,0.5\n" * 4)
    manifest = folder / "facecast.toml"
    manifest.write_text(
        manifest.read_text() + '"happy" = ["source/happy.csv", "target/happy.obj"]\n'
    )
    write_expression_set(folder, _generated(("neutral", "mouthLeft")))
    assert load_example_set(folder).names == (
        "neutral",
        "jawOpen",
        "eyeBlinkLeft",
        "happy",
        "mouthLeft",
    )


def test_a_folder_for_another_target_is_refused_and_left_as_it_was(tmp_path):
    folder = tmp_path / "examples"
    write_expression_set(folder, _generated())
    before = sorted(p.relative_to(folder) for p in folder.rglob("*"))
    vertices, faces = _square()
    other = GeneratedExpressions(
        names=("neutral", "jawOpen"),
        target_vertices=np.stack([vertices[:-5], vertices[:-5]]),
        target_faces=faces[faces.max(axis=1) < 20],
        source_points=np.zeros((2, 4, 3)),
        stable_points=None,
        correspondence=identity_correspondence(vertices, faces, vertices, faces),
    )
    with pytest.raises(ExampleSetError) as caught:
        write_expression_set(folder, other)
    assert caught.value.code == "target_mismatch"
    assert sorted(p.relative_to(folder) for p in folder.rglob("*")) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["examples"]


# -- the command ----------------------------------------------------------------------------


def test_missing_ict_is_named_as_what_the_command_needs(tmp_path, capsys):
    target = tmp_path / "face.obj"
    write_obj(target, *_square())
    code = main(["expressions", str(target), "-o", str(tmp_path / "out"), "--ict",
                 str(tmp_path / "nowhere")])  # fmt: skip
    assert code == 2
    assert "ICT-FaceKit not found" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_non_manifold_target_is_refused_before_anything_is_written(tmp_path, capsys):
    target = tmp_path / "fan.obj"
    target.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 -1 0\nv 0 0 1\nf 1 2 3\nf 2 1 4\nf 1 2 5\n")
    assert main(["expressions", str(target), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "not a manifold surface" in err and "edge (0, 1)" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.ict
@needs_ict
def test_command_on_ict_topology_writes_a_set_that_fits(tmp_path, capsys):
    from facecast.rig.sources.ict_arkit import arkit_example_set

    truth = arkit_example_set(ARCHIVE, identity="person01")
    target = tmp_path / "person01.obj"
    write_obj(target, truth.target_neutral, truth.target_faces)
    out = tmp_path / "examples"
    code = main(["expressions", str(target), "-o", str(out), "--names", "jawOpen",
                 "mouthSmileLeft", "--quiet"])  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert "same topology (identity)" in printed and "wrote 2 expression(s)" in printed
    examples = load_example_set(out)
    assert examples.names == ("neutral", "jawOpen", "mouthSmileLeft")
    assert examples.num_points == 24
    # Where ICT's own jawOpen moves a vertex by more than a centimetre, the transferred one
    # moves it to within a few millimetres of the same place.
    jaw = examples.target_vertices[1] - examples.target_vertices[0]
    true_jaw = truth.target_vertices[truth.names.index("jawOpen")] - truth.target_neutral
    moving = np.linalg.norm(true_jaw, axis=1) > 1.0
    assert np.median(np.linalg.norm(jaw[moving] - true_jaw[moving], axis=1)) < 0.25
    rig = fit(examples)
    assert rig.num_examples == 3


@pytest.mark.ict
@needs_ict
def test_markers_out_of_range_write_nothing(tmp_path, capsys):
    target = tmp_path / "face.obj"
    write_obj(target, *_square())
    markers = tmp_path / "markers.txt"
    markers.write_text("0 0\n100 4\n99999 24\n")
    code = main(["expressions", str(target), "-o", str(tmp_path / "out"), "--markers",
                 str(markers), "--quiet"])  # fmt: skip
    assert code == 2
    assert "source vertex 99999, outside [0, 9409)" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.ict
@needs_ict
def test_another_topology_without_markers_asks_for_them(tmp_path, capsys):
    target = tmp_path / "face.obj"
    write_obj(target, *_square())
    code = main(["expressions", str(target), "-o", str(tmp_path / "out"), "--quiet"])
    assert code == 2
    assert "needs markers" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_gltf_target_is_read_as_its_face_mesh(tmp_path):
    from facecast.rig.io.gltf import export_glb
    from facecast.rig.transfer import read_target_mesh

    vertices, faces = _square()
    path = tmp_path / "face.glb"
    path.write_bytes(export_glb(vertices, faces, 0.1 * np.ones((1, 25, 3)), ["smile"]))
    read_vertices, read_faces = read_target_mesh(path)
    np.testing.assert_allclose(read_vertices, vertices, atol=1e-6)  # float32 in the file
    np.testing.assert_array_equal(read_faces, faces)


def test_an_unknown_mesh_type_and_a_file_in_the_folders_place_are_refused(tmp_path):
    from facecast.rig.transfer import read_target_mesh

    (tmp_path / "face.stl").write_text("solid x\n")
    with pytest.raises(ExampleSetError) as caught:
        read_target_mesh(tmp_path / "face.stl")
    assert caught.value.code == "bad_mesh_type"
    (tmp_path / "taken").write_text("a file, not a folder")
    with pytest.raises(ExampleSetError) as caught:
        write_expression_set(tmp_path / "taken", _generated())
    assert caught.value.code == "bad_output"
    assert (tmp_path / "taken").read_text() == "a file, not a folder"


@pytest.mark.ict
@needs_ict
def test_automatic_markers_on_a_target_that_is_no_face_write_nothing(tmp_path, capsys):
    target = tmp_path / "face.obj"
    write_obj(target, *_square())
    code = main(["expressions", str(target), "-o", str(tmp_path / "out"), "--markers", "auto",
                 "--quiet"])  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err
    assert "without markers" in err and "does not look like a face" in err
    assert not (tmp_path / "out").exists()


def test_a_still_fraction_out_of_range_is_refused_before_anything_is_written(tmp_path, capsys):
    target = tmp_path / "face.obj"
    write_obj(target, *_square())
    code = main(["expressions", str(target), "-o", str(tmp_path / "out"), "--markers", "auto",
                 "--still", "1.5", "--ict", str(tmp_path)])  # fmt: skip
    assert code == 2
    assert "still: expected a fraction in (0, 1)" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
