"""The Y4M reader of ``facecast track``: frames located and read back, bad files refused
with errors that say what is accepted (no browser needed: the file is refused first)."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.cli.main import main
from facecast.cli.y4m import Y4MError, open_y4m


def _write(path, header: bytes, frames: list[bytes]):
    path.write_bytes(header + b"".join(b"FRAME\n" + frame for frame in frames))
    return path


def _planes(width: int, height: int, value: int, chroma: tuple[int, int] = (2, 2)) -> bytes:
    cw, ch = -(-width // chroma[0]), -(-height // chroma[1])
    return bytes([value]) * (width * height) + bytes([128]) * (2 * cw * ch)


def test_frames_are_located_and_read_back(tmp_path):
    frames = [_planes(6, 4, v) for v in (10, 20, 30)]
    path = _write(tmp_path / "a.y4m", b"YUV4MPEG2 W6 H4 F30000:1001 Ip A1:1 C420jpeg\n", frames)

    video = open_y4m(path)

    assert (video.width, video.height, video.format, video.num_frames) == (6, 4, "I420", 3)
    assert video.fps == pytest.approx(29.97, abs=1e-3)
    assert [video.read(i) for i in range(3)] == frames


def test_odd_sizes_and_frame_parameters_are_read(tmp_path):
    frame = _planes(5, 3, 77, (1, 1))
    path = tmp_path / "odd.y4m"
    path.write_bytes(b"YUV4MPEG2 W5 H3 F25:1 C444\nFRAME Ixyz\n" + frame)

    video = open_y4m(path)

    assert video.format == "I444" and video.read(0) == frame
    assert np.frombuffer(video.read(0), np.uint8)[:15].tolist() == [77] * 15


def test_a_file_that_is_not_y4m_names_what_is_accepted(tmp_path):
    path = tmp_path / "clip.mp4"
    path.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(100))

    with pytest.raises(Y4MError, match=r"not a YUV4MPEG2 video.*4:2:0, 4:2:2 or 4:4:4.*ffmpeg"):
        open_y4m(path)


def test_an_unsupported_colour_space_names_what_is_accepted(tmp_path):
    path = _write(tmp_path / "deep.y4m", b"YUV4MPEG2 W4 H4 F25:1 C420p10\n", [bytes(48)])

    with pytest.raises(Y4MError, match=r"C420p10 is not supported.*C420jpeg") as caught:
        open_y4m(path)
    assert caught.value.code == "unsupported_video"


@pytest.mark.parametrize(
    ("content", "code"),
    [
        (b"YUV4MPEG2 W4 H4 F25:1\nFRAME\n" + bytes(23), "truncated_video"),
        (b"YUV4MPEG2 W4 H4 F25:1\nFRAME\n" + bytes(24) + b"JUNK\n", "truncated_video"),
        (b"YUV4MPEG2 W4 H4 F25:1\n", "empty_video"),
        (b"YUV4MPEG2 W0 H4 F25:1\n", "bad_video"),
        (b"YUV4MPEG2 W4 H4 F0:1\n", "bad_video"),
        (b"YUV4MPEG2 H4 F25:1\n", "bad_video"),
    ],
)
def test_damaged_files_are_refused_with_a_code(tmp_path, content, code):
    path = tmp_path / "bad.y4m"
    path.write_bytes(content)

    with pytest.raises(Y4MError) as caught:
        open_y4m(path)
    assert caught.value.code == code


def test_the_command_says_what_is_wrong_with_the_video(tmp_path, capsys):
    path = tmp_path / "clip.avi"
    path.write_bytes(b"RIFF" + bytes(64))

    status = main(["track", str(path), "-o", str(tmp_path / "p.npz")])

    assert status == 2
    err = capsys.readouterr().err
    assert "facecast track: error:" in err and "not a YUV4MPEG2 video" in err
    assert not (tmp_path / "p.npz").exists()


@pytest.mark.parametrize(
    "fields",
    [
        b"W4 H4 F" + b"9" * 400 + b":1",  # float() of it overflowed: a traceback (issue 31)
        b"W4 H4 F25:" + b"7" * 400,
        b"W4 H4 F25:0",
        b"W4 H4 F-25:1",
        b"W4 H4 F25",
        b"W4 H4 F1001:1",  # over MAX_FPS
        b"W4 H4 F2147483648:1",  # over a 32-bit int
        b"W+4 H4 F25:1",
        b"W4 H4_0 F25:1",
        b"W" + b"4" * 5000 + b" H4 F25:1",  # past int()'s digit limit
        b"W4 H4 F25:1 A" + b"1" * 400 + b":1",
        b"W4 H4 F25:1 A1",
        b"W4097 H4 F25:1",  # over MAX_SIDE: more than the tracker's page takes
    ],
)
def test_every_header_number_is_checked(tmp_path, fields):
    path = tmp_path / "bad.y4m"
    path.write_bytes(b"YUV4MPEG2 " + fields + b"\nFRAME\n" + bytes(24))

    with pytest.raises(Y4MError) as caught:
        open_y4m(path)
    assert caught.value.code == "bad_video"


def test_the_command_refuses_a_header_number_with_exit_2(tmp_path, capsys):
    path = tmp_path / "huge_rate.y4m"
    path.write_bytes(b"YUV4MPEG2 W4 H4 F" + b"9" * 400 + b":1\nFRAME\n" + bytes(24))

    status = main(["track", str(path), "-o", str(tmp_path / "p.npz")])

    assert status == 2
    err = capsys.readouterr().err
    assert "facecast track: error:" in err and "frame rate numerator" in err
    assert "Traceback" not in err


def test_max_frames_locates_only_the_frames_asked_for(tmp_path):
    frame = b"FRAME\n" + bytes(24)
    path = tmp_path / "clip.y4m"
    # Two good frames, then what would fail a full read: a frame cut short.
    path.write_bytes(b"YUV4MPEG2 W4 H4 F25:1\n" + frame * 2 + b"JUNK\n" + bytes(5))

    video = open_y4m(path, max_frames=2)

    assert video.num_frames == 2
    assert video.read(1) == bytes(24)
    with pytest.raises(Y4MError):
        open_y4m(path)


def test_the_tracker_serves_its_files_and_frames_under_its_random_path_alone(tmp_path):
    """``facecast track``'s loopback server (the browser's only source): the page and each
    frame under the run's random path, nothing else, and the socket closed after."""
    import urllib.error
    import urllib.request

    from facecast.cli.track import _serving

    frames = [_planes(6, 4, v) for v in (10, 20)]
    video = open_y4m(_write(tmp_path / "a.y4m", b"YUV4MPEG2 W6 H4 F25:1\n", frames))
    page = tmp_path / "track.html"
    page.write_text("<!doctype html>")

    def get(url: str) -> tuple[int, bytes]:
        try:
            with urllib.request.urlopen(url, timeout=10) as response:
                return response.status, response.read()
        except urllib.error.HTTPError as error:
            return error.code, b""

    with _serving(video.read, {"/track": (page, "text/html")}) as url:
        base = url.removesuffix("track")
        origin = base.split("/", 3)
        assert url.startswith("http://127.0.0.1:") and len(origin[3]) > 16  # a token path
        assert get(url) == (200, b"<!doctype html>")
        assert [get(f"{base}frames/{i}") for i in (0, 1)] == [(200, f) for f in frames]
        for wrong in (f"{base}frames/2", f"{base}frames/x", f"{base}other",
                      "/".join(origin[:3]) + "/track", "/".join(origin[:3]) + "/frames/0"):  # fmt: skip
            assert get(wrong) == (404, b""), wrong
    with pytest.raises(urllib.error.URLError):
        urllib.request.urlopen(url, timeout=5)
