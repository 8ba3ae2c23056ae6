"""Loading example sets from folders, .npz files and glTF targets, and every bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facecast.rig.characters.loaders import load_example_set
from facecast.rig.errors import ExampleSetError
from facecast.rig.examples import ExampleSet
from facecast.rig.io.gltf import export_glb
from facecast.rig.io.meshio import points_to_csv, write_obj

EXAMPLES = ("happy", "sad", "surprise")
FEATURES = [0, 4, 8, 2]


def grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """An n x n vertex grid in the z=0 plane and its 2(n-1)^2 triangles."""
    xs, ys = np.meshgrid(np.arange(float(n)), np.arange(float(n)))
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)
    faces = []
    for r in range(n - 1):
        for c in range(n - 1):
            a = n * r + c
            faces += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    return vertices, np.array(faces)


def synthetic_shapes(seed: int = 0):
    """Source meshes (4, 9, 3), target meshes (4, 16, 3) and their faces; row 0 neutral."""
    rng = np.random.default_rng(seed)
    src, src_faces = grid(3)
    tgt, tgt_faces = grid(4)
    source = src + np.concatenate([np.zeros((1, 9, 3)), rng.normal(0, 0.1, (3, 9, 3))])
    target = tgt + np.concatenate([np.zeros((1, 16, 3)), rng.normal(0, 0.1, (3, 16, 3))])
    return source, src_faces, target, tgt_faces


def write_set(folder: Path, source_kind: str = "obj", *, examples=EXAMPLES) -> dict:
    """Write a facecast.toml example-set folder; returns the arrays written."""
    source, src_faces, target, tgt_faces = synthetic_shapes()
    (folder / "source").mkdir(parents=True)
    (folder / "target").mkdir()
    lines = []
    for i, name in enumerate(("neutral", *examples)):
        src_file = f"source/{name}.{source_kind}"
        if source_kind == "obj":
            write_obj(folder / src_file, source[i], src_faces)
        elif source_kind == "npy":
            np.save(folder / src_file, source[i][FEATURES])
        else:
            (folder / src_file).write_text(points_to_csv(source[i][FEATURES]))
        write_obj(folder / f"target/{name}.obj", target[i], tgt_faces)
        if i:
            lines.append(f'{name} = ["{src_file}", "target/{name}.obj"]')
    features = f"feature_points = {FEATURES}\n" if source_kind == "obj" else ""
    (folder / "facecast.toml").write_text(
        f'[source]\nneutral = "source/neutral.{source_kind}"\n{features}'
        '[target]\nneutral = "target/neutral.obj"\n'
        "[examples]\n" + "\n".join(lines) + "\n"
    )
    return {
        "source": source,
        "target": target,
        "target_faces": tgt_faces,
        "source_faces": src_faces,
    }


def edit_manifest(folder: Path, old: str, new: str) -> None:
    manifest = folder / "facecast.toml"
    text = manifest.read_text()
    assert old in text
    manifest.write_text(text.replace(old, new))


# -- (a) folder -------------------------------------------------------------------------


def test_folder_with_obj_sources_loads_meshes_points_and_toml_order(tmp_path):
    written = write_set(tmp_path)

    example_set = load_example_set(tmp_path)

    assert example_set.names == ("neutral", *EXAMPLES)
    np.testing.assert_array_equal(example_set.target_vertices, written["target"])
    np.testing.assert_array_equal(example_set.target_faces, written["target_faces"])
    np.testing.assert_array_equal(example_set.source_vertices, written["source"])
    np.testing.assert_array_equal(example_set.source_points, written["source"][:, FEATURES])
    np.testing.assert_array_equal(example_set.feature_indices, FEATURES)


def test_examples_keep_toml_order_not_alphabetical(tmp_path):
    write_set(tmp_path, examples=("zed", "alpha", "mid"))

    example_set = load_example_set(tmp_path / "facecast.toml")

    assert example_set.names == ("neutral", "zed", "alpha", "mid")


@pytest.mark.parametrize("kind", ["npy", "csv"])
def test_folder_with_point_sources_loads_points_without_feature_indices(tmp_path, kind):
    written = write_set(tmp_path, kind)

    example_set = load_example_set(tmp_path)

    np.testing.assert_allclose(example_set.source_points, written["source"][:, FEATURES])
    assert example_set.feature_indices is None and example_set.source_vertices is None


def test_feature_points_may_be_a_file_in_the_folder(tmp_path):
    write_set(tmp_path)
    (tmp_path / "source" / "features.txt").write_text("# eyes\n0, 4\n8 2\n")
    edit_manifest(
        tmp_path, f"feature_points = {FEATURES}", 'feature_points = "source/features.txt"'
    )

    example_set = load_example_set(tmp_path)

    np.testing.assert_array_equal(example_set.feature_indices, FEATURES)


def _bad(tmp_path, **kwargs) -> ExampleSetError:
    with pytest.raises(ExampleSetError) as info:
        load_example_set(tmp_path, **kwargs)
    return info.value


def test_missing_manifest_is_an_error_naming_the_folder(tmp_path):
    error = _bad(tmp_path)

    assert str(tmp_path) in str(error)


def test_malformed_toml_names_the_manifest(tmp_path):
    write_set(tmp_path)
    (tmp_path / "facecast.toml").write_text("[source\nneutral = ")

    error = _bad(tmp_path)

    assert "facecast.toml: malformed TOML" in str(error) and error.code == "bad_manifest"


def test_missing_example_file_names_example_and_file(tmp_path):
    write_set(tmp_path)
    (tmp_path / "target" / "sad.obj").unlink()

    error = _bad(tmp_path)

    assert "'sad'" in str(error) and "sad.obj: file not found" in str(error)
    assert error.code == "missing_file"


def test_target_vertex_count_mismatch_names_example(tmp_path):
    written = write_set(tmp_path)
    write_obj(tmp_path / "target" / "happy.obj", written["target"][1][:-1], [[0, 1, 2]])

    error = _bad(tmp_path)

    assert "example 'happy'" in str(error) and "15 vertices" in str(error)
    assert error.code == "vertex_count_mismatch"


def test_source_vertex_count_mismatch_names_example(tmp_path):
    written = write_set(tmp_path)
    write_obj(tmp_path / "source" / "surprise.obj", written["source"][3][:-2], [[0, 1, 2]])

    error = _bad(tmp_path)

    assert "example 'surprise'" in str(error) and "source" in str(error)
    assert error.code == "vertex_count_mismatch"


def test_source_point_count_mismatch_names_example(tmp_path):
    write_set(tmp_path, "npy")
    np.save(tmp_path / "source" / "sad.npy", np.zeros((3, 3)))

    error = _bad(tmp_path)

    assert "example 'sad'" in str(error) and error.code == "point_count_mismatch"


def test_example_without_source_pair_names_example(tmp_path):
    write_set(tmp_path)
    edit_manifest(
        tmp_path, 'sad = ["source/sad.obj", "target/sad.obj"]', 'sad = ["target/sad.obj"]'
    )

    error = _bad(tmp_path)

    assert "[examples] sad" in str(error) and "[source file, target file]" in str(error)


def test_feature_index_out_of_range_names_index_and_source_neutral(tmp_path):
    write_set(tmp_path)
    edit_manifest(tmp_path, f"feature_points = {FEATURES}", "feature_points = [0, 9]")

    error = _bad(tmp_path)

    assert "index 9" in str(error) and "neutral.obj" in str(error)
    assert error.code == "index_out_of_range"


def test_obj_sources_without_feature_points_are_an_error(tmp_path):
    write_set(tmp_path)
    edit_manifest(tmp_path, f"feature_points = {FEATURES}\n", "")

    error = _bad(tmp_path)

    assert "feature_points" in str(error) and "facecast.toml" in str(error)


def test_nan_coordinate_names_file_and_line(tmp_path):
    write_set(tmp_path)
    path = tmp_path / "target" / "happy.obj"
    lines = path.read_text().splitlines()
    lines[3] = "v nan 0 0"
    path.write_text("\n".join(lines) + "\n")

    error = _bad(tmp_path)

    assert "example 'happy'" in str(error) and "happy.obj, line 4: NaN or Inf" in str(error)
    assert error.code == "non_finite"


def test_nan_in_csv_source_names_file_and_line(tmp_path):
    write_set(tmp_path, "csv")
    (tmp_path / "source" / "sad.csv").write_text("x,y,z\n0,0,0\n1,1,1\n2,inf,2\n3,3,3\n")

    error = _bad(tmp_path)

    assert "sad.csv, line 4: NaN or Inf" in str(error)


def test_fewer_than_two_examples_is_an_error(tmp_path):
    write_set(tmp_path, examples=())

    error = _bad(tmp_path)

    assert error.code == "too_few_examples" and "facecast.toml" in str(error)


@pytest.mark.parametrize("escape", ["../outside.obj", "target/../../outside.obj", "/etc/passwd"])
def test_path_escaping_the_folder_is_refused(tmp_path, escape):
    folder = tmp_path / "set"
    write_set(folder)
    write_obj(tmp_path / "outside.obj", *grid(4))
    edit_manifest(folder, '"target/happy.obj"', f'"{escape}"')

    error = _bad(folder)

    assert error.code == "path_escape" and escape in str(error)


def test_example_named_neutral_is_refused(tmp_path):
    write_set(tmp_path)
    edit_manifest(tmp_path, "happy = [", "neutral = [")

    error = _bad(tmp_path)

    assert "'neutral' is reserved" in str(error)


def test_mixing_mesh_and_point_sources_is_refused(tmp_path):
    write_set(tmp_path)
    np.save(tmp_path / "source" / "odd.npy", np.zeros((4, 3)))
    edit_manifest(tmp_path, '"source/sad.obj"', '"source/odd.npy"')

    error = _bad(tmp_path)

    assert "mix meshes" in str(error)


# -- (b) npz -----------------------------------------------------------------------------


def test_npz_written_by_save_npz_round_trips(tmp_path):
    write_set(tmp_path / "set")
    original = load_example_set(tmp_path / "set")
    path = tmp_path / "set.npz"
    original.save_npz(path)

    loaded = load_example_set(path)

    assert loaded.names == original.names
    np.testing.assert_allclose(loaded.target_vertices, original.target_vertices, atol=1e-6)
    np.testing.assert_array_equal(loaded.source_points, original.source_points)
    np.testing.assert_array_equal(loaded.feature_indices, original.feature_indices)
    np.testing.assert_array_equal(loaded.target_faces, original.target_faces)


def test_npz_missing_arrays_names_file_and_arrays(tmp_path):
    path = tmp_path / "partial.npz"
    np.savez(path, names=np.array(["neutral", "a"]), source_points=np.zeros((2, 3, 3)))

    error = _bad(path)

    assert "partial.npz" in str(error) and "target_vertices" in str(error)


def test_corrupt_npz_names_file(tmp_path):
    path = tmp_path / "corrupt.npz"
    path.write_bytes(b"PK\x03\x04 definitely not a zip")

    error = _bad(path)

    assert "corrupt.npz: not a readable .npz" in str(error)


def test_npz_with_inconsistent_arrays_names_file(tmp_path):
    path = tmp_path / "bad.npz"
    np.savez(
        path,
        names=np.array(["neutral", "a"]),
        source_points=np.zeros((2, 3, 3)),
        target_vertices=np.zeros((3, 4, 3)),
        target_faces=np.array([[0, 1, 2]]),
    )

    error = _bad(path)

    assert "bad.npz: target_vertices" in str(error)


# -- (c) glTF target paired with a source folder ---------------------------------------


def write_gltf_pair(folder: Path, *, source_kind: str = "obj", names=EXAMPLES) -> dict:
    """A GLB with neutral + EXAMPLES morph targets and a flat source folder."""
    source, src_faces, target, tgt_faces = synthetic_shapes()
    folder.mkdir(parents=True, exist_ok=True)
    deltas = target - target[0]
    glb = folder / "character.glb"
    glb.write_bytes(export_glb(target[0], tgt_faces, deltas, ["neutral", *EXAMPLES]))
    src = folder / "source"
    src.mkdir()
    for i, name in enumerate(("neutral", *EXAMPLES)):
        if name != "neutral" and name not in names:
            continue
        if source_kind == "obj":
            write_obj(src / f"{name}.obj", source[i], src_faces)
        else:
            np.save(src / f"{name}.npy", source[i][FEATURES])
    if source_kind == "obj":
        (src / "feature_points.txt").write_text(" ".join(map(str, FEATURES)))
    return {"glb": glb, "source_dir": src, "source": source, "target": target, "faces": tgt_faces}


def test_glb_target_paired_by_name_with_obj_source_folder(tmp_path):
    pair = write_gltf_pair(tmp_path)

    example_set = load_example_set(pair["glb"], source=pair["source_dir"])

    assert example_set.names == ("neutral", *EXAMPLES)
    np.testing.assert_allclose(example_set.target_vertices, pair["target"], atol=1e-5)
    np.testing.assert_array_equal(example_set.target_faces, pair["faces"])
    np.testing.assert_array_equal(example_set.source_points, pair["source"][:, FEATURES])


def test_glb_target_with_npy_point_sources(tmp_path):
    pair = write_gltf_pair(tmp_path, source_kind="npy")

    example_set = load_example_set(pair["glb"], source=pair["source_dir"])

    np.testing.assert_array_equal(example_set.source_points, pair["source"][:, FEATURES])


def test_glb_target_via_manifest_with_feature_points_in_toml(tmp_path):
    pair = write_gltf_pair(tmp_path)
    (pair["source_dir"] / "feature_points.txt").unlink()
    (tmp_path / "facecast.toml").write_text(
        f'[source]\nfolder = "source"\nfeature_points = {FEATURES}\n'
        '[target]\ngltf = "character.glb"\n'
    )

    example_set = load_example_set(tmp_path)

    assert isinstance(example_set, ExampleSet)
    np.testing.assert_array_equal(example_set.feature_indices, FEATURES)


def test_morph_target_without_source_file_is_named(tmp_path):
    pair = write_gltf_pair(tmp_path, names=("happy", "surprise"))

    error = _bad(pair["glb"], source=pair["source_dir"])

    assert "morph target 'sad'" in str(error) and error.code == "unpaired_example"


def test_unpaired_morph_target_is_skipped_with_warning_when_allowed(tmp_path):
    pair = write_gltf_pair(tmp_path, names=("happy", "surprise"))

    with pytest.warns(UserWarning, match=r"'sad'"):
        example_set = load_example_set(pair["glb"], source=pair["source_dir"], allow_unpaired=True)

    assert example_set.names == ("neutral", "happy", "surprise")


def test_source_file_without_morph_target_is_named(tmp_path):
    pair = write_gltf_pair(tmp_path)
    write_obj(pair["source_dir"] / "wink.obj", pair["source"][1], [[0, 1, 2]])

    error = _bad(pair["glb"], source=pair["source_dir"])

    assert "source file 'wink.obj'" in str(error) and error.code == "unpaired_example"


def test_glb_source_vertex_count_mismatch_names_example(tmp_path):
    pair = write_gltf_pair(tmp_path)
    write_obj(pair["source_dir"] / "sad.obj", pair["source"][2][:5], [[0, 1, 2]])

    error = _bad(pair["glb"], source=pair["source_dir"])

    assert "example 'sad'" in str(error) and error.code == "vertex_count_mismatch"


def test_glb_without_source_neutral_is_an_error(tmp_path):
    pair = write_gltf_pair(tmp_path)
    (pair["source_dir"] / "neutral.obj").unlink()

    error = _bad(pair["glb"], source=pair["source_dir"])

    assert "no source neutral" in str(error)


def test_glb_without_source_pairs_with_the_generic_set_and_names_the_rules_tried(tmp_path):
    _, _, target, faces = synthetic_shapes()
    glb = tmp_path / "character.glb"
    glb.write_bytes(export_glb(target[0], faces, target[1:3] - target[0], ["wink", "grin"]))

    error = _bad(glb)

    assert error.code == "too_few_examples" and "character.glb" in str(error)
    assert "Perfect Sync" in str(error) and "Fcl_" in str(error)


def test_unknown_path_type_is_an_error_naming_it(tmp_path):
    path = tmp_path / "set.zip"
    path.write_bytes(b"")

    error = _bad(path)

    assert "set.zip: not an example set" in str(error)


ICT = Path(__file__).resolve().parents[3] / "shared" / "data" / "ict-facekit" / "ict_facekit.npz"


@pytest.mark.ict
@pytest.mark.skipif(not ICT.exists(), reason="needs ../shared/data/ict-facekit")
def test_ict_head_obj_folder_loads_with_landmarks_as_feature_points(tmp_path):
    with np.load(ICT) as ict:
        faces = ict["faces"]
        names = [str(n) for n in ict["expression_names"][:3]]
        target = np.concatenate([ict["neutral"][None], ict["expressions"][:3]]).astype(np.float64)
        deltas = target - target[0]
        source = ict["identities"][0].astype(np.float64) + deltas
        landmarks = ict["landmarks68"].tolist()
    write_set_from_arrays(tmp_path, names, source, faces, target, faces, landmarks)

    example_set = load_example_set(tmp_path)

    assert example_set.names == ("neutral", *names)
    np.testing.assert_array_equal(example_set.target_vertices, target)
    np.testing.assert_array_equal(example_set.target_faces, faces)
    np.testing.assert_array_equal(example_set.source_points, source[:, landmarks])


def write_set_from_arrays(folder, names, source, source_faces, target, target_faces, features):
    lines = []
    for i, name in enumerate(("neutral", *names)):
        write_obj(folder / f"s_{name}.obj", source[i], source_faces)
        write_obj(folder / f"t_{name}.obj", target[i], target_faces)
        lines.append(f'"{name}" = ["s_{name}.obj", "t_{name}.obj"]')
    (folder / "facecast.toml").write_text(
        f'[source]\nneutral = "s_neutral.obj"\nfeature_points = {list(features)}\n'
        '[target]\nneutral = "t_neutral.obj"\n[examples]\n' + "\n".join(lines[1:]) + "\n"
    )
