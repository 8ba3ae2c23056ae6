"""The ground-truth webcam benchmark's numbers: a performer with known weights, and scores.

An ICT-FaceKit identity (the performer) makes a real take's ARKit weights and, clip by clip,
its key-expressions; another identity is the character, so the ideal clone is known. This
module builds those weights, meshes and exact landmarks, turns tracked key clips into a
capture as the /perform page does, and scores each cloning path against the truth. It
must not render, track, print or do I/O (``facecast.cli.bench.webcam`` does).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from ..characters.character_examples import generic_pairing
from ..characters.generic import generic_sources
from ..closure import CLOSURE_NAMES
from ..errors import InputError
from ..examples import ExampleSet
from ..pose import similarity_transform
from ..rebase import calibrate
from ..retarget import fit_performer, target_examples
from ..rig import Rig
from ..sources.capture import robust_example
from ..sources.ict import DEFAULT_LANDMARKS, ict_example_set
from ..sources.source_rig import arkit_from_ict
from .evaluate import cloning_error, nnls_weights

__all__ = [
    "GOAL_GENERIC_PERCENT",
    "GOAL_PERSONAL_PERCENT",
    "KEY_HOLD_FRAMES",
    "KEY_RAMP_FRAMES",
    "PERFORMER_IDENTITY",
    "KeyClips",
    "Performer",
    "captured_keys",
    "eye_closures",
    "generic_rig",
    "hold_last_found",
    "ict_performer",
    "key_clips",
    "on_generic_set",
    "score",
    "source_on_neutral",
    "superposition",
    "webcam_rows",
]

#: The face rendered as the performer: neither ICT's generic face (the generic rig's source)
#: nor ``sources.ict_arkit.ARKIT_TARGET_IDENTITY`` (the character).
PERFORMER_IDENTITY = "person07"
#: A key clip: the face goes from rest to the key-expression in KEY_RAMP_FRAMES frames
#: (smoothstep), then holds it KEY_HOLD_FRAMES frames, which are the capture.
KEY_RAMP_FRAMES = 4
KEY_HOLD_FRAMES = 10
#: A real take's eye closures: the runs of frames where its true ``eyeBlink*`` is at least
#: this (ARKit's reading of a real performer's blinks and winks).
CLOSURE_LEVEL = 0.5
#: Frames either side of a closure its peaks are looked for in: a causal filter lags, a
#: tracker may close early.
CLOSURE_MARGIN = 3
#: Issue 34's take goals: eq. 4.1's worst axis, %, on tracked points as viewers get them
#: (the live filter's rows), the personal path's and the generic path's.
GOAL_PERSONAL_PERCENT, GOAL_GENERIC_PERCENT = 2.0, 2.5


@dataclass(frozen=True, eq=False)
class Performer:
    """An ICT identity's whole head (eyes, teeth, mouth inside) with its ARKit shapes.

    Attributes
    ----------
    names : tuple of str
        ``"neutral"``, then the ARKit names (``arkit_from_ict``), M in all.
    neutral : (V, 3) float64
    deltas : (M - 1, 3V) float32
        Each shape minus the neutral, flattened.
    faces : (F, 3) int64
    landmarks : (K,) int64
        Vertex indices of the feature points (ICT's default 24 landmarks).
    """

    names: tuple[str, ...]
    neutral: np.ndarray
    deltas: np.ndarray
    faces: np.ndarray
    landmarks: np.ndarray

    def _activations(self, activations: npt.ArrayLike) -> np.ndarray:
        act = np.asarray(activations, dtype=np.float64)
        m = len(self.names)
        if act.ndim != 2 or act.shape[1] != m:
            raise InputError(f"activations: expected shape (F, {m}), got {act.shape}")
        return act

    def vertices(self, activations: npt.ArrayLike) -> np.ndarray:
        """(B, V, 3) float32: the head making ``activations`` (B, M; column 0 ignored)."""
        act = self._activations(activations)
        flat = act[:, 1:].astype(np.float32) @ self.deltas
        flat += self.neutral.reshape(-1).astype(np.float32)
        out: np.ndarray = flat.reshape(len(act), -1, 3)
        return out

    def landmark_points(self, activations: npt.ArrayLike) -> np.ndarray:
        """(B, K, 3) float64: the exact feature points, in the head's own frame (cm)."""
        act = self._activations(activations)
        columns = (self.landmarks[:, None] * 3 + np.arange(3)).reshape(-1)
        deltas = self.deltas[:, columns].astype(np.float64)
        flat = self.neutral[self.landmarks].reshape(-1) + act[:, 1:] @ deltas
        out: np.ndarray = flat.reshape(len(act), -1, 3)
        return out


def ict_performer(
    path: str | os.PathLike[str],
    identity: str | None = PERFORMER_IDENTITY,
    landmarks: Sequence[int] = DEFAULT_LANDMARKS,
) -> Performer:
    """ICT-FaceKit's ``identity`` (None: its generic face) with every ARKit shape
    (``arkit_from_ict``), whole head; its feature points ``landmarks`` (positions in ICT's
    ``landmarks68``)."""
    ict = ict_example_set(path, identity=identity, landmarks=landmarks)
    names, meshes = arkit_from_ict(ict.names[1:], ict.target_vertices[0], ict.target_vertices[1:])
    neutral = meshes[0]
    deltas = (meshes[1:] - neutral).reshape(len(names) - 1, -1).astype(np.float32)
    if ict.feature_indices is None:
        raise InputError("the ICT example set has no feature indices")
    return Performer(
        names=names,
        neutral=neutral,
        deltas=deltas,
        faces=np.asarray(ict.target_faces, dtype=np.int64),
        landmarks=np.asarray(ict.feature_indices, dtype=np.int64),
    )


@dataclass(frozen=True, eq=False)
class KeyClips:
    """The key-expressions as a performer makes them for a calibration, one clip each.

    Attributes
    ----------
    names : tuple of str
        The expressions performed, the neutral first.
    activations : (F, M) float64
        The face's weights, a column per expression of the face (``key_clips``'s
        ``names``); column 0, the neutral's, is 0.
    held : tuple of (start, stop)
        Per performed name, the frames [start, stop) where it is held: the capture.
    """

    names: tuple[str, ...]
    activations: np.ndarray
    held: tuple[tuple[int, int], ...]


def key_clips(
    names: Sequence[str],
    *,
    keys: Sequence[str] | None = None,
    ramp: int = KEY_RAMP_FRAMES,
    hold: int = KEY_HOLD_FRAMES,
) -> KeyClips:
    """The neutral held, then each key: ``ramp`` frames rising, ``hold`` frames at 1.

    The face is back at rest at the start of each clip, as after a capture.

    Parameters
    ----------
    names : sequence of str
        The face's expressions, the neutral first: the activations' columns.
    keys : sequence of str, optional
        The expressions performed, in this order (default: all but the neutral); the
        others are skipped, as the calibration walk-through lets a performer skip.
    """
    if ramp < 0 or hold < 3:
        raise InputError(f"key clips need ramp >= 0 and hold >= 3 frames, got {ramp}, {hold}")
    column = {name: i for i, name in enumerate(names)}
    performed = list(names[1:]) if keys is None else list(keys)
    unknown = [name for name in performed if name not in column or column[name] == 0]
    if unknown or len(set(performed)) != len(performed):
        raise InputError(
            f"keys: each an expression of the face other than the neutral, once; got "
            f"{(unknown or performed)[0]!r}",
            code="unknown_expression",
        )
    rise = (np.arange(1, ramp + 1) / (ramp + 1.0)) if ramp else np.zeros(0)
    rise = rise * rise * (3.0 - 2.0 * rise)  # smoothstep: no jump at either end
    frames = hold + len(performed) * (ramp + hold)
    activations = np.zeros((frames, len(names)))
    held = [(0, hold)]
    start = hold
    for name in performed:
        i = column[name]
        activations[start : start + ramp, i] = rise
        activations[start + ramp : start + ramp + hold, i] = 1.0
        held.append((start + ramp, start + ramp + hold))
        start += ramp + hold
    return KeyClips(names=(names[0], *performed), activations=activations, held=tuple(held))


def captured_keys(
    points: npt.ArrayLike, clips: KeyClips, found: npt.ArrayLike | None = None
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Each key's captured points and held frames, as the calibration walk-through takes them.

    ``capture.robust_example`` (outliers out, the median) of the frames where the key is
    held and a face was found; a key with fewer than 3 such frames is not captured (the
    page refuses it), and the neutral must be.

    Parameters
    ----------
    points : (F, K, 3) float
        The key clips' points, tracked or exact (NaN where no face was found).
    found : (F,) bool, optional
        Default: the frames whose points are finite.

    Returns
    -------
    points : {name: (K, 3) float64}
    held : {name: (n, K, 3) float64}
        The frames each capture was made from (the server measures the noise on them).
    """
    x = np.asarray(points, dtype=np.float64)
    if x.ndim != 3 or x.shape[0] != len(clips.activations) or x.shape[2] != 3:
        raise InputError(
            f"key points: expected shape ({len(clips.activations)}, K, 3), got {x.shape}",
            code="wrong_point_count",
        )
    ok = np.asarray(np.isfinite(x).all(axis=(1, 2)))
    if found is not None:
        ok &= np.asarray(found, dtype=bool)
    captured: dict[str, np.ndarray] = {}
    held: dict[str, np.ndarray] = {}
    for name, (start, stop) in zip(clips.names, clips.held, strict=True):
        frames = x[start:stop][ok[start:stop]]
        if len(frames) < 3:
            continue
        captured[name], _, kept = robust_example(frames)
        held[name] = frames[kept]
    if clips.names[0] not in captured:
        raise InputError(
            "the neutral clip has fewer than 3 frames with a face: nothing to calibrate on",
            code="no_neutral",
        )
    return captured, held


def hold_last_found(points: npt.ArrayLike, found: npt.ArrayLike) -> np.ndarray:
    """(F, K, 3): each frame without a face replaced by the last one with (the first found
    frame before any), which is what a viewer keeps seeing while the tracker has lost it."""
    x = np.array(points, dtype=np.float64)
    ok = np.asarray(found, dtype=bool) & np.isfinite(x).all(axis=(1, 2))
    if not ok.any():
        raise InputError("no frame has a face", code="no_face")
    index = np.where(ok, np.arange(len(x)), -1)
    np.maximum.accumulate(index, out=index)
    index[index < 0] = int(np.argmax(ok))
    out: np.ndarray = x[index]
    return out


def on_generic_set(examples: ExampleSet, *, uploaded: bool = False) -> ExampleSet:
    """``examples`` (ICT's shapes under ARKit names) on facecast's shipped generic set:
    ICT's landmarks with the lids and the iris centres as the tracker sees ICT's generic
    face (README, option (z)), the set a character uploaded as a file is paired with. Every
    shape is kept, gaze too; with ``uploaded`` only those an upload pairs
    (``characters.generic_pairing``: gaze is left out, ``generic.GAZE_SHAPES``)."""
    if uploaded:
        paired, _ = generic_pairing(examples.names[1:])
        examples = examples.subset([name for name in examples.names[1:] if name in paired])
    shipped = generic_sources()
    found = {name: shipped.source_points(name) for name in examples.names}
    points = [p for p in found.values() if p is not None]
    if len(points) < len(found):
        missing = sorted(name for name, p in found.items() if p is None)
        raise InputError(f"facecast's generic set has no {missing}", code="missing_examples")
    return replace(examples, source_points=np.stack(points))


def source_on_neutral(examples: ExampleSet, neutral: npt.ArrayLike) -> ExampleSet:
    """``examples`` with every source example moved onto another view of its neutral.

    ``neutral`` (K, 3), e.g. the source face's neutral as a tracker sees it (its points lie
    millimetres from the face's landmark vertices: two definitions of the same landmarks),
    is put into the source's frame by the best similarity, and each source example becomes
    it plus the example's own displacement: the shapes' motion is kept, only the rest pose
    changes (README, "The eyes clip", option (k)).
    """
    points = examples.source_points
    x = np.asarray(neutral, dtype=np.float64)
    if x.shape != points.shape[1:] or not np.isfinite(x).all():
        raise InputError(
            f"neutral: expected finite points of shape {points.shape[1:]}, got {x.shape}",
            code="wrong_point_count",
        )
    rotation, scales, translation = similarity_transform(x[None], points[0], scale=True)
    placed = scales[0] * x @ rotation[0].T + translation[0]
    return replace(examples, source_points=points - points[0] + placed)


def generic_rig(
    character: Rig,
    neutral: npt.ArrayLike,
    noise: float | None,
    keys: Mapping[str, np.ndarray] | None = None,
    contrast: tuple[float, float] | None = None,
) -> Rig:
    """The generic path: the character's own rig re-based on the performer's captured
    neutral, as a ``calibrate`` carrying the held frames' ``noise`` asks the server to
    (/perform sends one for a rig that is not the performer's): ``rebase.calibrate``. With
    ``keys`` (a capture), its closed eyes go with it (``blinks``), as /perform sends the
    walk-through's captured ``eyeBlinkLeft`` / ``eyeBlinkRight`` with the neutral, read
    through the blink curve ``contrast`` (calibrate ``blink_contrast``: ``?blink=`` on
    /perform, ``--blink-contrast`` on ``facecast perform``; None: the server's, as a client
    that sends none gets).
    """
    if noise is None or keys is None:
        return calibrate(character, neutral, noise)
    k = np.asarray(neutral).shape[0]
    blinks = {name: keys[name][:k] for name in CLOSURE_NAMES if name in keys}
    return calibrate(character, neutral, noise, blinks or None, contrast if blinks else None)


def score(
    truth: np.ndarray,
    rig: Rig,
    weights: np.ndarray,
    activations: np.ndarray,
    names: Sequence[str],
) -> dict[str, Any]:
    """A cloned take against the truth: eq. 4.1 per axis, RMS, max, jitter, and weights.

    Parameters
    ----------
    truth : (F, V, 3)
        The ideal clone.
    rig : Rig
        Blends ``weights`` (its names, its target).
    weights : (F, M') float
        In ``rig.names`` order.
    activations : (F, M) float
        The true weights, in ``names`` order (a name the rig lacks counts as weight 0).

    Returns
    -------
    dict (JSON-able)
        ``cloning_error``'s figures without the series, ``weight_rms`` {name: RMS over
        the frames of the weight's error}, for every name but the neutral, and ``closures``
        {eyeBlinkLeft / eyeBlinkRight: ``eye_closures``} for those of ``names``.
    """
    vertices = rig.blend(np.asarray(weights, dtype=np.float64))
    errors = cloning_error(truth, vertices)
    errors.pop("per_frame", None)
    column = {name: i for i, name in enumerate(rig.names)}
    rms = {}
    for j, name in enumerate(names[1:], start=1):
        got = weights[:, column[name]] if name in column else 0.0
        rms[name] = float(np.sqrt(np.mean((got - activations[:, j]) ** 2)))
    errors["weight_rms"] = rms
    errors["closures"] = {
        name: eye_closures(weights[:, column[name]] if name in column else np.zeros(len(weights)),
                           activations[:, names.index(name)])
        for name in CLOSURE_NAMES
        if name in names
    }  # fmt: skip
    return errors


def eye_closures(
    estimated: npt.ArrayLike,
    truth: npt.ArrayLike,
    *,
    level: float = CLOSURE_LEVEL,
    margin: int = CLOSURE_MARGIN,
) -> dict[str, Any]:
    """A take's eye closures (the runs of frames where ``truth`` >= ``level``), each with
    the estimate's peak as a share of the truth's, and the whole series' correlation.

    The eyes clip's blinks are made, 5 frames each; a real take's are a real performer's,
    as long and as one-sided as they came (ARKit's reading of them).

    Parameters
    ----------
    estimated, truth : (F,) float
        One weight's estimate and truth, frame by frame.

    Returns
    -------
    dict (JSON-able)
        ``events``: per closure its ``start`` frame, ``frames`` (the run's length) and
        ``share`` (the estimate's peak over the truth's, both over the run and ``margin``
        frames either side); ``correlation``: Pearson's r of the two series, None when
        either is constant.
    """
    got = np.asarray(estimated, dtype=np.float64)
    true = np.asarray(truth, dtype=np.float64)
    if got.ndim != 1 or got.shape != true.shape:
        raise InputError(
            f"closures: expected two series of one length, got {got.shape} and {true.shape}",
            code="bad_input",
        )
    closed = np.concatenate([[False], true >= level, [False]])
    edges = np.flatnonzero(np.diff(closed.astype(np.int8)))
    events = []
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        around = slice(max(0, start - margin), min(len(true), stop + margin))
        events.append({"start": int(start), "frames": int(stop - start),
                       "share": float(got[around].max() / true[around].max())})  # fmt: skip
    steady = got.std() == 0 or true.std() == 0
    correlation = None if steady else float(np.corrcoef(got, true)[0, 1])
    return {"events": events, "correlation": correlation}


def superposition(
    take_points: npt.ArrayLike,
    keys: Mapping[str, np.ndarray],
    activations: npt.ArrayLike,
    names: Sequence[str],
    *,
    window: int = 7,
) -> tuple[np.ndarray, float, float]:
    """How far a take's points are from the same mix of its captured keys.

    A tracker that superposed expressions would give S_B + sum_i w_i (S_i - S_B) for the
    true weights w and the captured keys S_i; what it gives instead is the error no rig
    fitted on those keys can undo.

    Parameters
    ----------
    take_points : (F, K, 3)
    keys : {name: (K, 3)}
        The captured keys, the neutral (``names[0]``) among them; a name not captured
        counts as not moving the points.
    activations : (F, M)
        The true weights, in ``names`` order.
    window : int
        Frames of the centred moving average that separates the slow part.

    Returns
    -------
    mix : (F, K, 3)
        The keys mixed by the true weights.
    rms : float
        RMS over frames and coordinates of ``take_points - mix``.
    slow_rms : float
        The same of its centred ``window``-frame moving average: the part frame noise
        does not explain.
    """
    points = np.asarray(take_points, dtype=np.float64)
    act = np.asarray(activations, dtype=np.float64)
    neutral = keys[names[0]]
    mix = np.broadcast_to(neutral, points.shape).copy()
    for j, name in enumerate(names[1:], start=1):
        if name in keys:
            mix += act[:, j, None, None] * (keys[name] - neutral)
    residual = points - mix
    half = window // 2
    padded = np.concatenate([residual[:1].repeat(half, 0), residual, residual[-1:].repeat(half, 0)])
    running = np.cumsum(np.concatenate([np.zeros((1, *residual.shape[1:])), padded]), axis=0)
    slow = (running[window:] - running[:-window]) / window
    return mix, float(np.sqrt(np.mean(residual**2))), float(np.sqrt(np.mean(slow**2)))


def webcam_rows(
    character: Rig,
    truth: np.ndarray,
    activations: np.ndarray,
    take_points: npt.ArrayLike,
    keys: Mapping[str, np.ndarray],
    *,
    noise: float,
    generic: Mapping[str, tuple[Rig, float | None]] | None = None,
    personal_also: Mapping[str, npt.ArrayLike] | None = None,
    contrast: tuple[float, float] | None = None,
) -> dict[str, dict[str, Any]]:
    """Clone one take's points by each path and score it against the truth.

    Parameters
    ----------
    character : Rig
        The character's rig (its target examples, names and settings; ``fit_performer``
        refits it on the keys).
    truth : (F, V, 3)
        The take's ideal clone on the character.
    activations : (F, M)
        The take's true weights, in ``character.names`` order.
    take_points : (F, K, 3)
        The take's feature points (tracked or exact; no NaN).
    keys : {name: (K, 3)}
        The captured key-expressions (``captured_keys``), the neutral included. K may
        exceed the character's points (a later layout's: ``fit_performer`` fits the
        personal rig on all K, a generic rig takes the first of them, as the page sends).
    noise : float
        The landmark noise the personal rig is fitted with (the server measures it from the
        held frames: ``server.performers.held_noise``).
    generic : {label: (Rig, noise or None)}, optional
        Rigs on the character's own examples, not yet re-based: each is re-based on the
        captured neutral (``generic_rig``: with the noise a ``calibrate`` carries, or
        exactly with None, as a calibrate without one) and scored as a row of its own.
    personal_also : {label: (F, K, 3)}, optional
        Other points for the same take, each cloned by the personal rig as a row
        ``"personal on <label>"`` (e.g. ``superposition``'s mix of the keys).
    contrast : (low, high), optional
        The generic rows' blink curve, as the client's calibrate sends it
        (``generic_rig``; None: the server's).

    Returns
    -------
    {label: score(...)}
        ``personal`` (the performer's own rig, fitted as the server fits it), ``nnls`` (its
        peer: non-negative least squares on the same captured keys and points), the
        ``personal_also`` rows, then one row per ``generic`` rig.
    """
    points = np.asarray(take_points, dtype=np.float64)
    names = character.names
    rows: dict[str, dict[str, Any]] = {}
    personal = fit_performer(character, keys, noise=noise)
    rows["personal"] = score(truth, personal, personal.weights(points), activations, names)
    captured = personal.names  # the keys captured, in the character's order
    examples = ExampleSet(
        names=captured,
        source_points=np.stack([keys["neutral" if i == 0 else n] for i, n in enumerate(captured)]),
        target_vertices=target_examples(personal),
        target_faces=personal.target_faces,
    )
    rows["nnls"] = score(truth, personal, nnls_weights(examples, points), activations, names)
    for label, other in (personal_also or {}).items():
        weights = personal.weights(np.asarray(other, dtype=np.float64))
        rows[f"personal on {label}"] = score(truth, personal, weights, activations, names)
    for label, (rig, rebase_noise) in (generic or {}).items():
        k = rig.num_points  # a take of a later layout (the iris after 24): the first k
        rebased = generic_rig(rig, keys["neutral"][:k], rebase_noise, keys, contrast)
        rows[label] = score(truth, rebased, rebased.weights(points[:, :k]), activations, names)
    return rows
