"""``output=moving`` on WS /v1/stream: only the moving vertices, equal to the full mesh's there."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import websockets
from _server_helpers import NAMES, open_session, recv_error, recv_message

from facecast.protocol import ErrorCode, Frame, Hello, Result, encode
from facecast.rig import ExampleSet, fit
from facecast.server.settings import Settings
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio

#: Target vertices no example moves.
STILL = np.array([0, 3, 4, 11])


def still_rig(num_vertices: int = 16, still=STILL, **fit_options):
    """4 examples, 5 feature points; vertices ``STILL`` of the target never move."""
    rng = np.random.default_rng(0)
    m, k = len(NAMES), 5
    source = np.repeat(rng.normal(size=(1, k, 3)), m, axis=0)
    source[1:] += rng.normal(scale=0.3, size=(m - 1, k, 3))
    target = np.repeat(rng.normal(size=(1, num_vertices, 3)), m, axis=0)
    target[1:] += rng.normal(scale=0.3, size=(m - 1, num_vertices, 3))
    target[1:, still] = target[0, still]
    faces = np.array([[i, i + 1, i + 2] for i in range(num_vertices - 2)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit(ExampleSet(NAMES, source, target, faces), **fit_options)


def points_near(rig, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (rig.source_neutral + rng.normal(scale=0.1, size=rig.source_neutral.shape)).astype(
        np.float32
    )


def connect(server, path: str = "/v1/stream"):
    return websockets.connect(f"{server.ws_url}{path}", subprotocols=["facecast.v1"])


async def stream(server, rig_id: str, points: list[np.ndarray], **hello):
    """The ready and the results of one session sending ``points`` one at a time."""
    async with connect(server) as ws:
        ready = await open_session(ws, rig_id, **hello)
        results = []
        for seq, p in enumerate(points):
            await ws.send(encode(Frame(seq=seq, ts=seq / 60, points=p)))
            message = await recv_message(ws)
            assert isinstance(message, Result), message
            results.append(message)
    return ready, results


@pytest.fixture(params=["inline", "pool"])
async def served(request, tmp_path, ws_impl, monkeypatch):
    from facecast.server.stream import session as session_module

    # Every blend on the loop, or every one through the clone pool's batcher.
    monkeypatch.setattr(
        session_module, "INLINE_MAX_SECONDS", 1e9 if request.param == "inline" else 0.0
    )
    async with run_server(Settings(rigs_dir=tmp_path / "rigs"), ws=ws_impl) as server:
        server.app.state.store.put_rig("exact", still_rig())
        server.app.state.store.put_rig("bounded", still_rig(noise=0.05, clamp="nonneg"))
        server.app.state.store.put_rig("statue", still_rig(still=np.arange(16)))
        yield server


@pytest.mark.parametrize("rig_id", ["exact", "bounded"])
async def test_ready_lists_the_vertices_some_example_moves(served, rig_id):
    rig = served.app.state.store.get(rig_id)
    ready, _ = await stream(served, rig_id, [], output="moving")
    assert ready.output == "moving"
    np.testing.assert_array_equal(ready.moving, np.setdiff1d(np.arange(16), STILL))
    np.testing.assert_array_equal(ready.moving, rig.moving_vertices)


@pytest.mark.parametrize("rig_id", ["exact", "bounded"])
async def test_moving_f32_results_equal_the_full_vertices_on_the_moving_subset_bit_for_bit(
    served, rig_id
):
    rig = served.app.state.store.get(rig_id)
    points = [points_near(rig, seed) for seed in range(4)]
    ready, moving = await stream(served, rig_id, points, output="moving")
    _, full = await stream(served, rig_id, points, output="vertices")
    for p, part, whole in zip(points, moving, full, strict=True):
        assert part.vertices.shape == (ready.moving.size, 3)
        assert part.vertices.dtype == np.float32
        np.testing.assert_array_equal(
            part.vertices.view(np.uint32), whole.vertices[ready.moving].view(np.uint32)
        )
        np.testing.assert_array_equal(part.vertices, rig.blend(rig.weights(p))[ready.moving])


async def test_moving_f16_results_equal_the_full_f16_vertices_on_the_moving_subset(served):
    rig = served.app.state.store.get("bounded")
    points = [points_near(rig, seed) for seed in range(3)]
    ready, moving = await stream(served, "bounded", points, output="moving", dtype="f16")
    _, full = await stream(served, "bounded", points, output="vertices", dtype="f16")
    assert ready.dtype == "f16"
    for part, whole in zip(moving, full, strict=True):
        assert part.vertices.dtype == np.float16
        np.testing.assert_array_equal(part.vertices, whole.vertices[ready.moving])


async def test_still_vertices_of_the_full_output_are_the_target_neutral(served):
    rig = served.app.state.store.get("bounded")
    _, full = await stream(served, "bounded", [points_near(rig, 9)], output="vertices")
    np.testing.assert_array_equal(full[0].vertices[STILL], rig.target_neutral[STILL])


async def test_a_channel_publisher_cannot_ask_for_the_moving_output(served):
    async with connect(served, "/v1/channels/stage/publish") as ws:
        await ws.send(encode(Hello(rig="exact", output="moving")))
        error = await recv_error(ws)
    assert error.code == ErrorCode.INVALID_FIELD
    assert error.fatal


async def test_a_rig_that_moves_no_vertex_refuses_the_moving_output(served):
    async with connect(served) as ws:
        await ws.send(encode(Hello(rig="statue", output="moving")))
        error = await recv_error(ws)
    assert error.code == ErrorCode.INVALID_FIELD
    assert "moves no vertex" in error.message
