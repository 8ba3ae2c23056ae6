"""Source animations in (.npz, .npy, OBJ frames) and cloned animations out (.npz, .glb, OBJ)."""

from __future__ import annotations

import io

import numpy as np
import pygltflib
import pytest
import trimesh

from facecast.rig.errors import InputError
from facecast.rig.io.gltf import read_glb_morph_targets
from facecast.rig.io.meshio import read_obj, write_obj
from facecast.rig.sources.animation import SourceAnimation, write_clone_output
from facecast.rig.sources.loading import load_source_animation

FEATURES = [0, 3, 5]


def mesh_frames(frames: int = 4, vertices: int = 6, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(frames, vertices, 3))


def clone_inputs(frames: int = 3):
    """A 4-vertex, 2-triangle target with M=3 examples and per-frame weights."""
    rng = np.random.default_rng(7)
    neutral = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    deltas = rng.normal(scale=0.1, size=(3, 4, 3))
    deltas[0] = 0.0
    weights = rng.random((frames, 3))
    vertices = neutral + np.einsum("fm,mvc->fvc", weights, deltas)
    return {
        "weights": weights,
        "vertices": vertices,
        "names": ["neutral", "a", "b"],
        "neutral": neutral,
        "faces": faces,
        "deltas": deltas,
        "fps": 30.0,
    }


# -- loading ----------------------------------------------------------------------------


def test_npz_with_points_and_fps(tmp_path):
    points = mesh_frames(5, 3)
    path = tmp_path / "perf.npz"
    np.savez(path, points=points, fps=np.float64(24.0))

    animation = load_source_animation(path, num_points=3)

    np.testing.assert_array_equal(animation.points, points)
    assert animation.fps == 24.0 and animation.num_frames == 5
    np.testing.assert_allclose(animation.times, np.arange(5) / 24.0)


def test_a_take_tracked_in_the_grown_layout_drives_a_rig_of_its_earlier_version(tmp_path):
    """``facecast track`` writes the layout it tracked in; the layout grew 20 -> 24 points
    by appending, so a rig fitted on 20 takes the first 20 (as /perform sends it). A file
    naming no layout, or a count that is no version of its layout, stays an error."""
    points = mesh_frames(4, 24)
    tracked, bare = tmp_path / "tracked.npz", tmp_path / "bare.npz"
    np.savez(tracked, points=points, layout=np.str_("mediapipe_face_mesh"))
    np.savez(bare, points=points)

    animation = load_source_animation(tracked, num_points=20)

    np.testing.assert_array_equal(animation.points, points[:, :20])
    assert load_source_animation(tracked, num_points=24).points.shape == (4, 24, 3)
    for path, k in ((bare, 20), (tracked, 21), (tracked, 25)):
        with pytest.raises(InputError) as info:
            load_source_animation(path, num_points=k)
        assert info.value.code == "point_count_mismatch", (path.name, k)


def test_npz_without_fps_defaults_to_60(tmp_path):
    path = tmp_path / "perf.npz"
    np.savez(path, points=mesh_frames(2, 3))

    assert load_source_animation(path).fps == 60.0


def test_npz_with_vertices_selects_feature_points(tmp_path):
    vertices = mesh_frames()
    path = tmp_path / "perf.npz"
    np.savez(path, vertices=vertices)

    animation = load_source_animation(path, feature_indices=FEATURES)

    np.testing.assert_array_equal(animation.points, vertices[:, FEATURES])
    assert animation.source_vertices is None


def test_npz_with_vertices_keeps_meshes_when_asked(tmp_path):
    vertices = mesh_frames()
    path = tmp_path / "perf.npz"
    np.savez(path, vertices=vertices)

    animation = load_source_animation(path, feature_indices=FEATURES, keep_vertices=True)

    np.testing.assert_array_equal(animation.source_vertices, vertices)


def test_npz_with_vertices_but_no_feature_indices_is_an_error(tmp_path):
    path = tmp_path / "perf.npz"
    np.savez(path, vertices=mesh_frames())

    with pytest.raises(InputError, match=r"perf.npz: .*pass feature_indices"):
        load_source_animation(path)


def test_npz_timestamps_are_kept(tmp_path):
    path = tmp_path / "perf.npz"
    np.savez(path, points=mesh_frames(3, 2), timestamps=np.array([0.0, 0.02, 0.05]))

    animation = load_source_animation(path)

    np.testing.assert_array_equal(animation.times, [0.0, 0.02, 0.05])


def test_obj_frames_sorted_naturally_with_fps_file(tmp_path):
    frames = mesh_frames(12)
    faces = [[0, 1, 2]]
    for i, frame in enumerate(frames):
        write_obj(tmp_path / f"take_{i}.obj", frame, faces)  # take_10 sorts after take_9
    (tmp_path / "fps.txt").write_text("25\n")

    animation = load_source_animation(tmp_path, feature_indices=FEATURES)

    np.testing.assert_array_equal(animation.points, frames[:, FEATURES])
    assert animation.fps == 25.0 and animation.source_vertices is None


def test_obj_frames_keep_meshes_as_float32_when_asked(tmp_path):
    frames = mesh_frames(2)
    for i, frame in enumerate(frames):
        write_obj(tmp_path / f"f{i}.obj", frame, [[0, 1, 2]])

    animation = load_source_animation(tmp_path, feature_indices=FEATURES, keep_vertices=True)

    assert animation.source_vertices.dtype == np.float32
    np.testing.assert_allclose(animation.source_vertices, frames, rtol=1e-6)


def test_npy_points(tmp_path):
    path = tmp_path / "p.npy"
    np.save(path, mesh_frames(2, 3))

    assert load_source_animation(path).points.shape == (2, 3, 3)


@pytest.mark.parametrize(
    ("arrays", "kwargs", "expected"),
    [
        ({"points": np.zeros((0, 3, 3))}, {}, "F >= 1"),
        ({"points": np.zeros((2, 3, 2))}, {}, "shape (F, K, 3)"),
        ({"points": np.zeros((2, 3))}, {}, "shape (F, K, 3)"),
        (
            {"points": np.zeros((2, 3, 3))},
            {"num_points": 5},
            "expected 5 feature points per frame, got 3",
        ),
        ({"points": np.array([[[0, 0, 0]], [[0, np.inf, 0]]])}, {}, "frame 1 has NaN or Inf"),
        ({"points": np.zeros((2, 3, 3)), "fps": np.float64(-1)}, {}, "fps must be positive"),
        (
            {"vertices": np.zeros((2, 4, 3))},
            {"feature_indices": [0, 4]},
            "feature index 4 out of range",
        ),
        ({"other": np.zeros(3)}, {}, "needs a 'points' or a 'vertices' array"),
        ({"points": np.array([[["a", "b", "c"]]])}, {}, "not a numeric array"),
    ],
)
def test_bad_npz_animation_names_file_and_problem(tmp_path, arrays, kwargs, expected):
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)

    with pytest.raises(InputError) as info:
        load_source_animation(path, **kwargs)

    assert "bad.npz" in str(info.value) and expected in str(info.value)


def test_obj_frames_with_differing_vertex_counts_name_the_frame(tmp_path):
    write_obj(tmp_path / "f0.obj", mesh_frames(1)[0], [[0, 1, 2]])
    write_obj(tmp_path / "f1.obj", mesh_frames(1, 5)[0], [[0, 1, 2]])

    with pytest.raises(InputError, match=r"f1.obj: frame has 5 vertices") as info:
        load_source_animation(tmp_path, feature_indices=FEATURES)

    assert info.value.code == "vertex_count_mismatch"


def test_obj_frame_with_nan_names_file_and_line(tmp_path):
    write_obj(tmp_path / "f0.obj", mesh_frames(1)[0], [[0, 1, 2]])
    (tmp_path / "f1.obj").write_text("v 0 0 0\nv 0 0 nan\n")

    with pytest.raises(InputError, match=r"f1.obj, line 2: NaN or Inf"):
        load_source_animation(tmp_path, feature_indices=[0])


def test_obj_frame_folder_needs_feature_indices(tmp_path):
    write_obj(tmp_path / "f0.obj", mesh_frames(1)[0], [[0, 1, 2]])

    with pytest.raises(InputError, match=r"pass feature_indices"):
        load_source_animation(tmp_path)


def test_empty_folder_and_bad_fps_file_are_errors(tmp_path):
    with pytest.raises(InputError, match=r"no .obj frames"):
        load_source_animation(tmp_path, feature_indices=[0])
    write_obj(tmp_path / "f0.obj", mesh_frames(1)[0], [[0, 1, 2]])
    (tmp_path / "fps.txt").write_text("fast")
    with pytest.raises(InputError, match=r"fps.txt: fps must be a number"):
        load_source_animation(tmp_path, feature_indices=[0])


def test_missing_and_unknown_files_are_errors(tmp_path):
    (tmp_path / "perf.txt").write_text("")

    with pytest.raises(InputError, match=r"nope.npz: file not found"):
        load_source_animation(tmp_path / "nope.npz")
    with pytest.raises(InputError, match=r"perf.txt: not a source animation"):
        load_source_animation(tmp_path / "perf.txt")


def test_source_animation_rejects_decreasing_timestamps():
    with pytest.raises(InputError, match=r"non-decreasing"):
        SourceAnimation(points=np.zeros((2, 1, 3)), timestamps=[1.0, 0.5])


# -- writing -----------------------------------------------------------------------------


def test_write_npz_round_trips_weights_vertices_names_fps(tmp_path):
    inputs = clone_inputs()
    path = tmp_path / "out.npz"

    write_clone_output(path, **inputs)

    with np.load(path, allow_pickle=False) as out:
        np.testing.assert_allclose(out["weights"], inputs["weights"], rtol=1e-6)
        np.testing.assert_allclose(out["vertices"], inputs["vertices"], atol=1e-6)
        assert out["names"].tolist() == inputs["names"] and float(out["fps"]) == 30.0


def test_write_glb_holds_morph_targets_and_weight_animation(tmp_path):
    inputs = clone_inputs()
    path = tmp_path / "out.glb"

    write_clone_output(path, **inputs)

    neutral, _, deltas, names = read_glb_morph_targets(path)
    gltf = pygltflib.GLTF2.load(str(path))
    scene = trimesh.load(io.BytesIO(path.read_bytes()), file_type="glb")
    # The neutral's all-zero target is left out, and with it its animation track.
    expected = inputs["neutral"] + inputs["deltas"][1:]
    np.testing.assert_allclose(neutral + deltas, expected, atol=1e-6)
    assert names == inputs["names"][1:]
    sampler = gltf.animations[0].samplers[0]
    assert gltf.accessors[sampler.input].count == 3
    assert gltf.accessors[sampler.output].count == 3 * 2
    assert len(next(iter(scene.geometry.values())).vertices) == 4


def test_write_obj_frames_then_read_them_back_as_an_animation(tmp_path):
    inputs = clone_inputs(frames=4)
    folder = tmp_path / "frames"

    write_clone_output(folder, **inputs)

    names = sorted(p.name for p in folder.glob("*.obj"))
    assert names == [f"frame_{i:05d}.obj" for i in range(4)]
    vertices, faces = read_obj(folder / "frame_00002.obj")
    np.testing.assert_allclose(vertices, inputs["vertices"][2], atol=1e-6)
    np.testing.assert_array_equal(faces, inputs["faces"])
    again = load_source_animation(folder, feature_indices=[0, 1, 2, 3])
    assert again.fps == 30.0
    np.testing.assert_allclose(again.points, inputs["vertices"], atol=1e-6)


def test_write_obj_frames_without_vertices_blends_them(tmp_path):
    inputs = clone_inputs(frames=70)  # more than one blending chunk
    expected = inputs["vertices"]
    inputs["vertices"] = None
    folder = tmp_path / "frames"

    write_clone_output(folder, **inputs)

    vertices, _ = read_obj(folder / "frame_00069.obj")
    np.testing.assert_allclose(vertices, expected[69], atol=1e-5)


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"deltas": np.zeros((3, 5, 3))}, "deltas: expected shape (3, 4, 3)"),
        ({"names": ["a"]}, "names: 1 names for 3 weight columns"),
        ({"vertices": np.zeros((3, 5, 3))}, "vertices: expected shape (3, 4, 3)"),
        ({"weights": np.zeros(3)}, "weights: expected shape (F, M)"),
        ({"fps": 0}, "fps must be positive"),
    ],
)
def test_write_rejects_inconsistent_arguments(tmp_path, change, expected):
    inputs = clone_inputs() | change

    with pytest.raises(InputError) as info:
        write_clone_output(tmp_path / "out.npz", **inputs)

    assert expected in str(info.value)
    assert not (tmp_path / "out.npz").exists()
