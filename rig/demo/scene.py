"""The procedural demo: a human-ish source head, a cartoon target head and a performance.

Everything is generated from seeded formulas in milliseconds, so the demo runs on a fresh
machine with no downloads; it must not read files or touch the network.

Public names
------------
- ``demo_example_set()`` -> ExampleSet: source head (warped UV sphere) and cartoon target
  (icosphere), neutral + 6 emotions + 5 visemes + a blink (``DEMO_NAMES``).
- ``demo_animation(seconds, fps)`` -> SourceAnimation: the source performance.
- ``demo_activations(seconds, fps)`` -> (F, M): per-example activation curves that
  drive the performance (column 0, the neutral, is zero).
- ``demo_target_frames(activations)`` -> (F, V, 3): the ideal clone, the target's own
  expressions driven by the same activations (ground truth for evaluation).
- ``demo_landmarks(character)``: named semantic landmark positions on either neutral.

Each expression is a set of facial "controls" (jaw, smile, brows, lids, ...); the source
and the target give the same expression different control values, so the target's
examples are characteristic of the cartoon and not a resampled copy of the source's.
The heads' neutral geometry is built in ``geometry`` and posed by the controls in
``controls``; this module holds the expressions, the performance and the public API.
"""

from __future__ import annotations

import functools

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from ..examples import ExampleSet
from ..sources.animation import SourceAnimation
from ..sources.synthetic import frame_count, smooth_bump
from .controls import CONTROL_INDEX, CONTROLS, character_model, pose_vertices

__all__ = [
    "DEMO_EMOTIONS",
    "DEMO_FEATURE_NAMES",
    "DEMO_NAMES",
    "DEMO_VISEMES",
    "demo_activations",
    "demo_animation",
    "demo_example_set",
    "demo_landmarks",
    "demo_target_frames",
]

DEMO_EMOTIONS = ("happy", "sad", "surprise", "fear", "anger", "disgust")
DEMO_VISEMES = ("aa", "oo", "ee", "mbp", "fv")
DEMO_NAMES = ("neutral", *DEMO_EMOTIONS, *DEMO_VISEMES, "blink")

# Each expression as values of the face controls (``controls.CONTROLS``).
_SOURCE_POSES: dict[str, dict[str, float]] = {
    "happy": {"smile": 1.0, "cheek": 0.8, "squint": 0.45, "jaw": 0.12, "lid": -0.15},
    "sad": {"frown": 1.0, "brow_in_up": 1.0, "lid": -0.35, "press": 0.2},
    "surprise": {"brow_in_up": 1.0, "brow_out_up": 1.0, "lid": 1.0, "jaw": 0.75, "pucker": 0.2},
    "fear": {"brow_in_up": 1.0, "brow_out_up": 0.35, "lid": 0.8, "stretch": 0.9, "jaw": 0.3},
    "anger": {"brow_down": 1.0, "squint": 0.6, "lid": 0.25, "press": 0.55, "frown": 0.25},
    "disgust": {"wrinkle": 1.0, "lip_raise": 0.9, "brow_down": 0.45, "squint": 0.5, "frown": 0.3},
    "aa": {"jaw": 1.0, "stretch": 0.1},
    "oo": {"pucker": 1.0, "jaw": 0.3},
    "ee": {"stretch": 0.8, "jaw": 0.3, "smile": 0.2, "lip_raise": 0.2},
    "mbp": {"press": 1.0, "jaw": -0.05},
    "fv": {"bite": 1.0, "lip_raise": 0.25, "jaw": 0.1},
    "blink": {"lid": -1.0},
}
# The cartoon's own acting: a bigger grin, a wider-eyed surprise, harder furrows, ears
# that droop when sad and perk up when surprised; its sad mouth moves comparatively less.
_TARGET_POSES: dict[str, dict[str, float]] = {
    "happy": {"smile": 1.9, "cheek": 1.0, "squint": 0.5, "jaw": 0.4, "ears": 0.4},
    "sad": {"frown": 0.8, "brow_in_up": 1.6, "lid": -0.45, "ears": -1.0},
    "surprise": {"brow_in_up": 1.5, "brow_out_up": 1.7, "lid": 1.8, "jaw": 1.15, "ears": 1.0},
    "fear": {"brow_in_up": 1.6, "brow_out_up": 0.5, "lid": 1.5, "stretch": 1.3, "jaw": 0.45,
             "ears": -0.6},
    "anger": {"brow_down": 1.8, "squint": 0.7, "lip_raise": 0.7, "frown": 0.5, "jaw": 0.15,
              "ears": -0.4},
    "disgust": {"wrinkle": 1.6, "lip_raise": 1.3, "brow_down": 0.6, "squint": 0.6, "frown": 0.6,
                "ears": -0.3},
    "aa": {"jaw": 1.3, "stretch": 0.2},
    "oo": {"pucker": 1.35, "jaw": 0.35},
    "ee": {"stretch": 1.2, "jaw": 0.35, "smile": 0.35, "lip_raise": 0.25},
    "mbp": {"press": 1.2, "pucker": 0.15},
    "fv": {"bite": 1.3, "lip_raise": 0.35, "jaw": 0.1},
    "blink": {"lid": -1.0},
}  # fmt: skip

# Semantic feature points on the source, by landmark name (about 20).
DEMO_FEATURE_NAMES = (
    "mouth_corner_l", "mouth_corner_r", "upper_lip", "lower_lip",
    "upper_lid_l", "upper_lid_r", "lower_lid_l", "lower_lid_r",
    "brow_inner_l", "brow_inner_r", "brow_outer_l", "brow_outer_r",
    "forehead_l", "forehead_r", "chin", "jaw_l",
    "cheek_l", "cheek_r", "nose_tip", "nose_wing_l", "nose_wing_r",
)  # fmt: skip

# The feature points head-pose removal aligns on first (no jaw, no lips): of every subset
# of 3 or more of the 15 off the mouth and jaw, aligning an unmoved example on these turns
# it least (at most 4.6 mrad; all 21 points: 87 mrad).
DEMO_STABLE_NAMES = ("lower_lid_l", "lower_lid_r", "forehead_l", "forehead_r")

_MAX_FRAMES = 36_000  # 10 min at 60 fps of points
_MAX_VERTEX_FRAMES = 4_000  # bounds the (F, Vs, 3) float32 meshes to about 220 MB


def _controls_of(poses: dict[str, dict[str, float]]) -> np.ndarray:
    """(M, C) control values of each example, row 0 the neutral."""
    table = np.zeros((len(DEMO_NAMES), len(CONTROLS)))
    for m, name in enumerate(DEMO_NAMES[1:], start=1):
        for control, value in poses[name].items():
            table[m, CONTROL_INDEX[control]] = value
    return table


# -- public API -------------------------------------------------------------------------
def demo_landmarks(character: str = "source") -> dict[str, np.ndarray]:
    """Named semantic landmarks (3,) float64 on the neutral of "source" or "target"."""
    if character not in ("source", "target"):
        raise InputError(
            f"character must be 'source' or 'target', got {character!r}", code="bad_demo_argument"
        )
    return {k: v.copy() for k, v in character_model(character).landmarks.items()}


@functools.cache
def _feature_indices() -> np.ndarray:
    model = character_model("source")
    marks = model.landmarks
    wanted = np.stack([marks[name] for name in DEMO_FEATURE_NAMES])
    distance = np.linalg.norm(model.neutral[None, :, :] - wanted[:, None, :], axis=2)
    indices: np.ndarray = distance.argmin(axis=1)
    indices.flags.writeable = False
    return indices


def demo_example_set() -> ExampleSet:
    """The demo's paired examples: neutral + 6 emotions + 5 visemes + blink (13).

    Returns
    -------
    ExampleSet
        ``source_points`` (13, 21, 3), ``source_vertices`` (13, Vs, 3) with ``source_faces``,
        ``feature_indices`` (21,), ``stable_points`` (4,) (``DEMO_STABLE_NAMES``),
        ``target_vertices`` (13, V, 3) and ``target_faces``;
        the source and target meshes differ in vertex count and topology.
    """
    source, target = character_model("source"), character_model("target")
    source_vertices = pose_vertices(source, _controls_of(_SOURCE_POSES))
    target_vertices = pose_vertices(target, _controls_of(_TARGET_POSES))
    return ExampleSet.from_source_meshes(
        DEMO_NAMES,
        source_vertices,
        _feature_indices().copy(),
        target_vertices,
        target.faces.copy(),
        source_faces=source.faces.copy(),
        stable_points=[DEMO_FEATURE_NAMES.index(name) for name in DEMO_STABLE_NAMES],
    )


def demo_activations(seconds: float = 12.0, fps: float = 60.0, *, seed: int = 7) -> np.ndarray:
    """Activation curves of the demo performance, one column per example.

    Emotions come and go over ~2 s with cross-fades and occasional blends, peaks up to
    1.15; speech-like bursts of visemes (one every ~0.17 s, overlapping) run over them;
    blinks every few seconds; everything is scaled by a slow seeded wobble.

    Returns
    -------
    (F, M) float64
        ``F = round(seconds * fps)`` frames; columns follow ``DEMO_NAMES`` (column 0, the
        neutral, is zero); frame ``i`` is at ``i / fps`` seconds.
    """
    frames = frame_count(seconds, fps, _MAX_FRAMES, code="bad_demo_argument")
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / float(fps)
    total = frames / float(fps)
    col = {name: i for i, name in enumerate(DEMO_NAMES)}
    act = np.zeros((frames, len(DEMO_NAMES)))

    order = ["happy", "surprise", "sad", "anger", "fear", "disgust"]
    start = 0.5
    k = 0
    while start < total:
        name = order[k % len(order)]
        hold = rng.uniform(0.9, 1.7)
        peak = rng.uniform(0.6, 1.15)
        act[:, col[name]] += peak * smooth_bump(t, start, start + hold, 0.5, 0.6)
        if rng.random() < 0.4:  # blend in a second emotion for part of the segment
            other = order[(k + rng.integers(1, len(order))) % len(order)]
            act[:, col[other]] += rng.uniform(0.25, 0.5) * smooth_bump(
                t, start + 0.3 * hold, start + 0.8 * hold, 0.4, 0.4
            )
        start += hold + rng.uniform(0.7, 1.2)
        k += 1

    visemes = list(DEMO_VISEMES)
    start = 0.8
    while start < total:
        length = rng.uniform(1.2, 2.6)
        s = start
        while s < min(start + length, total):
            step = rng.uniform(0.13, 0.22)
            name = visemes[rng.integers(len(visemes))]
            act[:, col[name]] += rng.uniform(0.35, 0.9) * smooth_bump(t, s, s + 0.02, step, step)
            s += step
        start += length + rng.uniform(0.4, 1.0)

    start = rng.uniform(0.8, 1.8)
    while start < total:
        act[:, col["blink"]] += rng.choice([1.0, 1.0, 0.85]) * smooth_bump(
            t, start, start, 0.09, 0.13
        )
        start += rng.uniform(2.2, 4.2)

    wobble = np.zeros_like(act)
    for _ in range(3):
        freq = rng.uniform(0.1, 0.6, size=len(DEMO_NAMES))
        phase = rng.uniform(0.0, 2 * np.pi, size=len(DEMO_NAMES))
        wobble += np.sin(2 * np.pi * freq * t[:, None] + phase)
    act *= 1.0 + 0.03 * wobble
    # Overlapping bumps may stack up: saturate softly (C1) above 1, at most 1.25.
    over = np.clip(act - 1.0, 0.0, None)
    act = np.minimum(act, 1.0) + 0.25 * np.tanh(over / 0.25)
    act[:, 0] = 0.0
    return act


def _sanitize_activations(activations: npt.ArrayLike) -> np.ndarray:
    try:
        act = np.asarray(activations, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(
            f"activations: not a numeric array ({exc})", code="bad_activations"
        ) from None
    if act.ndim == 1:
        act = act[None, :]
    if act.ndim != 2 or act.shape[1] != len(DEMO_NAMES):
        raise InputError(
            f"activations: expected shape (F, {len(DEMO_NAMES)}), got {act.shape}",
            code="bad_activations",
        )
    if act.shape[0] > _MAX_VERTEX_FRAMES:
        raise InputError(
            f"activations: at most {_MAX_VERTEX_FRAMES} frames at once, got {act.shape[0]}",
            code="too_many_frames",
        )
    if not np.isfinite(act).all():
        raise InputError("activations: NaN or Inf values", code="non_finite")
    return act


def demo_target_frames(activations: npt.ArrayLike) -> np.ndarray:
    """The ideal clone: the target's own expressions driven by ``activations``.

    Parameters
    ----------
    activations : (F, M) float
        As returned by ``demo_activations`` (columns follow ``DEMO_NAMES``).

    Returns
    -------
    (F, V, 3) float32
        Target vertices per frame (the same frames as the source animation).
    """
    act = _sanitize_activations(activations)
    return pose_vertices(character_model("target"), act @ _controls_of(_TARGET_POSES)).astype(
        np.float32
    )


def demo_animation(
    seconds: float = 12.0, fps: float = 60.0, *, with_vertices: bool = True, seed: int = 7
) -> SourceAnimation:
    """The demo performance on the source face, at the demo's feature points.

    Parameters
    ----------
    seconds, fps : float
        Length and frame rate; frames are at ``i / fps``.
    with_vertices : bool
        Also return the full source meshes per frame (at most 4000 frames).
    seed : int
        Seed of the performance (the same seed gives the same frames).

    Returns
    -------
    SourceAnimation
        ``points`` (F, 21, 3) float64 and, with ``with_vertices``, ``source_vertices``
        (F, Vs, 3) float32; driven by ``demo_activations(seconds, fps, seed=seed)``.
    """
    limit = _MAX_VERTEX_FRAMES if with_vertices else _MAX_FRAMES
    frame_count(seconds, fps, limit, code="bad_demo_argument")
    act = demo_activations(seconds, fps, seed=seed)
    controls = act @ _controls_of(_SOURCE_POSES)
    model = character_model("source")
    indices = _feature_indices()
    if with_vertices:
        vertices = pose_vertices(model, controls)
        return SourceAnimation(
            points=vertices[:, indices, :],
            fps=float(fps),
            source_vertices=vertices.astype(np.float32),
        )
    # Points only: pose just the feature vertices' neighbourhood, in chunks.
    points = np.empty((act.shape[0], len(indices), 3))
    for lo in range(0, act.shape[0], 1000):
        points[lo : lo + 1000] = pose_vertices(model, controls[lo : lo + 1000])[:, indices, :]
    return SourceAnimation(points=points, fps=float(fps))
