"""``facecast stream`` end to end against a real server: output files equal offline cloning."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.cli.main import main
from facecast.rig.demo import demo_animation

from ._stream_fixtures import RIG_ID, demo_rig, live_server, rigs_dir

__all__ = ["demo_rig", "live_server", "rigs_dir"]  # fixtures used by name


@pytest.fixture(scope="module")
def short_animation(tmp_path_factory):
    """One second of the demo performance at 60 fps as an .npz source animation."""
    animation = demo_animation(seconds=1.0, fps=60.0)
    path = tmp_path_factory.mktemp("anim") / "performance.npz"
    np.savez(path, points=animation.points, fps=np.float64(animation.fps))
    return path, animation


def test_stream_demo_writes_npz_equal_to_offline_weights(live_server, demo_rig, tmp_path):
    out = tmp_path / "clone.npz"

    status = main(["stream", live_server.base_url, "demo", "--rig", RIG_ID, "-o", str(out), "-q"])

    assert status == 0
    with np.load(out) as written:
        weights = written["weights"]
        fps = float(written["fps"])
    points = demo_animation().points
    expected = np.stack([demo_rig.weights(p) for p in points]).astype(np.float32)
    np.testing.assert_array_equal(weights, expected)
    assert fps == 60.0


def test_realtime_vertices_f16_match_offline_clone_within_f16_tolerance(
    live_server, demo_rig, short_animation, tmp_path
):
    source, animation = short_animation
    out = tmp_path / "clone.npz"

    status = main(
        [
            "stream", live_server.base_url, str(source), "--rig", RIG_ID, "-o", str(out),
            "--output", "vertices", "--dtype", "f16", "--realtime", "-q",
        ]
    )  # fmt: skip

    assert status == 0
    with np.load(out) as written:
        vertices = written["vertices"]
        weights = written["weights"]
    expected = demo_rig.clone(animation.points)
    scale = np.abs(expected).max()
    np.testing.assert_allclose(vertices, expected, atol=2e-3 * scale, rtol=0)
    # Weights recovered from the f16 vertices are close to the rig's own.
    np.testing.assert_allclose(weights, demo_rig.weights(animation.points), atol=0.05)


def test_stream_to_glb_writes_a_gltf_binary(live_server, short_animation, tmp_path):
    source, _ = short_animation
    out = tmp_path / "clone.glb"

    status = main(
        ["stream", live_server.base_url, str(source), "--rig", RIG_ID, "-o", str(out), "-q"]
    )

    assert status == 0
    assert out.read_bytes()[:4] == b"glTF"


def test_stream_with_an_unknown_rig_exits_2_naming_the_rig(live_server, tmp_path, capsys):
    out = tmp_path / "clone.npz"

    status = main(["stream", live_server.base_url, "demo", "--rig", "nope", "-o", str(out), "-q"])

    assert status == 2
    assert "rig_not_found" in capsys.readouterr().err
    assert not out.exists()


def test_stream_with_a_malformed_url_exits_2(tmp_path, capsys):
    status = main(["stream", "localhost:1", "demo", "--rig", RIG_ID, "-o", str(tmp_path / "o.npz")])

    assert status == 2
    assert "server URL" in capsys.readouterr().err
