"""WS /v1/stream against a real uvicorn, under both of uvicorn's WebSocket implementations."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import statistics
import time

import msgpack
import numpy as np
import pytest
import websockets
from _server_helpers import (
    close_code_of,
    errors_logged,
    frame_points,
    masked_frame,
    open_session,
    raw_websocket,
    recv_error,
    recv_message,
    server_logs,
    tiny_example_set,
    tiny_rig,
    wait_until,
)

from facecast.protocol import (
    Calibrate,
    Calibrated,
    Error,
    ErrorCode,
    Frame,
    Hello,
    Ping,
    Pong,
    Result,
    Smoothing,
    encode,
)
from facecast.rig import fit
from facecast.rig.filters import KALMAN_ACCELERATION, KalmanFilter, OneEuroFilter
from facecast.rig.rebase import calibrate, rebase
from facecast.server.compute.cloning import blend_seconds
from facecast.server.settings import Settings
from facecast.server.stream.session import INLINE_MAX_SECONDS
from facecast.server.testing import run_server

pytestmark = pytest.mark.anyio


def connect(server, **kwargs):
    return websockets.connect(f"{server.ws_url}/v1/stream", subprotocols=["facecast.v1"], **kwargs)


def frame(seq: int, points: np.ndarray, ts: float | None = None) -> bytes:
    return encode(Frame(seq=seq, ts=float(seq) / 60 if ts is None else ts, points=points))


async def next_result(ws) -> Result:
    message = await recv_message(ws)
    assert isinstance(message, Result), message
    return message


@pytest.fixture
async def served(settings, rig, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        yield server


# -- results ------------------------------------------------------------------------------


async def test_weights_f32_equal_rig_weights_exactly(served, rig):
    points = [frame_points(rig, i) for i in range(5)]
    async with connect(served) as ws:
        ready = await open_session(ws, "face")
        results = []
        for seq, p in enumerate(points):
            await ws.send(frame(seq, p, ts=100.0 + seq))
            results.append(await next_result(ws))

    assert ready.names == rig.names and ready.num_points == rig.num_points
    for seq, (p, result) in enumerate(zip(points, results, strict=True)):
        assert (result.seq, result.ts, result.weights.dtype) == (seq, 100.0 + seq, np.float32)
        np.testing.assert_array_equal(result.weights, rig.weights(p).astype(np.float32))


async def test_vertices_f32_equal_rig_blend_exactly(served, rig):
    p = frame_points(rig, 1)
    async with connect(served) as ws:
        await open_session(ws, "face", output="vertices")
        await ws.send(frame(7, p))
        result = await next_result(ws)

    assert result.vertices.shape == (rig.num_vertices, 3)
    np.testing.assert_array_equal(result.vertices, rig.blend(rig.weights(p)))


@pytest.mark.parametrize("output", ["weights", "vertices"])
async def test_f16_results_are_within_f16_tolerance(served, rig, output):
    p = frame_points(rig, 2)
    expected = rig.weights(p) if output == "weights" else rig.blend(rig.weights(p))
    async with connect(served) as ws:
        await open_session(ws, "face", output=output, dtype="f16")
        await ws.send(frame(0, p))
        result = await next_result(ws)

    assert result.values.dtype == np.float16
    np.testing.assert_allclose(result.values.astype(np.float64), expected, rtol=2e-3, atol=2e-3)


async def test_aligned_session_removes_head_pose(served, rig):
    p = frame_points(rig, 3).astype(np.float64)
    angle = 0.3
    rot = np.array(
        [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    )
    moved = (p @ rot.T + [1.0, 2.0, 3.0]).astype(np.float32)
    async with connect(served) as ws:
        await open_session(ws, "face", align=True)
        await ws.send(frame(0, moved))
        result = await next_result(ws)

    np.testing.assert_allclose(
        result.weights, rig.weights(moved, align=True).astype(np.float32), atol=1e-6
    )


async def test_ping_is_answered_with_pong_and_the_servers_clock(served):
    async with connect(served) as ws:
        await open_session(ws, "face")
        sent = time.time()
        await ws.send(encode(Ping(id=42, ts=1.5)))
        pong = await recv_message(ws)
        received = time.time()

    assert isinstance(pong, Pong) and (pong.id, pong.ts) == (42, 1.5)
    assert pong.server_ts is not None and sent <= pong.server_ts <= received


async def test_calibrate_with_points_then_results_use_the_calibrated_rig(served, rig):
    neutral = frame_points(rig, 10) + np.float32(0.5)
    p = frame_points(rig, 11) + np.float32(0.5)
    async with connect(served) as ws:
        await open_session(ws, "face")
        await ws.send(encode(Calibrate(points=neutral)))
        ack = await recv_message(ws)
        await ws.send(frame(0, p))
        result = await next_result(ws)
        await ws.send(encode(Calibrate(reset=True)))
        reset = await recv_message(ws)

    assert ack == Calibrated(active=True) and reset == Calibrated(active=False)
    expected = rig.calibrated(neutral).weights(p).astype(np.float32)
    np.testing.assert_allclose(result.weights, expected, atol=1e-6)


async def test_calibrate_without_points_uses_the_next_frame(served, rig):
    neutral = frame_points(rig, 12)
    async with connect(served) as ws:
        await open_session(ws, "face")
        await ws.send(encode(Calibrate()))
        await ws.send(frame(5, neutral))
        ack = await recv_message(ws)
        result = await next_result(ws)

    assert ack == Calibrated(active=True, seq=5)
    # The captured neutral maps onto the source neutral: weights of the neutral example.
    np.testing.assert_allclose(result.weights, np.eye(rig.num_examples)[0], atol=1e-5)


async def test_calibrate_with_noise_rebases_noise_aware_and_bounded(served, rig):
    neutral = frame_points(rig, 10) + np.float32(0.5)
    p = frame_points(rig, 11) + np.float32(0.5)
    async with connect(served) as ws:
        await open_session(ws, "face")
        await ws.send(encode(Calibrate(noise=0.01)))
        await ws.send(frame(0, neutral))  # the next frame is the neutral, with that noise
        ack = await recv_message(ws)
        first = await next_result(ws)
        await ws.send(frame(1, p))
        result = await next_result(ws)

    assert ack == Calibrated(active=True, seq=0)
    np.testing.assert_allclose(first.weights, np.eye(rig.num_examples)[0], atol=1e-6)
    expected = rebase(rig, neutral, noise=0.01).weights(p).astype(np.float32)
    np.testing.assert_allclose(result.weights, expected, atol=1e-6)
    assert result.weights[1:].min() >= 0.0 and result.weights[1:].max() <= 1.0


def _blink_rig():
    """The tiny rig with its first expression named as a blink (the closure maps that one)."""
    names = ("neutral", "eyeBlinkLeft", "frown", "jaw")
    return fit(dataclasses.replace(tiny_example_set(), names=names))


async def test_calibrate_with_the_performers_closed_eye_reads_it_as_closed(served):
    served.app.state.store.put_rig("blinky", blinky := _blink_rig())
    source = tiny_example_set().source_points.astype(np.float32)
    neutral = source[0] + np.float32(0.5)  # the performer's face: another place
    # Their closed eye: most of the way to the rig's own blink, on their face.
    closed = neutral + np.float32(0.7) * (source[1] - source[0])
    async with connect(served) as ws:
        await open_session(ws, "blinky")
        await ws.send(
            encode(Calibrate(points=neutral, noise=0.01, blinks={"eyeBlinkLeft": closed}))
        )
        ack = await recv_message(ws)
        await ws.send(frame(0, closed))
        result = await next_result(ws)

    assert ack == Calibrated(active=True, seq=None)
    assert rebase(blinky, neutral, noise=0.01).weights(closed)[1] < 0.9  # part-way, plain
    assert result.weights[1] == pytest.approx(1.0, abs=1e-6)  # read as closed
    assert result.weights.sum() == pytest.approx(1.0, abs=1e-5)


async def test_calibrate_with_the_performers_own_blink_contrast_reads_through_it(served):
    served.app.state.store.put_rig("blinky", blinky := _blink_rig())
    source = tiny_example_set().source_points.astype(np.float32)
    neutral = source[0] + np.float32(0.5)
    closed = neutral + np.float32(0.7) * (source[1] - source[0])
    blinks = {"eyeBlinkLeft": closed}
    # An eye a little more than halfway closed, which the two curves read differently.
    part = neutral + np.float32(0.6) * (closed - neutral)
    async with connect(served) as ws:
        await open_session(ws, "blinky")
        await ws.send(encode(Calibrate(points=neutral, noise=0.01, blinks=blinks,
                                       blink_contrast=(0.6, 0.9))))  # fmt: skip
        ack = await recv_message(ws)
        await ws.send(frame(0, part))
        result = await next_result(ws)

    assert ack == Calibrated(active=True, seq=None)
    own = calibrate(blinky, neutral, 0.01, blinks, contrast=(0.6, 0.9)).weights(part)
    default = calibrate(blinky, neutral, 0.01, blinks).weights(part)
    assert abs(own[1] - default[1]) > 0.2  # the curves differ here
    np.testing.assert_allclose(result.weights, own.astype(np.float32), atol=1e-6)


# -- results that would not be finite (issue 13, item 3) ----------------------------------


def _huge_rig():
    """A rig whose target mesh lies beyond float16's range (65504): every f16 vertex is inf."""
    example_set = tiny_example_set()
    return fit(dataclasses.replace(example_set, target_vertices=example_set.target_vertices * 1e5))


async def test_points_in_other_units_get_points_out_of_range_and_the_session_lives(served, rig):
    millimetres = frame_points(rig, 20) * np.float32(1000.0)
    async with connect(served) as ws:
        await open_session(ws, "face", output="vertices", dtype="f16")
        await ws.send(frame(3, millimetres))
        error = await recv_error(ws)
        await ws.send(frame(4, frame_points(rig, 21)))
        result = await next_result(ws)

    assert (error.code, error.seq, error.fatal) == (ErrorCode.POINTS_OUT_OF_RANGE, 3, False)
    assert "rig's units" in error.message
    assert result.seq == 4 and np.isfinite(result.vertices.astype(np.float32)).all()


@pytest.mark.parametrize("dtype", ["f16", "f32"])
async def test_a_result_beyond_its_dtype_is_an_error_for_that_frame_only(served, dtype):
    huge = _huge_rig()
    served.app.state.store.put_rig("huge", huge)
    p = frame_points(huge, 22)
    async with connect(served) as ws:
        await open_session(ws, "huge", output="vertices", dtype=dtype)
        await ws.send(frame(0, p))
        first = await recv_message(ws)
        await ws.send(encode(Ping(id=1, ts=0.0)))
        pong = await recv_message(ws)

    assert isinstance(pong, Pong) and pong.id == 1  # the session lives
    if dtype == "f16":
        assert isinstance(first, Error)
        assert (first.code, first.seq, first.fatal) == (ErrorCode.RESULT_NOT_FINITE, 0, False)
    else:
        assert isinstance(first, Result)
        np.testing.assert_array_equal(first.vertices, huge.clone(p))


async def test_calibrate_with_an_absurd_neutral_is_refused_and_results_stay_finite(served, rig):
    absurd = np.full((rig.num_points, 3), 1e300)
    p = frame_points(rig, 23)
    async with connect(served) as ws:
        await open_session(ws, "face")
        await ws.send(encode(Calibrate(points=absurd)))
        error = await recv_error(ws)
        await ws.send(frame(0, p))
        result = await next_result(ws)

    assert (error.code, error.fatal) == (ErrorCode.CALIBRATION_FAILED, False)
    np.testing.assert_array_equal(result.weights, rig.weights(p).astype(np.float32))


async def test_calibrate_with_an_absurd_noise_is_refused_and_results_stay_finite(served, rig):
    neutral = frame_points(rig, 10)
    p = frame_points(rig, 24)
    async with connect(served) as ws:
        await open_session(ws, "face")
        await ws.send(encode(Calibrate(points=neutral, noise=1e300)))
        error = await recv_error(ws)
        await ws.send(frame(0, p))
        result = await next_result(ws)

    assert (error.code, error.fatal) == (ErrorCode.CALIBRATION_FAILED, False)
    assert "noise" in error.message
    np.testing.assert_array_equal(result.weights, rig.weights(p).astype(np.float32))


async def test_hello_on_a_rig_file_the_protocol_cannot_carry_is_refused_not_readied(served):
    # A ready naming a 300-character example would be refused by every client.
    es = tiny_example_set()
    named = fit(dataclasses.replace(es, names=("neutral", "s" * 300, "frown", "jaw")))
    named.save(served.settings.rigs_dir / "long.rig")
    async with connect(served) as ws:
        await ws.send(encode(Hello(rig="long")))
        error = await recv_error(ws)

    assert (error.code, error.fatal) == (ErrorCode.UNKNOWN_RIG, True)
    assert "cannot be streamed" in error.message


async def test_invalid_utf8_in_a_text_frame_closes_1007_without_an_error_log(served):
    reader, writer, status = await raw_websocket(served.host, served.port, "/v1/stream")
    with server_logs() as records:
        writer.write(masked_frame(0x1, b"\xff\xfe not UTF-8"))
        await writer.drain()
        code = await close_code_of(reader)
    writer.close()

    assert status.startswith("HTTP/1.1 101") and code == 1007
    assert errors_logged(records) == []


@pytest.mark.parametrize("target", ["points", "weights"])
async def test_smoothing_applies_a_one_euro_filter_clocked_by_frame_ts(served, rig, target):
    smoothing = Smoothing(min_cutoff=2.0, beta=0.5, target=target)
    frames = [(frame_points(rig, i), 0.1 * i) for i in range(4)]
    reference = OneEuroFilter(min_cutoff=2.0, beta=0.5)
    expected = []
    for p, ts in frames:
        if target == "points":
            smoothed = reference(p.astype(np.float64).reshape(-1), ts).reshape(p.shape)
            expected.append(rig.weights(smoothed))
        else:
            expected.append(reference(rig.weights(p), ts))
    async with connect(served) as ws:
        await open_session(ws, "face", smoothing=smoothing)
        results = []
        for seq, (p, ts) in enumerate(frames):
            await ws.send(frame(seq, p, ts=ts))
            results.append(await next_result(ws))

    for result, want in zip(results, expected, strict=True):
        np.testing.assert_allclose(result.weights, want.astype(np.float32), atol=1e-6)
    assert not np.allclose(results[-1].weights, rig.weights(frames[-1][0]), atol=1e-4)


@pytest.mark.parametrize("given", [None, 0.02])
async def test_kalman_smoothing_filters_the_points_with_the_rigs_noise(served, given):
    noisy_rig = fit(tiny_example_set(), noise=0.05)  # the rig's noise unless one is given
    served.app.state.store.put_rig("noisy", noisy_rig)
    smoothing = Smoothing(filter="kalman", acceleration=300.0, noise=given)
    sigma = 0.05 if given is None else given
    frames = [(frame_points(noisy_rig, i), 0.1 * i) for i in range(4)]
    reference = KalmanFilter(noise=sigma, acceleration=300.0 * sigma)
    expected = [
        noisy_rig.weights(reference(p.astype(np.float64).reshape(-1), ts).reshape(p.shape))
        for p, ts in frames
    ]
    async with connect(served) as ws:
        ready = await open_session(ws, "noisy", smoothing=smoothing)
        results = []
        for seq, (p, ts) in enumerate(frames):
            await ws.send(frame(seq, p, ts=ts))
            results.append(await next_result(ws))

    for result, want in zip(results, expected, strict=True):
        np.testing.assert_allclose(result.weights, want.astype(np.float32), atol=1e-6)
    assert not np.allclose(results[-1].weights, noisy_rig.weights(frames[-1][0]), atol=1e-4)
    assert ready.smoothing == "kalman"


async def _smoothed_weights(served, rig_id: str, frames, smoothing: Smoothing):
    """The ready and the results of ``frames`` (points, ts) sent with ``smoothing``."""
    async with connect(served) as ws:
        ready = await open_session(ws, rig_id, smoothing=smoothing)
        results = []
        for seq, (p, ts) in enumerate(frames):
            await ws.send(frame(seq, p, ts=ts))
            results.append(await next_result(ws))
    return ready, [r.weights for r in results]


def _offline_point_filter(rig, frames, point_filter):
    """The weights of ``frames`` whose points went through ``point_filter`` first."""
    return [
        rig.weights(point_filter(p.astype(np.float64).reshape(-1), ts).reshape(p.shape))
        for p, ts in frames
    ]


async def test_auto_smoothing_on_a_rig_fitted_with_noise_runs_the_kalman_filter(served):
    noisy_rig = fit(tiny_example_set(), noise=0.05)
    served.app.state.store.put_rig("noisy", noisy_rig)
    frames = [(frame_points(noisy_rig, i), 0.1 * i) for i in range(4)]
    kalman = KalmanFilter(noise=0.05, acceleration=KALMAN_ACCELERATION * 0.05)
    expected = _offline_point_filter(noisy_rig, frames, kalman)

    ready, weights = await _smoothed_weights(served, "noisy", frames, Smoothing())

    assert ready.smoothing == "kalman"
    for got, want in zip(weights, expected, strict=True):
        np.testing.assert_allclose(got, want.astype(np.float32), atol=1e-6)


@pytest.mark.parametrize(
    ("smoothing", "offline", "runs"),
    [
        # A noise given makes the Kalman filter possible on a rig fitted exactly.
        (
            Smoothing(noise=0.02, acceleration=300.0),
            lambda: KalmanFilter(noise=0.02, acceleration=6.0),
            "kalman",
        ),
        (Smoothing(min_cutoff=2.0, beta=0.5), lambda: OneEuroFilter(2.0, 0.5), "one-euro"),
    ],
    ids=["noise-given", "no-noise"],
)
async def test_auto_smoothing_on_a_rig_fitted_exactly(served, rig, smoothing, offline, runs):
    frames = [(frame_points(rig, i), 0.1 * i) for i in range(4)]
    expected = _offline_point_filter(rig, frames, offline())

    ready, weights = await _smoothed_weights(served, "face", frames, smoothing)

    assert ready.smoothing == runs
    for got, want in zip(weights, expected, strict=True):
        np.testing.assert_allclose(got, want.astype(np.float32), atol=1e-6)


async def test_auto_smoothing_on_a_rig_fitted_exactly_takes_a_calibrates_noise(served, rig):
    # No noise at the hello (an exact rig, no smoothing.noise): the one-euro filter; a
    # calibrate with a noise makes it the Kalman filter on the re-base's σ from the
    # neutral's frame on (the calibrate without points takes the next frame, which is
    # filtered too); a calibrate again on the same neutral and noise (as with the closed
    # eyes) goes on with the same filter, and a reset keeps it (PROTOCOL.md §5.1.1, §5.2.5).
    frames = [(frame_points(rig, i) + np.float32(0.5), 0.1 * i) for i in range(6)]
    neutral = frames[0][0]
    rebased = rebase(rig, neutral, noise=0.02)
    sigma = rebased.fit_report["rebase"]["noise"]  # the re-base's σ: the Kalman's
    kalman = KalmanFilter(noise=sigma, acceleration=KALMAN_ACCELERATION * sigma)
    expected = _offline_point_filter(rebased, frames, kalman)
    async with connect(served) as ws:
        ready = await open_session(ws, "face", smoothing=Smoothing())
        await ws.send(encode(Calibrate(noise=0.02)))
        weights, acks = [], []
        for seq, (p, ts) in enumerate(frames):
            if seq == 3:
                await ws.send(encode(Calibrate(points=neutral, noise=0.02)))
                acks.append(await recv_message(ws))
            await ws.send(frame(seq, p, ts=ts))
            if seq == 0:
                acks.append(await recv_message(ws))
            weights.append((await next_result(ws)).weights)
        await ws.send(encode(Calibrate(reset=True)))
        reset = await recv_message(ws)

    assert ready.smoothing == "one-euro"
    assert acks == [Calibrated(active=True, seq=0, smoothing="kalman"),
                    Calibrated(active=True, smoothing="kalman")]  # fmt: skip
    assert reset == Calibrated(active=False, smoothing="kalman")
    for got, want in zip(weights, expected, strict=True):
        np.testing.assert_allclose(got, want.astype(np.float32), atol=1e-6)


@pytest.mark.parametrize(
    "smoothing",
    [Smoothing(filter="one-euro", beta=0.5), Smoothing(beta=0.5, target="weights")],
    ids=["named-one-euro", "auto-weights"],
)
async def test_one_euro_runs_on_a_noise_rig_when_named_or_smoothing_weights(served, smoothing):
    noisy_rig = fit(tiny_example_set(), noise=0.05)
    served.app.state.store.put_rig("noisy", noisy_rig)
    frames = [(frame_points(noisy_rig, i), 0.1 * i) for i in range(4)]
    reference = OneEuroFilter(min_cutoff=2.0, beta=0.5)
    if smoothing.target == "points":
        expected = _offline_point_filter(noisy_rig, frames, reference)
    else:
        expected = [reference(noisy_rig.weights(p), ts) for p, ts in frames]

    ready, weights = await _smoothed_weights(served, "noisy", frames, smoothing)

    assert ready.smoothing == "one-euro"
    for got, want in zip(weights, expected, strict=True):
        np.testing.assert_allclose(got, want.astype(np.float32), atol=1e-6)


async def test_a_session_without_smoothing_says_no_filter(served):
    async with connect(served) as ws:
        ready = await open_session(ws, "face")

    assert ready.smoothing is None


async def test_kalman_smoothing_on_a_rig_fitted_without_noise_needs_a_noise(served):
    async with connect(served) as ws:  # "face" is fitted exactly
        await ws.send(encode(Hello(rig="face", smoothing=Smoothing(filter="kalman"))))
        error = await recv_error(ws)

    assert (error.code, error.fatal) == (ErrorCode.INVALID_FIELD, True)
    assert "smoothing.noise" in error.message


# -- bad input: each gets its code, and the server keeps serving ---------------------------


def _raw(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _bad_points(rig, **change) -> bytes:
    p = frame_points(rig, 0)
    wire = {"dtype": "f32", "shape": list(p.shape), "data": p.tobytes()}
    wire.update(change)
    return _raw({"v": 1, "type": "frame", "seq": 9, "ts": 0.0, "points": wire})


# name -> (bytes or str to send after a successful hello, expected code)
def _after_hello_cases(rig) -> dict:
    k = rig.num_points
    nan = frame_points(rig, 0)
    nan[0, 0] = np.nan
    inf = frame_points(rig, 0)
    inf[1, 2] = np.inf
    return {
        "malformed-msgpack": (b"\xc1\xc1\xc1", ErrorCode.MALFORMED),
        "binary-garbage": (bytes(range(256)) * 4, ErrorCode.MALFORMED),
        "text-frame": ("hello", ErrorCode.TEXT_NOT_SUPPORTED),
        "not-a-map": (_raw([1, 2, 3]), ErrorCode.INVALID_MESSAGE),
        "missing-type": (_raw({"v": 1, "seq": 1}), ErrorCode.INVALID_MESSAGE),
        "unknown-type": (_raw({"v": 1, "type": "explode"}), ErrorCode.UNKNOWN_TYPE),
        "missing-field": (_raw({"v": 1, "type": "frame", "seq": 1}), ErrorCode.INVALID_FIELD),
        "wrong-k": (frame(1, np.zeros((k + 1, 3), np.float32)), ErrorCode.WRONG_POINT_COUNT),
        "wrong-dtype": (_bad_points(rig, dtype="i32"), ErrorCode.INVALID_ARRAY),
        "short-data": (_bad_points(rig, data=b"\x00" * 7), ErrorCode.INVALID_ARRAY),
        "nan": (frame(1, nan), ErrorCode.NON_FINITE),
        "inf": (frame(1, inf), ErrorCode.NON_FINITE),
        "oversized": (
            _raw({"v": 1, "type": "ping", "pad": bytes(70_000)}),
            ErrorCode.MESSAGE_TOO_LARGE,
        ),
        "second-hello": (encode(Hello(rig="face")), ErrorCode.WRONG_STATE),
    }


CASES = [
    "malformed-msgpack",
    "binary-garbage",
    "text-frame",
    "not-a-map",
    "missing-type",
    "unknown-type",
    "missing-field",
    "wrong-k",
    "wrong-dtype",
    "short-data",
    "nan",
    "inf",
    "oversized",
    "second-hello",
]


async def test_each_bad_message_after_hello_gets_its_code_and_the_session_goes_on(
    tmp_path, rig, ws_impl
):

    settings = Settings(rigs_dir=tmp_path / "rigs", max_message_bytes=65536)
    cases = _after_hello_cases(rig)
    p = frame_points(rig, 4)
    got = {}
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        async with connect(server) as ws:
            await open_session(ws, "face")
            for name in CASES:
                payload, _ = cases[name]
                await ws.send(payload)
                error = await recv_error(ws)
                got[name] = (error.code, error.fatal)
            await ws.send(frame(99, p))
            result = await next_result(ws)

    assert got == {name: (cases[name][1], False) for name in CASES}
    assert result.seq == 99


# name -> (messages to send on a fresh connection, expected code); all fatal.
FATAL_CASES = {
    "frame-before-hello": ([frame(0, np.zeros((5, 3), np.float32))], ErrorCode.WRONG_STATE),
    "garbage-before-hello": ([b"\x00\x01garbage"], ErrorCode.MALFORMED),
    "text-before-hello": (["hi"], ErrorCode.TEXT_NOT_SUPPORTED),
    "unknown-version": (
        [_raw({"v": 99, "type": "hello", "rig": "face"})],
        ErrorCode.UNSUPPORTED_VERSION,
    ),
    "unknown-rig": ([encode(Hello(rig="nobody"))], ErrorCode.UNKNOWN_RIG),
    "invalid-rig-id": ([encode(Hello(rig="../../etc/passwd"))], ErrorCode.UNKNOWN_RIG),
    "scale-without-align": (
        [_raw({"v": 1, "type": "hello", "rig": "face", "options": {"scale": True}})],
        ErrorCode.INVALID_FIELD,
    ),
}


@pytest.mark.parametrize("case", list(FATAL_CASES))
async def test_fatal_error_closes_that_session_and_others_are_served(served, rig, case):
    messages, code = FATAL_CASES[case]
    p = frame_points(rig, 0)
    async with connect(served) as healthy:
        await open_session(healthy, "face")
        async with connect(served) as bad:
            for m in messages:
                await bad.send(m)
            error = await recv_error(bad)
            with pytest.raises(websockets.ConnectionClosed):
                await bad.recv()
        await healthy.send(frame(1, p))
        result = await next_result(healthy)

    assert (error.code, error.fatal) == (code, True)
    assert bad.close_code in (1003, 1008)
    assert result.seq == 1


async def test_message_far_over_the_limit_is_cut_by_the_socket_with_1009(tmp_path, rig, ws_impl):

    settings = Settings(rigs_dir=tmp_path / "rigs", max_message_bytes=4096)
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        async with connect(server) as ws:
            await open_session(ws, "face")
            # About 5x what uvicorn lets through (2 x 4096 + 64 kB); small enough to fit
            # the loopback socket buffers, so the send is not cut short by the close.
            with contextlib.suppress(OSError, websockets.ConnectionClosed):
                await ws.send(bytes(400_000))
            with pytest.raises(websockets.ConnectionClosed):
                while True:
                    await ws.recv()

    assert ws.close_code == 1009


# -- flow control ---------------------------------------------------------------------------


async def test_flood_of_frames_keeps_only_the_newest_and_counts_drops(tmp_path, ws_impl):
    # Large enough to be cloned in the pool (blend_seconds over INLINE_MAX_SECONDS), so
    # the flood outruns the clones whatever the machine's load: frames cloned inline are
    # all answered while the reader keeps up, and whether it does is a matter of timing.
    big = tiny_rig(num_vertices=60_000)
    assert blend_seconds(big.num_vertices, big.num_examples) > INLINE_MAX_SECONDS
    settings = Settings(rigs_dir=tmp_path / "rigs", max_fps=1e6, rate_burst=100_000)
    n = 300
    p = frame_points(big, 0)
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("big", big)
        async with connect(server) as ws:
            await open_session(ws, "big", output="vertices")
            await asyncio.gather(*(ws.send(frame(seq, p)) for seq in range(n)))
            results = []
            while not results or results[-1].seq != n - 1:
                results.append(await next_result(ws))

    seqs = [r.seq for r in results]
    assert seqs == sorted(seqs)  # newest-only never reorders
    assert len(results) < n  # some were superseded
    assert len(results) + results[-1].dropped == n  # every frame is a result or a drop


async def test_pipelined_frames_reaching_an_idle_session_are_all_processed(served, rig):
    p = frame_points(rig, 0)
    seqs = []
    async with connect(served) as ws:
        await open_session(ws, "face")
        for seq in range(0, 40, 2):
            # Two frames in one burst (usually one TCP segment), then both answers.
            await asyncio.gather(ws.send(frame(seq, p)), ws.send(frame(seq + 1, p)))
            seqs += [(await next_result(ws)).seq, (await next_result(ws)).seq]

    assert seqs == list(range(40))


@pytest.mark.parametrize("where", ["inline", "thread"])
async def test_client_with_two_frames_in_flight_never_loses_one(
    tmp_path, ws_impl, monkeypatch, where
):
    from facecast.server.stream import session as session_module

    # All blends on the loop, or all in the clone pool, whatever the rig's size.
    limit = 1e9 if where == "inline" else 0.0
    monkeypatch.setattr(session_module, "INLINE_MAX_SECONDS", limit)
    # 120 kB results: past the transport's high-water mark, so sends do wait for the
    # client to read, the window in which a third frame used to replace the second.
    rig = tiny_rig(num_vertices=10_000)
    settings = Settings(rigs_dir=tmp_path / "rigs", max_fps=1e6, rate_burst=100_000)
    n = 60
    p = frame_points(rig, 0)
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("mid", rig)
        async with connect(server, max_size=None) as ws:
            await open_session(ws, "mid", output="vertices")
            await ws.send(frame(0, p))
            await ws.send(frame(1, p))
            results = []
            for seq in range(2, n + 2):
                results.append(await next_result(ws))
                if seq < n:
                    await ws.send(frame(seq, p))  # one more each time one comes back

    assert [r.seq for r in results] == list(range(n))
    assert results[-1].dropped == 0
    expected = rig.blend(rig.weights(p))
    np.testing.assert_allclose(results[-1].vertices, expected, rtol=1e-5, atol=1e-5)


async def test_idle_timeout_counts_from_the_last_message(tmp_path, rig, ws_impl):
    settings = Settings(rigs_dir=tmp_path / "rigs", idle_timeout=0.4)
    p = frame_points(rig, 0)
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        async with connect(server) as ws:
            sent = [time.monotonic()]  # when each message went out: the hello, the frames
            await open_session(ws, "face")
            for seq in range(8):  # 8 frames 0.1 s apart: 0.8 s, twice the timeout
                sent.append(time.monotonic())
                with contextlib.suppress(websockets.ConnectionClosed):
                    await ws.send(frame(seq, p))  # the server may have ended it meanwhile
                message = await recv_message(ws)
                if isinstance(message, Error):
                    answered = len(sent) - 2  # the frame before this one, or the hello
                    break
                await asyncio.sleep(0.1)  # pacing the client, not waiting for the server
            else:
                answered = len(sent) - 1
                message = await recv_error(ws, timeout=5)
            came = time.monotonic()

    assert (message.code, message.fatal) == (ErrorCode.IDLE_TIMEOUT, True)
    # The server had the answered message by the time it answered, so the timeout can
    # only come idle_timeout after it was sent. (Under CPU load a frame can come back so
    # late that the gap to the next one really is longer: then it ends there, rightly.)
    # A timer not re-armed by frames would fire 0.4 s after the hello, 0.1 s after a frame.
    assert came - sent[answered] >= settings.idle_timeout


async def test_frames_over_the_rate_are_dropped_with_one_rate_limited_error(tmp_path, rig, ws_impl):

    settings = Settings(rigs_dir=tmp_path / "rigs", max_fps=5, rate_burst=3)
    p = frame_points(rig, 0)
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        async with connect(server) as ws:
            await open_session(ws, "face")
            started = time.monotonic()
            for seq in range(20):
                await ws.send(frame(seq, p))
            await ws.send(encode(Ping(id=1, ts=0.0)))
            messages = []
            while not isinstance(messages[-1] if messages else None, Pong):
                messages.append(await recv_message(ws))
            took = time.monotonic() - started  # the server read the burst within this
            session = next(iter(server.app.state.sessions))

    errors = [m for m in messages if not isinstance(m, Result | Pong)]
    # One error per ERROR_INTERVAL (1 s): a second only if reading the burst took longer.
    assert {(e.code, e.fatal) for e in errors} == {(ErrorCode.RATE_LIMITED, False)}
    assert len(errors) <= 1 + int(took)
    # The bucket refills 5 tokens a second while the server reads the burst.
    assert session.counters.dropped_rate >= 20 - 3 - 1 - int(5 * took)


async def test_client_that_never_reads_is_bounded_and_does_not_slow_others(tmp_path, ws_impl):

    big = tiny_rig(num_vertices=50_000)  # 600 kB per f32 result: socket buffers fill fast
    settings = Settings(rigs_dir=tmp_path / "rigs", max_fps=1e6, rate_burst=100_000)
    p = frame_points(big, 0)
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("big", big)
        server.app.state.store.put_rig("face", tiny_rig())
        # max_queue=1: the client library stops reading the socket once one message waits.
        async with connect(server, max_queue=1, max_size=None, close_timeout=0.5) as stuck:
            await open_session(stuck, "big", output="vertices")
            sessions = list(server.app.state.sessions)
            stuck_session = sessions[0]
            async with connect(server) as other:
                await open_session(other, "face")
                latencies = []
                for seq in range(400):
                    await stuck.send(frame(seq, p))
                    if seq % 4 == 0:
                        start = time.perf_counter()
                        await other.send(frame(seq, frame_points(big, 0)[:5]))
                        await next_result(other)
                        latencies.append(time.perf_counter() - start)
            c = stuck_session.counters
            await wait_until(lambda: c.frames_in == 400)  # the last sends may still be in flight
            snapshot = (c.frames_in, c.results_out, c.dropped, stuck_session.pending)

    frames_in, results_out, dropped, pending = snapshot
    assert frames_in == 400
    assert results_out < 50  # the socket stopped taking results ...
    # ... and nothing piles up: one result in the blocked send, one frame held for the
    # writer after it, one in the mailbox.
    assert frames_in - results_out - dropped <= 3
    assert pending <= 1
    assert statistics.median(latencies) < 0.05, latencies


async def test_client_that_never_reads_an_inline_session_is_bounded(tmp_path, ws_impl):
    from facecast.server.stream import session as session_module

    mid = tiny_rig(num_vertices=20_000)  # 240 kB results, cloned on the loop
    settings = Settings(rigs_dir=tmp_path / "rigs", max_fps=1e6, rate_burst=100_000)
    p = frame_points(mid, 0)
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("mid", mid)
        async with connect(server, max_queue=1, max_size=None, close_timeout=0.5) as stuck:
            await open_session(stuck, "mid", output="vertices")
            session = next(iter(server.app.state.sessions))
            for seq in range(300):
                await stuck.send(frame(seq, p))
            c = session.counters
            await wait_until(lambda: c.frames_in == 300)
            snapshot = (c.results_out, c.dropped, *session.queued_results)

    results_out, dropped, outbox, outbox_bytes = snapshot
    assert results_out < 100 and dropped > 100  # the socket stopped taking results
    # Waiting results are bounded by bytes (one past the bound at most), frames by two.
    assert outbox_bytes <= session_module._MAX_OUTBOX_BYTES + 250_000
    assert 300 - results_out - dropped <= outbox + 3


async def test_idle_session_gets_idle_timeout_then_close(tmp_path, rig, ws_impl):

    settings = Settings(rigs_dir=tmp_path / "rigs", idle_timeout=0.3)
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        async with connect(server) as ws:
            # The idle period starts at the client's last message, the hello, not at the
            # ready: the server may take a while (a rig load under CPU load) to answer.
            started = time.monotonic()
            await open_session(ws, "face")
            error = await recv_error(ws, timeout=5)
            waited = time.monotonic() - started
            with pytest.raises(websockets.ConnectionClosed):
                await ws.recv()

    assert (error.code, error.fatal) == (ErrorCode.IDLE_TIMEOUT, True)
    # Never before the timeout (the server saw the hello after it was sent); the upper
    # bound only tells "fired at the timeout" from "never fired", well below recv's 5 s.
    assert settings.idle_timeout <= waited < 3
    assert ws.close_code == 1008


async def test_connection_over_the_limit_gets_overloaded(tmp_path, rig, ws_impl):

    settings = Settings(rigs_dir=tmp_path / "rigs", max_connections=1)
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        async with connect(server) as first:
            await open_session(first, "face")
            async with connect(server) as second:
                await second.send(encode(Hello(rig="face")))
                error = await recv_error(second)
                with pytest.raises(websockets.ConnectionClosed):
                    await second.recv()

    assert (error.code, error.fatal) == (ErrorCode.OVERLOADED, True)
    assert second.close_code == 1013


async def test_shutdown_closes_open_sessions_with_1001(settings, rig, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        server.app.state.store.put_rig("face", rig)
        ws = await connect(server)
        await open_session(ws, "face")
        server.server.should_exit = True
        with pytest.raises(websockets.ConnectionClosed):
            while True:
                await asyncio.wait_for(ws.recv(), 10)

    assert ws.close_code == 1001


async def test_metrics_count_frames_results_and_errors(served, rig):
    import httpx

    async with connect(served) as ws:
        await open_session(ws, "face")
        await ws.send(frame(0, frame_points(rig, 0)))
        await next_result(ws)
        await ws.send(b"\xc1")
        await recv_error(ws)
        async with httpx.AsyncClient(base_url=served.base_url) as http:
            text = (await http.get("/metrics")).text

    assert "facecast_connections 1.0" in text
    assert "facecast_frames_in_total 1.0" in text
    assert "facecast_frames_out_total 1.0" in text
    assert 'facecast_errors_total{code="MALFORMED"} 1.0' in text
    assert "facecast_processing_seconds_count 1.0" in text
