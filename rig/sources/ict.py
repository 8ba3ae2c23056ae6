"""The ICT-FaceKit face model as an example set, and synthetic performances driven on it.

Reads the converted ``ict_facekit.npz`` (see shared/data/ict-facekit/README.md) and builds
arrays; it must not fit, evaluate or write anything.

The default feature points are 24 of the Multi-PIE 68 landmarks (brows, eye lids, nose,
mouth corners and lips, chin). With them every ICT expression except ``PupilDilate_L`` and
``PupilDilate_R`` (which move no vertex of the face surface) moves some feature point, so
those two are left out by default. The nearest pair left is eyeWide / eyeLookUp (about
0.11 cm apart in the reduced parameter space): distinguishable without noise, fragile with it.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..errors import ExampleSetError, InputError
from ..examples import ExampleSet
from ..npy_reads import NPY_READS
from .animation import SourceAnimation
from .synthetic import frame_count, smooth_bump

__all__ = [
    "DEFAULT_LANDMARKS",
    "DEFAULT_STABLE_LANDMARKS",
    "ICT_FILE",
    "ict_animation",
    "ict_example_set",
    "ict_regions",
    "ict_target_frames",
    "locate_ict",
    "stable_positions",
]

ICT_FILE = "ict_facekit.npz"

# Positions in ICT's ``landmarks68`` (Multi-PIE order): brows 17, 19, 21 / 22, 24, 26;
# upper and lower lids' outer thirds 37, 41 / 44, 46; nose tip and wings 30, 31, 35; mouth
# corners 48, 54; outer upper and lower lip 51, 57; inner upper and lower lip 62, 66; chin 8;
# then the lids' inner thirds 38, 40 / 43, 47. Both lids of each eye are needed to tell
# blinks, squints, wides and looks apart; the inner lips to tell rolls and presses from the
# outer-lip shapes; two points a lid to tell a blink from a look down (issue 34: with one
# a lid, ICT's eyeLookDown moves the upper lid point 0.64 cm where eyeBlink moves it 0.79,
# and a noise-aware fit splits the two; on the eyes clip's exact landmarks the personal
# path's blink peaks rise 0.74 -> 0.94 with the second, README "The eyes clip"). The last
# four were appended (the layout's 20-point version is its prefix), so rigs and captures
# of 20 points stay usable with the first 20.
DEFAULT_LANDMARKS: tuple[int, ...] = (
    17, 19, 21, 22, 24, 26, 37, 41, 44, 46, 30, 31, 35, 48, 51, 54, 57, 62, 66, 8,
    38, 40, 43, 47,
)  # fmt: skip

# Multi-PIE 68 positions that expressions move least, relative to how far a head rotation
# moves them: inner brows 21, 22, lower lids 41, 46 and the nose tip 30 (no jaw, no lips).
# Chosen by measurement over all 55 ICT expressions: among every subset of 3 or more of the
# 13 default landmarks off the jaw and lips, aligning an unmoved expression to the neutral
# on these turns it least, at most 24.5 mrad (rms 11.1), against 104 mrad for inner brows
# and upper lids (eyeBlink) and 136 mrad for all 20 points (jawOpen). Every landmark moves
# in some shape (the least, inner eye corners, by 0.07 cm), so no set is exact alone; the
# rig's pose refinement (pose.refine_pose) removes what remains.
DEFAULT_STABLE_LANDMARKS: tuple[int, ...] = (21, 22, 41, 46, 30)

# A shape whose largest feature-point displacement is below this (cm) is invisible to
# the feature points and would coincide with the neutral in parameter space.
_UNSEEN_CM = 1e-6
_MAX_FRAMES = 36_000  # 10 min at 60 fps


def _archive_path(path: str | os.PathLike[str]) -> Path:
    path = Path(path)
    if path.is_dir():
        path = path / ICT_FILE
    if not path.is_file():
        raise ExampleSetError(
            f"{path}: no such file (the ICT-FaceKit archive)", code="missing_file"
        )
    return path


def _read(path: Path) -> dict[str, np.ndarray]:
    keys = ("neutral", "faces", "expressions", "expression_names", "landmarks68")
    try:
        with NPY_READS, np.load(path, allow_pickle=False) as archive:
            return {k: archive[k] for k in keys}
    except KeyError as exc:
        raise ExampleSetError(f"{path}: not an ICT-FaceKit archive (missing {exc})") from None
    except Exception as exc:  # zipfile/zlib/numpy raise many types on a corrupt file
        raise ExampleSetError(
            f"{path}: not readable ({type(exc).__name__}: {exc})", code="bad_example_set"
        ) from None


def _identity(path: Path, name: str) -> np.ndarray:
    with NPY_READS, np.load(path, allow_pickle=False) as archive:
        if "identity_names" not in archive.files:
            raise ExampleSetError(f"{path}: holds no identities", code="unknown_identity")
        names = [str(n) for n in archive["identity_names"]]
        if name not in names:
            raise ExampleSetError(
                f"no ICT identity named {name!r}; expected one of {names[0]} ... {names[-1]}",
                code="unknown_identity",
            )
        identity: np.ndarray = archive["identities"][names.index(name)].astype(np.float64)
        return identity


def _landmark_vertices(landmarks68: np.ndarray, landmarks: Sequence[int]) -> np.ndarray:
    chosen = np.asarray(landmarks)
    if chosen.ndim != 1 or chosen.size == 0 or not np.issubdtype(chosen.dtype, np.integer):
        raise ExampleSetError("landmarks: expected a non-empty list of integers in [0, 68)")
    if chosen.min() < 0 or chosen.max() >= landmarks68.size:
        raise ExampleSetError(
            f"landmarks: positions must lie in [0, {landmarks68.size}), got "
            f"[{chosen.min()}, {chosen.max()}]",
            code="index_out_of_range",
        )
    if np.unique(chosen).size != chosen.size:
        raise ExampleSetError("landmarks: a landmark is chosen twice")
    indices: np.ndarray = landmarks68[chosen].astype(np.int64)
    return indices


def ict_regions(path: str | os.PathLike[str]) -> tuple[dict[str, tuple[int, int]], np.ndarray]:
    """The archive's parts and landmarks: ``({region name: (start, stop)}, landmarks68)``.

    Regions are ICT's vertex ranges (face, head_and_neck, mouth_socket, eye sockets,
    gums_and_tongue, teeth, eyeballs, lacrimal fluid, eye blend, eye occlusion, eyelashes);
    ``landmarks68`` (68,) int64 the vertex of each Multi-PIE landmark.
    """
    archive = _archive_path(path)
    try:
        with NPY_READS, np.load(archive, allow_pickle=False) as data:
            names = [str(n) for n in data["region_names"]]
            ranges = data["region_ranges"].astype(np.int64)
            landmarks: np.ndarray = data["landmarks68"].astype(np.int64)
    except KeyError as exc:
        raise ExampleSetError(f"{archive}: no ICT-FaceKit regions (missing {exc})") from None
    regions = {name: (int(a), int(b)) for name, (a, b) in zip(names, ranges, strict=True)}
    return regions, landmarks


def stable_positions(
    landmarks: Sequence[int], stable_landmarks: Sequence[int] = DEFAULT_STABLE_LANDMARKS
) -> tuple[int, ...] | None:
    """Positions in ``landmarks`` of the stable landmarks it holds; None if fewer than 3."""
    chosen = list(landmarks)
    positions = tuple(chosen.index(mark) for mark in stable_landmarks if mark in chosen)
    return positions if len(positions) >= 3 else None


def ict_example_set(
    path: str | os.PathLike[str],
    *,
    landmarks: Sequence[int] = DEFAULT_LANDMARKS,
    expressions: Sequence[str] | None = None,
    identity: str | None = None,
) -> ExampleSet:
    """The ICT expressions as paired examples: generic face -> itself or one identity.

    Parameters
    ----------
    path : path-like
        The ``ict-facekit`` folder or its ``ict_facekit.npz``.
    landmarks : sequence of int
        Positions in ICT's ``landmarks68`` used as feature points (K of them).
    expressions : sequence of str, optional
        Expression names to use, in this order. Default: all of them except those that
        move no chosen feature point (with the default landmarks: PupilDilate_L/R).
    identity : str, optional
        A person (``person00`` ... ``person19``): the target is that face plus the same
        expression deltas, as ICT's own linear model combines them. Default: the target
        is the generic face itself.

    Returns
    -------
    ExampleSet
        ``names`` ("neutral", expressions...), ``source_vertices`` (M, 26719, 3) with
        ``source_faces``, ``feature_indices`` (K,), ``target_vertices`` (M, 26719, 3),
        ``target_faces`` (52220, 3) and ``stable_points``: the positions of
        ``DEFAULT_STABLE_LANDMARKS`` among ``landmarks`` (None if fewer than 3 are chosen).

    Raises
    ------
    ExampleSetError
        Missing or unreadable archive, unknown expression or identity, bad landmarks, or
        an explicitly requested expression that moves no feature point.
    """
    archive = _archive_path(path)
    data = _read(archive)
    neutral = data["neutral"].astype(np.float64)
    all_names = [str(n) for n in data["expression_names"]]
    feature = _landmark_vertices(data["landmarks68"], landmarks)
    shapes = data["expressions"]
    motion = np.abs(shapes[:, feature, :] - neutral[feature]).max(axis=(1, 2))
    if expressions is None:
        pick = [i for i in range(len(all_names)) if motion[i] > _UNSEEN_CM]
    else:
        index = {n: i for i, n in enumerate(all_names)}
        unknown = [n for n in expressions if n not in index]
        if unknown:
            raise ExampleSetError(
                f"no ICT expression named {unknown[0]!r}", code="unknown_expression"
            )
        pick = [index[n] for n in expressions]
        unseen = [all_names[i] for i in pick if motion[i] <= _UNSEEN_CM]
        if unseen:
            raise ExampleSetError(
                f"expression {unseen[0]!r} moves none of the chosen feature points, so it "
                "would coincide with the neutral; add landmarks that it moves or drop it",
                code="expression_unseen",
            )
    names = ("neutral", *(all_names[i] for i in pick))
    source = np.empty((len(names), neutral.shape[0], 3))
    source[0] = neutral
    source[1:] = shapes[pick]
    if identity is None:
        target = source
    else:
        face = _identity(archive, identity)
        target = source - neutral + face  # eq. of ICT's model: face + (expression - neutral)
    return ExampleSet.from_source_meshes(
        names,
        source,
        feature,
        target,
        data["faces"],
        source_faces=data["faces"],
        stable_points=stable_positions(landmarks),
    )


def ict_animation(
    example_set: ExampleSet, *, seconds: float = 10.0, fps: float = 60.0, seed: int = 0
) -> tuple[np.ndarray, SourceAnimation]:
    """A random performance of sparse, smooth expression mixes on the source face.

    About three expressions are active at a time, each rising and falling in a smooth bump
    of 0.3-1.6 s to a peak in [0.3, 1]; overlapping bumps of one expression take their
    maximum, so every activation stays in [0, 1]. ``mouthClose`` is capped at ``jawOpen``
    (ICT's caution: it is a corrective shape for an open jaw).

    Parameters
    ----------
    example_set : ExampleSet
        Any set whose source examples combine linearly (as ICT's do); usually from
        ``ict_example_set``.
    seconds, fps : float
        Length and frame rate; frame ``i`` plays at ``i / fps``.
    seed : int

    Returns
    -------
    activations : (F, M) float64
        Column 0 (the neutral) is zero; the others in [0, 1].
    animation : SourceAnimation
        ``points`` (F, K, 3): ``S_B + activations @ (S_i - S_B)`` at the feature points.
    """
    frames = frame_count(seconds, fps, _MAX_FRAMES, code="bad_animation")
    seconds, fps = float(seconds), float(fps)
    rng = np.random.default_rng(seed)
    m = example_set.num_examples
    t = np.arange(frames) / fps
    activations = np.zeros((frames, m))
    # Events arrive at 3 per second and last about a second each: ~3 active at a time.
    count = max(1, round(3.0 * seconds))
    for _ in range(count):
        column = int(rng.integers(1, m))
        ramp = rng.uniform(0.15, 0.4)
        start = rng.uniform(-0.5, seconds)
        peak = rng.uniform(0.3, 1.0)
        end = start + rng.uniform(0.0, 0.8)
        bump = peak * smooth_bump(t, start, end, ramp, ramp)
        np.maximum(activations[:, column], bump, out=activations[:, column])
    names = example_set.names
    if "mouthClose" in names:
        close = names.index("mouthClose")
        jaw = activations[:, names.index("jawOpen")] if "jawOpen" in names else 0.0
        np.minimum(activations[:, close], jaw, out=activations[:, close])
    neutral = example_set.source_neutral
    deltas = (example_set.source_points - neutral).reshape(m, -1)
    points = (neutral.reshape(-1) + activations @ deltas).reshape(frames, -1, 3)
    return activations, SourceAnimation(points=points, fps=fps)


def ict_target_frames(
    example_set: ExampleSet, activations: npt.ArrayLike, *, dtype: npt.DTypeLike = np.float32
) -> np.ndarray:
    """The ideal clone of an ``ict_animation``: the target's examples mixed the same way.

    Parameters
    ----------
    example_set : ExampleSet
    activations : (F, M) float
        Column 0 is ignored (the neutral carries the rest of the sum).

    Returns
    -------
    (F, V, 3) ``dtype``: ``T_B + activations @ (T_i - T_B)``.
    """
    act = np.asarray(activations, dtype=np.float64)
    m = example_set.num_examples
    if act.ndim != 2 or act.shape[1] != m:
        raise InputError(f"activations: expected shape (F, {m}), got {act.shape}")
    target = example_set.target_vertices
    deltas = (target[1:] - target[0]).reshape(m - 1, -1).astype(dtype)
    frames = act[:, 1:].astype(dtype) @ deltas
    frames += target[0].reshape(-1).astype(dtype)
    out: np.ndarray = frames.reshape(act.shape[0], -1, 3)
    return out


def locate_ict(path: str | os.PathLike[str] | None = None) -> Path | None:
    """The ICT-FaceKit archive: ``path``, else ``$FACECAST_ICT``, else the shared data folder.

    The shared folder is ``../shared/data/ict-facekit`` next to the repository (or to the
    current directory). Returns the ``.npz`` path, or None when none of them holds one; an
    explicit ``path`` that does not exist is an error.
    """
    if path is not None:
        return _archive_path(path)
    candidates = []
    if os.environ.get("FACECAST_ICT"):
        candidates.append(Path(os.environ["FACECAST_ICT"]))
    relative = Path("..", "shared", "data", "ict-facekit")
    candidates += [Path(__file__).resolve().parents[1] / relative, Path.cwd() / relative]
    for candidate in candidates:
        archive = candidate / ICT_FILE if candidate.is_dir() else candidate
        if archive.is_file():
            return archive
    return None
