"""``facecast import ict-facekit`` and ``facecast bridge``: files written, errors reported."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facecast.cli.errors import CommandError
from facecast.rig.characters.loaders import load_example_set
from facecast.rig.errors import ExampleSetError
from facecast.rig.sources.source_rig import ARKIT_NAMES, load_source_rig

from ._helpers import run_command

ICT = Path(__file__).resolve().parents[3] / "shared" / "data" / "ict-facekit"
needs_ict = pytest.mark.skipif(
    not (ICT / "ict_facekit.npz").is_file(), reason="ICT-FaceKit data absent"
)


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    if not (ICT / "ict_facekit.npz").is_file():
        pytest.skip("ICT-FaceKit data absent")
    out = tmp_path_factory.mktemp("ict") / "arkit"
    assert run_command("import_", ["import", "ict-facekit", str(ICT), "-o", str(out)]) == 0
    return out


@pytest.mark.ict
@needs_ict
def test_import_writes_an_example_set_that_load_example_set_reads(imported):
    example_set = load_example_set(imported)
    assert example_set.names[0] == "neutral"
    assert set(example_set.names[1:]) == set(ARKIT_NAMES) - {"tongueOut"}
    assert example_set.num_points == 24 and example_set.num_vertices == 9409


@pytest.mark.ict
@needs_ict
def test_imported_split_shapes_sum_ict_halves_at_the_feature_points(imported):
    example_set = load_example_set(imported)
    with np.load(ICT / "ict_facekit.npz") as archive:
        names = [str(n) for n in archive["expression_names"]]
        neutral = archive["neutral"].astype(np.float64)
        left = archive["expressions"][names.index("browInnerUp_L")]
        right = archive["expressions"][names.index("browInnerUp_R")]
    text = (imported / "facecast.toml").read_text()
    vertices = [int(v) for v in text.split("ICT vertices [")[1].split("]")[0].split(",")]
    expected = (neutral + (left - neutral) + (right - neutral))[vertices]
    got = example_set.source_points[example_set.names.index("browInnerUp")]
    assert np.allclose(got, expected, atol=1e-5)


@pytest.mark.ict
@needs_ict
def test_imported_folder_is_a_source_rig_equal_to_the_ict_archive_one(imported):
    rng = np.random.default_rng(0)
    weights = rng.uniform(size=(4, 52))
    from_folder = load_source_rig(imported)
    from_archive = load_source_rig(ICT)
    assert from_folder.missing == ("tongueOut",)
    assert np.allclose(from_folder.points(weights), from_archive.points(weights), atol=1e-5)


@pytest.mark.ict
@needs_ict
def test_import_refuses_a_non_empty_output_folder(tmp_path):
    (tmp_path / "keep.txt").write_text("x")
    with pytest.raises(CommandError, match="--force"):
        run_command("import_", ["import", "ict-facekit", str(ICT), "-o", str(tmp_path)])


def test_import_of_a_folder_that_is_not_ict_names_what_it_expected(tmp_path):
    with pytest.raises(ExampleSetError) as info:
        run_command("import_", ["import", "ict-facekit", str(tmp_path), "-o", str(tmp_path / "o")])
    assert "generic_neutral_mesh.obj" in str(info.value)


@pytest.mark.parametrize("landmarks", ["1,1", "68", "a,b"])
def test_import_refuses_bad_landmark_lists(tmp_path, landmarks):
    with pytest.raises(CommandError, match="--landmarks"):
        run_command(
            "import_",
            [
                "import",
                "ict-facekit",
                str(tmp_path),
                "-o",
                str(tmp_path / "o"),
                "--landmarks",
                landmarks,
            ],
        )


def test_bridge_livelink_with_a_missing_source_rig_fails_clearly(tmp_path):
    with pytest.raises(ExampleSetError) as info:
        run_command(
            "bridge",
            [
                "bridge", "livelink", "http://127.0.0.1:9", "--channel", "stage", "--rig", "r",
                "--source-rig", str(tmp_path / "absent"), "--listen", "127.0.0.1:0",
            ],
        )  # fmt: skip
    assert info.value.code == "missing_file"


def test_bridge_livelink_without_a_server_is_a_command_error(tmp_path, example_set):
    example_set.save_npz(tmp_path / "source.npz")
    with pytest.raises(CommandError, match="cannot publish"):
        run_command(
            "bridge",
            [
                "bridge", "livelink", "http://127.0.0.1:9", "--channel", "stage", "--rig", "r",
                "--source-rig", str(tmp_path / "source.npz"), "--listen", "127.0.0.1:0",
            ],
        )  # fmt: skip


@pytest.mark.parametrize("address", ["nohost:", "host:99999", ":80"])
def test_bridge_refuses_bad_addresses(address, capsys):
    with pytest.raises(SystemExit):
        run_command(
            "bridge",
            ["bridge", "vmc", "http://h", "--channel", "c", "--rig", "r", "--send", address],
        )
    assert "HOST:PORT" in capsys.readouterr().err


@pytest.mark.parametrize("position", ["1,2", "a,b,c", "0,nan,0"])
def test_bridge_refuses_a_head_position_that_is_not_three_finite_numbers(position, capsys):
    with pytest.raises(SystemExit):
        run_command(
            "bridge",
            ["bridge", "livelink", "http://h", "--channel", "c", "--rig", "r",
             "--source-rig", "x", "--vmc-head-position", position],
        )  # fmt: skip
    assert "X,Y,Z" in capsys.readouterr().err
