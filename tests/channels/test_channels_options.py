"""Publisher options apply channel-wide; a watcher may only ping; ChannelFrame round-trips."""

from __future__ import annotations

import dataclasses

import httpx
import numpy as np
import pytest
from hypothesis import given
from hypothesis import settings as hsettings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from facecast.client.channel import FramePublisher, channel_url
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
    decode_server,
    encode,
)
from facecast.rig import fit
from facecast.rig.rebase import calibrate as calibrate_rig
from facecast.rig.rebase import rebase
from facecast.rig.sources.layouts import load_layout
from facecast.server.channels.fanout import ChannelFrame, key_state
from facecast.server.settings import Settings
from facecast.server.testing import run_server

from ._helpers import RIG_IDS, Publisher, Watcher, points, tiny_examples, wait_for, write_rigs

pytestmark = pytest.mark.anyio


async def test_calibration_rebases_every_watched_rig(settings, rigs, ws_impl):
    neutral = points(rigs["alpha"], 99)
    pts = points(rigs["alpha"], 5)
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "gamma")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await publisher.ws.send(publisher.protocol.send(Calibrate(points=neutral)))
        while not isinstance(await publisher.queue.get(), Calibrated):
            pass
        await publisher.send(0, pts)
        result = await watcher.result_with_seq(0)

    expected = rigs["gamma"].calibrated(neutral).weights(pts).astype(np.float32)
    np.testing.assert_array_equal(result.weights, expected)


async def test_calibration_with_noise_rebases_every_watched_rig_bounded(settings, rigs, ws_impl):
    # The page's calibrate carries the measured noise (PROTOCOL.md §5.1.3): every watched
    # rig is then re-based noise-aware, its weights bounded to [0, 1], as rig.rebase does.
    neutral = points(rigs["alpha"], 99)
    pts = np.stack([points(rigs["alpha"], seed) for seed in range(6)])
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "gamma")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await publisher.ws.send(publisher.protocol.send(Calibrate(points=neutral, noise=0.01)))
        while not isinstance(await publisher.queue.get(), Calibrated):
            pass
        results = []
        for seq, frame in enumerate(pts):
            await publisher.send(seq, frame)
            results.append((await watcher.result_with_seq(seq)).weights)

    received = np.stack(results)
    expected = rebase(rigs["gamma"], neutral, noise=0.01).weights(pts).astype(np.float32)
    exact = rigs["gamma"].calibrated(neutral).weights(pts)
    np.testing.assert_array_equal(received, expected)
    assert received[:, 1:].min() >= 0.0 and received[:, 1:].max() <= 1.0
    assert exact[:, 1:].min() < 0.0 or exact[:, 1:].max() > 1.0  # what it was without


async def test_the_publishers_closed_eye_is_read_as_closed_on_every_watched_rig(
    tmp_path, rigs, ws_impl
):
    # The page sends the performer's captured closed eyes with the neutral (§5.1.3
    # blinks): every watched rig that has the blink reads them as closed, as
    # rig.rebase.calibrate does; a rig without it is re-based as before.
    examples = tiny_examples(7, names=("neutral", "eyeBlinkLeft", "frown", "jaw"))
    blinky = fit(examples)
    write_rigs(tmp_path / "rigs", {"alpha": rigs["alpha"], "blinky": blinky})
    source = examples.source_points.astype(np.float32)
    neutral = source[0] + np.float32(0.5)  # the performer's face: another place
    # The performer's closed eye: most of the way to the blink's source example, on their face.
    closed = neutral + np.float32(0.7) * (source[1] - source[0])
    calibrate = Calibrate(points=neutral, noise=0.01, blinks={"eyeBlinkLeft": closed})
    settings = Settings(rigs_dir=tmp_path / "rigs", face_lost_after=30.0)
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "blinky")
        other = await Watcher.open(server.ws_url, "stage", "alpha")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await publisher.ws.send(publisher.protocol.send(calibrate))
        while not isinstance(await publisher.queue.get(), Calibrated):
            pass
        await publisher.send(0, closed)
        result = await watcher.result_with_seq(0)
        unblinking = await other.result_with_seq(0)

    read_closed = calibrate_rig(blinky, neutral, 0.01, {"eyeBlinkLeft": closed})
    np.testing.assert_array_equal(result.weights, read_closed.weights(closed).astype(np.float32))
    assert result.weights[1] == pytest.approx(1.0, abs=1e-6)
    assert rebase(blinky, neutral, noise=0.01).weights(closed)[1] < 0.9  # what it was without
    expected = rebase(rigs["alpha"], neutral, noise=0.01).weights(closed).astype(np.float32)
    np.testing.assert_array_equal(unblinking.weights, expected)


def test_a_channel_frame_carries_the_neutrals_closed_eyes_across_processes():
    closed = np.arange(6, dtype=np.float32).reshape(2, 3)
    frame = ChannelFrame(seq=1, ts=0.5, points=closed, neutral=closed + 1, neutral_noise=0.01,
                         neutral_blinks={"eyeBlinkRight": closed}, neutral_id="n1")  # fmt: skip
    back = ChannelFrame.from_bytes(frame.to_bytes(), max_points=8)
    assert list(back.neutral_blinks) == ["eyeBlinkRight"]
    np.testing.assert_array_equal(back.neutral_blinks["eyeBlinkRight"], closed)
    assert (
        ChannelFrame.from_bytes(
            ChannelFrame(seq=1, ts=0.5, points=closed).to_bytes(), max_points=8
        ).neutral_blinks
        is None
    )


async def test_a_frame_publishers_calibrate_rebases_the_channel_before_its_next_frame(
    settings, rigs, ws_impl
):
    # FramePublisher.calibrate (what 'facecast perform' sends after the held neutral).
    neutral = points(rigs["alpha"], 99)
    pts = points(rigs["alpha"], 5)
    results = []
    async with run_server(settings, ws=ws_impl) as server:
        url = channel_url(server.base_url, "stage", "publish")
        async with FramePublisher(url, Hello(rig="alpha"), on_result=results.append) as pub:
            await pub.calibrate(neutral, 0.01)
            await pub.send(pts, 0.0)
            assert await pub.drain(10.0)

    expected = rebase(rigs["alpha"], neutral, noise=0.01).weights(pts).astype(np.float32)
    np.testing.assert_array_equal(results[-1].weights, expected)


async def test_a_frame_publishers_calibrate_carries_the_closed_eyes(tmp_path, rigs, ws_impl):
    # FramePublisher.calibrate(..., blinks=...): the library's way to send them (§5.1.3).
    examples = tiny_examples(7, names=("neutral", "eyeBlinkLeft", "frown", "jaw"))
    write_rigs(tmp_path / "rigs", {"blinky": fit(examples)})
    source = examples.source_points.astype(np.float32)
    neutral = source[0] + np.float32(0.5)
    closed = neutral + np.float32(0.7) * (source[1] - source[0])
    results = []
    settings = Settings(rigs_dir=tmp_path / "rigs", face_lost_after=30.0)
    async with run_server(settings, ws=ws_impl) as server:
        url = channel_url(server.base_url, "stage", "publish")
        async with FramePublisher(url, Hello(rig="blinky"), on_result=results.append) as pub:
            await pub.calibrate(neutral, 0.01, blinks={"eyeBlinkLeft": closed})
            await pub.send(closed, 0.0)
            assert await pub.drain(10.0)

    assert results[-1].weights[1] == pytest.approx(1.0, abs=1e-6)


async def test_a_frame_publishers_own_blink_contrast_reaches_every_watched_rig(
    tmp_path, rigs, ws_impl
):
    # FramePublisher.calibrate(..., blink_contrast=...) ('facecast perform --blink-contrast'):
    # the channel's keys re-base through the performer's own curve (§5.1.3 blink_contrast).
    examples = tiny_examples(7, names=("neutral", "eyeBlinkLeft", "frown", "jaw"))
    blinky = fit(examples)
    write_rigs(tmp_path / "rigs", {"blinky": blinky})
    source = examples.source_points.astype(np.float32)
    neutral = source[0] + np.float32(0.5)
    closed = neutral + np.float32(0.7) * (source[1] - source[0])
    part = neutral + np.float32(0.6) * (closed - neutral)  # read apart by the two curves
    blinks = {"eyeBlinkLeft": closed}
    settings = Settings(rigs_dir=tmp_path / "rigs", face_lost_after=30.0)
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "blinky")
        url = channel_url(server.base_url, "stage", "publish")
        async with FramePublisher(url, Hello(rig="blinky")) as pub:
            await pub.calibrate(neutral, 0.01, blinks=blinks, blink_contrast=(0.6, 0.9))
            await pub.send(part, 0.0)
            result = await watcher.result_with_seq(0)

    own = calibrate_rig(blinky, neutral, 0.01, blinks, (0.6, 0.9)).weights(part)
    default = calibrate_rig(blinky, neutral, 0.01, blinks).weights(part)
    assert abs(own[1] - default[1]) > 0.2
    np.testing.assert_array_equal(result.weights, own.astype(np.float32))


def test_a_channel_frame_carries_the_blink_contrast_and_refuses_a_bad_one():
    pts = np.zeros((2, 3), np.float32)
    frame = ChannelFrame(seq=1, ts=0.5, points=pts, neutral=pts, neutral_noise=0.01,
                         neutral_blinks={"eyeBlinkLeft": pts}, neutral_contrast=(0.6, 0.9),
                         neutral_id="n1")  # fmt: skip
    assert ChannelFrame.from_bytes(frame.to_bytes(), max_points=8).neutral_contrast == (0.6, 0.9)
    bad = dataclasses.replace(frame, neutral_contrast=(0.9, 0.6)).to_bytes()
    with pytest.raises(ValueError, match="blink contrast"):
        ChannelFrame.from_bytes(bad, max_points=8)


async def test_a_frame_publisher_closed_leaves_its_channel_at_once(settings, rigs, ws_impl):
    # close() closes the socket itself: the server sees the publisher leave then, not when
    # its connection times out (facecast publish/record waited ~10 s for it).
    async with (
        run_server(settings, ws=ws_impl) as server,
        httpx.AsyncClient(base_url=server.base_url) as http,
    ):
        url = channel_url(server.base_url, "stage", "publish")
        publisher = await FramePublisher(url, Hello(rig="alpha")).start()
        await publisher.send(points(rigs["alpha"], 1), 0.0)
        assert await publisher.drain(10.0)
        await publisher.close()

        async def left() -> bool:
            response = await http.get("/v1/channels/stage")
            return response.status_code == 404 or not response.json()["publisher"]

        await wait_for(left, timeout=3.0, what="the closed publisher to leave the channel")


async def test_align_applies_to_every_watched_rig(settings, rigs, ws_impl):
    pts = points(rigs["alpha"], 8)
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "beta")
        publisher = await Publisher.open(server.ws_url, "stage", "alpha", align=True)
        await publisher.send(0, pts)
        result = await watcher.result_with_seq(0)

    expected = rigs["beta"].weights(pts, align=True).astype(np.float32)
    np.testing.assert_array_equal(result.weights, expected)


async def test_align_scale_leaves_the_stores_cached_rigs_unchanged(settings, rigs, ws_impl):
    # Each key removes scale on a rig of its own: the store's cached rig, which every other
    # key and session shares, keeps align_scale off.
    pts = points(rigs["alpha"], 8) * 1.3
    async with run_server(settings, ws=ws_impl) as server:
        store = server.app.state.store
        cached = store.get("beta")
        assert not cached.align_scale
        watcher = await Watcher.open(server.ws_url, "stage", "beta")
        publisher = await Publisher.open(
            server.ws_url, "stage", "alpha", align=True, align_scale=True
        )
        await publisher.send(0, pts)
        result = await watcher.result_with_seq(0)
        after = store.get("beta"), store.get("alpha")

    assert after[0] is cached
    assert not after[0].align_scale and not after[1].align_scale
    expected = rigs["beta"].with_align_scale(True).weights(pts, align=True).astype(np.float32)
    np.testing.assert_array_equal(result.weights, expected)
    unscaled = rigs["beta"].weights(pts, align=True).astype(np.float32)
    assert not np.array_equal(result.weights, unscaled)


async def test_a_watcher_may_ping_but_not_send_frames(settings, rigs, ws_impl):
    async with run_server(settings, ws=ws_impl) as server:
        watcher = await Watcher.open(server.ws_url, "stage", "beta")
        await watcher.ws.send(watcher.protocol.send(Ping(id=4, ts=1.5)))
        pong = await watcher.next(Pong)
        frame = Frame(seq=1, ts=0.0, points=points(rigs["alpha"], 0))
        await watcher.ws.send(encode(frame))
        error = await watcher.next(Error)
        publisher = await Publisher.open(server.ws_url, "stage", "alpha")
        await publisher.send(2, points(rigs["alpha"], 2))
        still = await watcher.result_with_seq(2)

    assert (pong.id, pong.ts) == (4, 1.5)
    assert error.code == ErrorCode.WRONG_STATE and not error.fatal
    assert isinstance(still, Result)


@hsettings(max_examples=60, deadline=None)
@given(
    seq=st.integers(0, 2**63),
    ts=st.floats(allow_nan=False, allow_infinity=False),
    pts=arrays(
        np.float32,
        st.tuples(st.integers(1, 8), st.just(3)),
        elements=st.floats(-1e6, 1e6, width=32),
    ),
    align=st.booleans(),
    with_neutral=st.booleans(),
    smoothing=st.none()
    | st.builds(
        Smoothing, min_cutoff=st.floats(0.01, 10), beta=st.floats(0, 5), target=st.just("weights")
    ),
)
def test_channel_frames_cross_processes_unchanged(seq, ts, pts, align, with_neutral, smoothing):
    frame = ChannelFrame(seq=seq, ts=ts, points=pts, align=align, smoothing=smoothing,
                         neutral=pts + 1 if with_neutral else None,
                         neutral_noise=0.0125 if with_neutral else None,
                         neutral_id="n1" if with_neutral else "")  # fmt: skip

    back = ChannelFrame.from_bytes(frame.to_bytes(), max_points=4096)

    assert (back.seq, back.ts, back.align, back.smoothing, back.neutral_id) == (
        seq, ts, align, smoothing, frame.neutral_id,
    )  # fmt: skip
    assert back.neutral_noise == frame.neutral_noise
    np.testing.assert_array_equal(back.points, pts)
    assert back.points.dtype == np.float32
    if with_neutral:
        np.testing.assert_array_equal(back.neutral, pts + 1)
    else:
        assert back.neutral is None


def test_a_keys_weight_smoothing_starts_afresh_when_ts_goes_back(rigs):
    # A publisher's clock that jumped back (restart, wrap): the key's filter is reset, so
    # the frame is smoothed as if it were the first one, not held back by the old state.
    rig = rigs[RIG_IDS[0]]
    smoothing = Smoothing(min_cutoff=0.05, beta=0.0, target="weights")

    def weights(state, seq: int, ts: float, seed: int) -> np.ndarray:
        frame = ChannelFrame(seq=seq, ts=ts, points=points(rig, seed), smoothing=smoothing)
        return decode_server(state.clone(frame, 0.0)).weights

    key = (RIG_IDS[0], "weights", "f32")
    running = key_state(key, rig)
    before = [weights(running, seq, 10.0 + seq / 60, seed=1) for seq in range(5)]
    back = weights(running, 5, 0.5, seed=2)
    fresh = weights(key_state(key, rig), 0, 0.5, seed=2)

    np.testing.assert_array_equal(back, fresh)
    assert not np.allclose(back, before[-1])  # a new pose, not the old one held


async def test_a_performer_on_the_layouts_26_points_drives_rigs_of_its_earlier_24_and_20(
    tmp_path, ws_impl
):
    # PROTOCOL.md §2.4: a rig of one of the tracker layout's earlier counts is its first
    # points, so a channel publishing the layout's 26 (a performer's own rig) is watched on
    # 24- and 20-point characters (ICT's landmarks, the cartoon) with the first 24 / 20
    # points - the neutral and the closed eyes of a calibrate too - as the /perform page
    # sends them to such a rig. A rig of a count the layout never had is still refused.
    counts = load_layout().counts
    assert counts[-1] == 26 and {20, 24} <= set(counts)
    names = ("neutral", "eyeBlinkLeft", "frown", "jaw", "smile")
    examples = tiny_examples(11, names=names, k=26)
    rigs = {f"k{k}": fit(dataclasses.replace(examples, source_points=examples.source_points[:, :k]))
            for k in (26, 24, 20)}  # fmt: skip
    rigs["k25"] = fit(dataclasses.replace(examples, source_points=examples.source_points[:, :25]))
    write_rigs(tmp_path / "rigs", rigs)
    source = examples.source_points.astype(np.float32)
    neutral = source[0] + np.float32(0.3)
    closed = neutral + np.float32(0.8) * (source[1] - source[0])
    frames = [neutral + np.float32(0.6) * (source[i] - source[0]) for i in (1, 3, 4)]
    calibrate = Calibrate(points=neutral, noise=0.01, blinks={"eyeBlinkLeft": closed})
    settings = Settings(rigs_dir=tmp_path / "rigs", face_lost_after=30.0)
    async with run_server(settings, ws=ws_impl) as server:
        watchers = {k: await Watcher.open(server.ws_url, "stage", f"k{k}") for k in (26, 24, 20)}
        raw = await Watcher.open(server.ws_url, "stage", "k20", output="points")
        misfit = await Watcher.open(server.ws_url, "stage", "k25")
        publisher = await Publisher.open(server.ws_url, "stage", "k26")
        await publisher.ws.send(publisher.protocol.send(calibrate))
        while not isinstance(await publisher.queue.get(), Calibrated):
            pass
        received = {k: [] for k in watchers}
        for seq, frame in enumerate(frames):
            await publisher.send(seq, frame)
            for k, watcher in watchers.items():
                received[k].append((await watcher.result_with_seq(seq)).weights)
        first_points = await raw.result_with_seq(0)
        told = await misfit.next(Error)

    for k, got in received.items():
        rig = calibrate_rig(rigs[f"k{k}"], neutral[:k], 0.01, {"eyeBlinkLeft": closed[:k]})
        expected = rig.weights(np.stack(frames)[:, :k]).astype(np.float32)
        np.testing.assert_array_equal(np.stack(got), expected)
    # The 24- and 20-point rigs read what the 26-point one reads (one example set cut).
    assert np.abs(np.stack(received[20]) - np.stack(received[26])).max() < 0.05
    np.testing.assert_array_equal(first_points.points, frames[0][:20])
    assert told.code == ErrorCode.WRONG_POINT_COUNT and not told.fatal
