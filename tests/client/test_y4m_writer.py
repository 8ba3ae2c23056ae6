"""Writing Y4M: the header ``open_y4m`` reads back, BT.601 limited-range planes, bad frames."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.cli.y4m import Y4MError, Y4MWriter, open_y4m, rgb_to_i420

W, H = 8, 4


def _planes(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    raw = np.frombuffer(data, dtype=np.uint8)
    y = raw[: W * H].reshape(H, W)
    u = raw[W * H : W * H + W * H // 4].reshape(H // 2, W // 2)
    v = raw[W * H + W * H // 4 :].reshape(H // 2, W // 2)
    return y, u, v


def test_written_frames_read_back_with_their_size_rate_and_bytes(tmp_path):
    frames = [np.full((H, W, 3), level, dtype=np.uint8) for level in (0, 128, 255)]
    with Y4MWriter(tmp_path / "clip.y4m", W, H, fps=60) as writer:
        for frame in frames:
            writer.write(frame)

    video = open_y4m(tmp_path / "clip.y4m")

    assert (video.width, video.height, video.fps, video.num_frames) == (W, H, 60.0, 3)
    assert video.format == "I420"
    for index, frame in enumerate(frames):
        assert video.read(index) == rgb_to_i420(frame)


@pytest.mark.parametrize(
    ("rgb", "y", "u", "v"),
    [
        ((0, 0, 0), 16, 128, 128),  # limited range: black is 16
        ((255, 255, 255), 235, 128, 128),  # and white 235
        ((255, 0, 0), 81, 90, 240),  # BT.601 red: Y 16 + 219 x 0.299, V at the top
        ((0, 0, 255), 41, 240, 110),
    ],
)
def test_colours_follow_bt601_limited_range(rgb, y, u, v):
    frame = np.broadcast_to(np.asarray(rgb, dtype=np.uint8), (H, W, 3))

    planes = _planes(rgb_to_i420(frame))

    assert [int(p.flat[0]) for p in planes] == [y, u, v]
    assert all((p == p.flat[0]).all() for p in planes)


def test_float_frames_equal_their_uint8_scaling():
    rng = np.random.default_rng(1)
    frame = rng.integers(0, 256, (H, W, 3)).astype(np.uint8)
    assert rgb_to_i420(frame.astype(np.float64) / 255.0) == rgb_to_i420(frame)


def test_chroma_is_the_mean_of_each_two_by_two_block():
    frame = np.zeros((H, W, 3), dtype=np.uint8)
    frame[0, 0] = (0, 0, 255)  # one blue pixel of the first block

    _, u, _ = _planes(rgb_to_i420(frame))

    assert u[0, 0] == round(128 + 224 * 0.5 / 4)
    assert (u.flat[1:] == 128).all()


@pytest.mark.parametrize("shape", [(H, W), (H, W, 4), (H + 1, W, 3), (H, W + 2, 3)])
def test_a_frame_of_another_shape_is_refused(tmp_path, shape):
    with Y4MWriter(tmp_path / "bad.y4m", W, H, fps=30) as writer:
        with pytest.raises(Y4MError):
            writer.write(np.zeros(shape, dtype=np.uint8))
        assert writer.frames == 0


def test_odd_sizes_are_refused(tmp_path):
    with pytest.raises(Y4MError):
        Y4MWriter(tmp_path / "odd.y4m", 7, 4, fps=30)
