"""The client library and ``facecast stream`` with output "moving" against a real server."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from facecast.cli.main import main
from facecast.client.connection import connect
from facecast.rig.demo import demo_animation

from ._stream_fixtures import RIG_ID, demo_rig, live_server, rigs_dir

__all__ = ["demo_rig", "live_server", "rigs_dir"]  # fixtures used by name


@pytest.fixture(scope="module")
def frames() -> np.ndarray:
    return demo_animation(seconds=0.5, fps=60.0).points


def test_session_knows_the_moving_vertices(live_server, demo_rig):
    async def run():
        async with connect(live_server.base_url, RIG_ID, output="moving") as session:
            return session.moving

    moving = asyncio.run(run())
    np.testing.assert_array_equal(moving, demo_rig.moving_vertices)
    assert moving.size < demo_rig.num_vertices  # the demo's head has still vertices


def test_full_vertices_of_moving_results_equal_vertices_results_bit_for_bit(
    live_server, demo_rig, frames
):
    async def run(output):
        async with connect(live_server.base_url, RIG_ID, output=output) as session:
            results = [await session.clone(p) for p in frames[:5]]
            if output == "moving":
                return session.full_vertices(
                    np.stack([r.vertices for r in results]), demo_rig.target_neutral
                )
            return np.stack([r.vertices for r in results])

    full = asyncio.run(run("vertices"))
    rebuilt = asyncio.run(run("moving"))
    assert rebuilt.shape == full.shape == (5, demo_rig.num_vertices, 3)
    np.testing.assert_array_equal(rebuilt.view(np.uint32), full.view(np.uint32))


def test_full_vertices_refuses_a_neutral_of_another_size(live_server, demo_rig, frames):
    async def run():
        async with connect(live_server.base_url, RIG_ID, output="moving") as session:
            result = await session.clone(frames[0])
            with pytest.raises(ValueError, match="neutral"):
                session.full_vertices(result.vertices, demo_rig.target_neutral[:-1])

    asyncio.run(run())


def test_stream_command_with_moving_output_writes_the_whole_mesh(live_server, demo_rig, tmp_path):
    source = tmp_path / "take.npz"
    animation = demo_animation(seconds=0.25, fps=60.0)
    np.savez(source, points=animation.points, fps=animation.fps)
    outputs = {}
    for output in ("vertices", "moving"):
        out = tmp_path / f"{output}.npz"
        argv = ["stream", live_server.base_url, str(source), "--rig", RIG_ID, "-o", str(out),
                "--output", output, "-q"]  # fmt: skip
        assert main(argv) == 0
        with np.load(out) as written:
            outputs[output] = written["vertices"]
    assert outputs["moving"].shape == (animation.num_frames, demo_rig.num_vertices, 3)
    np.testing.assert_array_equal(outputs["moving"], outputs["vertices"])
