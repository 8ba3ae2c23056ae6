"""``facecast clone`` smooths a take in time on a noise rig (RTS), and not with --smoothing none."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.cli import main as cli
from facecast.cli.commands import clone
from facecast.rig import SMOOTHING_CHOICES, load_rig, smooth_take
from facecast.rig.demo import demo_activations, demo_animation, demo_target_frames
from facecast.rig.filters import KALMAN_ACCELERATION, KalmanFilter

SIGMA = 0.2  # 1 % of the demo face
FPS = 60.0


@pytest.fixture(scope="module")
def rigs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rigs")
    assert cli.main(["fit", "demo", "-o", str(folder / "exact.rig")]) == 0
    assert cli.main(["fit", "demo", "-o", str(folder / "noise.rig"), "--noise", str(SIGMA)]) == 0
    return folder / "exact.rig", folder / "noise.rig"


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    """A noisy demo performance (.npz) and its ideal clone."""
    clean = demo_target_frames(demo_activations(4.0, FPS))
    points = demo_animation(4.0, FPS).points
    noisy = points + np.random.default_rng(0).normal(0.0, SIGMA, points.shape)
    path = tmp_path_factory.mktemp("take") / "take.npz"
    np.savez(path, points=noisy, fps=FPS)
    return path, clean, noisy


def _clone(rig, source, out, *extra: str) -> np.ndarray:
    assert cli.main(["clone", str(rig), str(source), "-o", str(out), *extra]) == 0
    with np.load(out) as archive:
        return archive["vertices"].astype(np.float64)


def test_clone_on_a_noise_rig_smooths_by_default_and_is_closer_to_the_clean_clone(
    rigs, take, tmp_path, capsys
):
    _, noise_rig = rigs
    source, clean, noisy = take
    rig = load_rig(noise_rig)

    smoothed = _clone(noise_rig, source, tmp_path / "default.npz")
    printed = capsys.readouterr().out
    per_frame = _clone(noise_rig, source, tmp_path / "none.npz", "--smoothing", "none")

    assert "RTS-smoothed" in printed
    take = smooth_take(rig, noisy, np.arange(len(noisy)) / FPS)
    np.testing.assert_allclose(smoothed, take.rig.clone(take.points), atol=1e-5)
    np.testing.assert_allclose(per_frame, rig.clone(noisy), atol=1e-5)
    ideal = clean.astype(np.float64)

    def rms(vertices: np.ndarray) -> float:
        return float(np.sqrt(np.mean((vertices - ideal) ** 2)))

    assert rms(smoothed) < 0.9 * rms(per_frame)


def test_clone_with_kalman_runs_the_causal_filter(rigs, take, tmp_path, capsys):
    _, noise_rig = rigs
    source, clean, noisy = take
    rig = load_rig(noise_rig)
    half = len(noisy) // 2
    head = tmp_path / "head.npz"
    np.savez(head, points=noisy[:half], fps=FPS)

    filtered = _clone(noise_rig, source, tmp_path / "kalman.npz", "--smoothing", "kalman")
    printed = capsys.readouterr().out
    filtered_head = _clone(noise_rig, head, tmp_path / "head-out.npz", "--smoothing", "kalman")

    assert "Kalman-filtered" in printed
    # The live filter with the rig's fitted noise and the default acceleration, per frame.
    live = KalmanFilter(SIGMA, KALMAN_ACCELERATION * SIGMA)
    expected = live.filter_series(noisy.reshape(len(noisy), -1), np.arange(len(noisy)) / FPS)
    np.testing.assert_allclose(filtered, rig.clone(expected.reshape(noisy.shape)), atol=1e-5)
    # Causal: a frame's clone does not depend on the frames after it (RTS's would).
    np.testing.assert_allclose(filtered[:half], filtered_head, atol=1e-5)
    ideal = clean.astype(np.float64)

    def rms(vertices: np.ndarray) -> float:
        return float(np.sqrt(np.mean((vertices - ideal) ** 2)))

    # The live default trades little smoothing for no lag: ~6 % less error here.
    assert rms(filtered) < 0.97 * rms(rig.clone(noisy))


def test_clone_on_an_exact_rig_does_not_smooth_by_default(rigs, take, tmp_path, capsys):
    exact, _ = rigs
    source, _, noisy = take

    vertices = _clone(exact, source, tmp_path / "exact.npz")

    assert "not smoothed" in capsys.readouterr().out
    np.testing.assert_allclose(vertices, load_rig(exact).clone(noisy), atol=1e-5)


def test_clone_refuses_rts_on_a_rig_without_noise(rigs, take, tmp_path, capsys):
    exact, _ = rigs
    source, _, _ = take

    code = cli.main(["clone", str(exact), str(source), "-o", str(tmp_path / "x.npz"),
                     "--smoothing", "rts"])  # fmt: skip

    assert code == 2
    err = capsys.readouterr().err
    assert "--smoothing rts" in err and "--noise" in err
    assert not (tmp_path / "x.npz").exists()


def test_clone_smoothing_choices_match_the_engine():
    assert clone.SMOOTHING_CHOICES == SMOOTHING_CHOICES
    assert clone.KALMAN_ACCELERATION == KALMAN_ACCELERATION


@pytest.mark.parametrize("value", ["-5", "nan", "0"])
def test_clone_refuses_a_bad_acceleration(rigs, take, tmp_path, capsys, value):
    _, noise_rig = rigs
    source, _, _ = take

    code = cli.main(["clone", str(noise_rig), str(source), "-o", str(tmp_path / "x.npz"),
                     "--acceleration", value])  # fmt: skip

    assert code == 2
    assert "acceleration must be finite and > 0" in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()
