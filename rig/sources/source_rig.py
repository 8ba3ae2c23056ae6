"""The source rig: ARKit blendshape weights -> source feature points, through an example set.

Trackers such as Live Link Face send 52 ARKit weights, not points; a source rig with
ARKit-named shapes turns them into the points the cloning rig expects. Linear only: it
must not fit or evaluate the cloning rig, and does no network or tracker I/O.

Points of a frame with weights ``w`` (52,)::

    points = neutral + sum_k w_k (shape_k - neutral)

Head angles (yaw, pitch, roll) optionally rotate those points rigidly about the
neutral's centroid, so a bridged stream carries real head motion for the server's
``align`` to remove.

Shape names are matched case-insensitively, first to the ARKit name itself
(``eyeBlinkLeft``, ``EyeBlinkLeft``), else to ICT-FaceKit's names in
``ARKIT_TO_ICT``: ``Left``/``Right`` become ``_L``/``_R`` (``eyeBlink_L``), and ICT
splits ``browInnerUp`` and ``cheekPuff`` into a left and a right shape, which the ARKit
weight drives together. ICT has no ``tongueOut``: a set without a shape for an ARKit
name gets a zero delta there and lists the name in ``SourceRig.missing``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..characters.expression_names import ARKIT_NAMES
from ..characters.generic import GENERIC_SOURCE_NAME, generic_sources, is_generic_layout
from ..characters.loaders import load_example_set
from ..errors import ExampleSetError, InputError
from ..examples import ExampleSet
from ..npy_reads import NPY_READS
from .ict import ict_example_set

__all__ = [
    "ARKIT_NAMES",
    "ARKIT_TO_ICT",
    "HEAD_POSE_NAMES",
    "NUM_ARKIT",
    "SourceRig",
    "arkit_from_ict",
    "arkit_index",
    "generic_source_rig",
    "head_rotation",
    "load_source_rig",
    "names_generic_set",
]

NUM_ARKIT = len(ARKIT_NAMES)

#: The 9 extra Live Link Face values after the 52 weights, radians.
HEAD_POSE_NAMES: tuple[str, ...] = (
    "headYaw", "headPitch", "headRoll",
    "leftEyeYaw", "leftEyePitch", "leftEyeRoll",
    "rightEyeYaw", "rightEyePitch", "rightEyeRoll",
)  # fmt: skip

#: ARKit name -> the ICT-FaceKit shapes it drives (each at the ARKit weight).
ARKIT_TO_ICT: dict[str, tuple[str, ...]] = {
    "eyeBlinkLeft": ("eyeBlink_L",),
    "eyeLookDownLeft": ("eyeLookDown_L",),
    "eyeLookInLeft": ("eyeLookIn_L",),
    "eyeLookOutLeft": ("eyeLookOut_L",),
    "eyeLookUpLeft": ("eyeLookUp_L",),
    "eyeSquintLeft": ("eyeSquint_L",),
    "eyeWideLeft": ("eyeWide_L",),
    "eyeBlinkRight": ("eyeBlink_R",),
    "eyeLookDownRight": ("eyeLookDown_R",),
    "eyeLookInRight": ("eyeLookIn_R",),
    "eyeLookOutRight": ("eyeLookOut_R",),
    "eyeLookUpRight": ("eyeLookUp_R",),
    "eyeSquintRight": ("eyeSquint_R",),
    "eyeWideRight": ("eyeWide_R",),
    "jawForward": ("jawForward",),
    "jawLeft": ("jawLeft",),
    "jawRight": ("jawRight",),
    "jawOpen": ("jawOpen",),
    "mouthClose": ("mouthClose",),
    "mouthFunnel": ("mouthFunnel",),
    "mouthPucker": ("mouthPucker",),
    "mouthLeft": ("mouthLeft",),
    "mouthRight": ("mouthRight",),
    "mouthSmileLeft": ("mouthSmile_L",),
    "mouthSmileRight": ("mouthSmile_R",),
    "mouthFrownLeft": ("mouthFrown_L",),
    "mouthFrownRight": ("mouthFrown_R",),
    "mouthDimpleLeft": ("mouthDimple_L",),
    "mouthDimpleRight": ("mouthDimple_R",),
    "mouthStretchLeft": ("mouthStretch_L",),
    "mouthStretchRight": ("mouthStretch_R",),
    "mouthRollLower": ("mouthRollLower",),
    "mouthRollUpper": ("mouthRollUpper",),
    "mouthShrugLower": ("mouthShrugLower",),
    "mouthShrugUpper": ("mouthShrugUpper",),
    "mouthPressLeft": ("mouthPress_L",),
    "mouthPressRight": ("mouthPress_R",),
    "mouthLowerDownLeft": ("mouthLowerDown_L",),
    "mouthLowerDownRight": ("mouthLowerDown_R",),
    "mouthUpperUpLeft": ("mouthUpperUp_L",),
    "mouthUpperUpRight": ("mouthUpperUp_R",),
    "browDownLeft": ("browDown_L",),
    "browDownRight": ("browDown_R",),
    "browInnerUp": ("browInnerUp_L", "browInnerUp_R"),
    "browOuterUpLeft": ("browOuterUp_L",),
    "browOuterUpRight": ("browOuterUp_R",),
    "cheekPuff": ("cheekPuff_L", "cheekPuff_R"),
    "cheekSquintLeft": ("cheekSquint_L",),
    "cheekSquintRight": ("cheekSquint_R",),
    "noseSneerLeft": ("noseSneer_L",),
    "noseSneerRight": ("noseSneer_R",),
    "tongueOut": (),
}

_ARKIT_LOWER = {name.lower(): i for i, name in enumerate(ARKIT_NAMES)}


def arkit_index(name: str) -> int | None:
    """Position of an ARKit blendshape name (any case: ``EyeBlinkLeft``), or None."""
    return _ARKIT_LOWER.get(name.lower())


def head_rotation(angles: npt.ArrayLike) -> np.ndarray:
    """Rotation matrices of head (yaw, pitch, roll) angles in radians.

    ``R = R_y(yaw) @ R_x(pitch) @ R_z(roll)`` in the face's frame (+y up, +z forward,
    +x the subject's left), applied to column vectors: yaw turns about the vertical,
    pitch nods about the ear-to-ear axis, roll tilts about the nose axis.

    Parameters
    ----------
    angles : (..., 3) float

    Returns
    -------
    (..., 3, 3) float64
    """
    a = np.asarray(angles, dtype=np.float64)
    cy, sy = np.cos(a[..., 0]), np.sin(a[..., 0])
    cp, sp = np.cos(a[..., 1]), np.sin(a[..., 1])
    cr, sr = np.cos(a[..., 2]), np.sin(a[..., 2])
    zero, one = np.zeros_like(cy), np.ones_like(cy)
    ry = np.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], axis=-1)
    rx = np.stack([one, zero, zero, zero, cp, -sp, zero, sp, cp], axis=-1)
    rz = np.stack([cr, -sr, zero, sr, cr, zero, zero, zero, one], axis=-1)
    shape = (*a.shape[:-1], 3, 3)
    return ry.reshape(shape) @ rx.reshape(shape) @ rz.reshape(shape)


def arkit_from_ict(
    ict_names: Sequence[str], neutral: np.ndarray, shapes: np.ndarray, *, strict: bool = False
) -> tuple[tuple[str, ...], np.ndarray]:
    """ICT-FaceKit's shapes under their ARKit names: ``(names, meshes)``, neutral first.

    ``shapes[i]`` is the shape ``ict_names[i]`` (any trailing dimensions: meshes, feature
    points). Each ARKit shape in ``ARKIT_NAMES`` order is its ICT parts' deltas added to
    ``neutral`` (ICT splits ``browInnerUp`` and ``cheekPuff`` into halves); one with no ICT
    part (``tongueOut``) is left out, as is one whose parts are missing unless ``strict``,
    which raises ``ExampleSetError`` naming the first missing part.
    """
    index = {name: i for i, name in enumerate(ict_names)}
    names, meshes = ["neutral"], [neutral]
    for arkit in ARKIT_NAMES:
        parts = ARKIT_TO_ICT[arkit]
        if not parts:
            continue
        missing = [p for p in parts if p not in index]
        if missing:
            if strict:
                raise ExampleSetError(f"no ICT shape {missing[0]!r} (for {arkit})")
            continue
        names.append(arkit)
        meshes.append(neutral + sum(shapes[index[p]] - neutral for p in parts))
    return tuple(names), np.stack(meshes)


def _match(names: Sequence[str]) -> tuple[tuple[tuple[int, ...], ...], tuple[str, ...]]:
    """For each ARKit name, the example indices it drives; and the examples left unused."""
    by_lower: dict[str, int] = {}
    for i, name in enumerate(names):
        if i == 0:
            continue  # the neutral is the base, never a shape
        key = name.lower()
        if key in by_lower:
            raise ExampleSetError(
                f"source rig: examples {names[by_lower[key]]!r} and {name!r} differ only in "
                "case; ARKit names are matched case-insensitively",
                code="ambiguous_shape_name",
            )
        by_lower[key] = i
    used: set[int] = set()
    matched: list[tuple[int, ...]] = []
    for arkit in ARKIT_NAMES:
        own = by_lower.get(arkit.lower())
        if own is not None:
            picks: tuple[int, ...] = (own,)
        else:
            ict = [by_lower.get(n.lower()) for n in ARKIT_TO_ICT[arkit]]
            picks = (
                tuple(i for i in ict if i is not None) if all(i is not None for i in ict) else ()
            )
        used.update(picks)
        matched.append(picks)
    unused = tuple(names[i] for i in range(1, len(names)) if i not in used)
    return tuple(matched), unused


@dataclass(frozen=True, eq=False)
class SourceRig:
    """ARKit weights to source feature points: a neutral plus one delta per ARKit shape.

    Parameters
    ----------
    neutral : (K, 3) float64
        Feature points of the neutral face.
    deltas : (52, K, 3) float64
        ``shape_k - neutral`` per ARKit name in ``ARKIT_NAMES`` order (summed over the
        shapes an ARKit name drives; zero where the set has none).
    shapes : tuple of 52 tuples of str
        The example names each ARKit weight drives (empty: missing).
    unused : tuple of str
        Examples of the set that match no ARKit name (ignored).
    """

    neutral: np.ndarray
    deltas: np.ndarray
    shapes: tuple[tuple[str, ...], ...]
    unused: tuple[str, ...] = ()
    # Made by __post_init__: the deltas as (52, 3K) and the neutral's centroid (3,).
    _flat: np.ndarray = field(init=False, repr=False)
    _centroid: np.ndarray = field(init=False, repr=False)

    def first(self, k: int) -> SourceRig:
        """This rig on its first ``k`` points: a layout's earlier version (the generic set
        has the layout's 26 points; a rig fitted on its first 24 or 20 takes those)."""
        if not 1 <= k <= self.num_points:
            raise ExampleSetError(f"source rig: {k} of its {self.num_points} points")
        return SourceRig(self.neutral[:k], self.deltas[:, :k], self.shapes, self.unused)

    def __post_init__(self) -> None:
        neutral = np.asarray(self.neutral, dtype=np.float64)
        deltas = np.asarray(self.deltas, dtype=np.float64)
        if neutral.ndim != 2 or neutral.shape[1] != 3 or neutral.shape[0] < 1:
            raise ExampleSetError(f"source rig neutral: expected (K, 3), got {neutral.shape}")
        if deltas.shape != (NUM_ARKIT, *neutral.shape):
            raise ExampleSetError(
                f"source rig deltas: expected ({NUM_ARKIT}, {neutral.shape[0]}, 3), got "
                f"{deltas.shape}"
            )
        if len(self.shapes) != NUM_ARKIT:
            raise ExampleSetError(f"source rig: expected {NUM_ARKIT} shape entries")
        if not (np.isfinite(neutral).all() and np.isfinite(deltas).all()):
            raise ExampleSetError("source rig: NaN or Inf coordinates", code="non_finite")
        object.__setattr__(self, "neutral", neutral)
        object.__setattr__(self, "deltas", deltas)
        # (52, 3K): the hot path is one matrix product, like the cloning rig's blend.
        object.__setattr__(self, "_flat", np.ascontiguousarray(deltas.reshape(NUM_ARKIT, -1)))
        object.__setattr__(self, "_centroid", neutral.mean(axis=0))

    @classmethod
    def from_example_set(cls, example_set: ExampleSet) -> SourceRig:
        """Take the source side of ``example_set``: example 0 is the neutral.

        Raises
        ------
        ExampleSetError
            ``no_arkit_shapes`` when no example matches an ARKit name;
            ``ambiguous_shape_name`` when two names differ only in case.
        """
        names = example_set.names
        matched, _ = _match(names)
        if not any(matched):
            raise ExampleSetError(
                f"source rig: none of the examples ({', '.join(names[1:6])}"
                f"{', ...' if len(names) > 6 else ''}) is named after an ARKit blendshape "
                "(e.g. eyeBlinkLeft or ICT's eyeBlink_L)",
                code="no_arkit_shapes",
            )
        return _from_named_points(names, example_set.source_points)

    @property
    def num_points(self) -> int:
        """K, the feature points produced per frame."""
        return int(self.neutral.shape[0])

    @property
    def missing(self) -> tuple[str, ...]:
        """ARKit names this rig has no shape for (their weights are ignored)."""
        return tuple(n for n, s in zip(ARKIT_NAMES, self.shapes, strict=True) if not s)

    def points(self, weights: npt.ArrayLike, *, head: npt.ArrayLike | None = None) -> np.ndarray:
        """Feature points for ARKit weights, optionally turned by head angles.

        Parameters
        ----------
        weights : (52,) or (F, 52) float
            In ``ARKIT_NAMES`` order.
        head : (3,) or (F, 3) float, optional
            Head yaw, pitch, roll in radians (see `head_rotation`); the points are
            rotated about the neutral's centroid.

        Returns
        -------
        (K, 3) or (F, K, 3) float64
        """
        w = np.asarray(weights, dtype=np.float64)
        single = w.ndim == 1
        batch = w[None] if single else w
        if batch.ndim != 2 or batch.shape[1] != NUM_ARKIT:
            raise InputError(
                f"ARKit weights: expected shape ({NUM_ARKIT},) or (F, {NUM_ARKIT}), got {w.shape}",
                code="bad_weights",
            )
        if not np.isfinite(batch).all():
            raise InputError("ARKit weights: NaN or Inf values", code="non_finite")
        out: np.ndarray = (batch @ self._flat).reshape(batch.shape[0], -1, 3)
        out += self.neutral
        if head is not None:
            angles = np.asarray(head, dtype=np.float64).reshape(-1, 3)
            if angles.shape[0] != batch.shape[0] or not np.isfinite(angles).all():
                raise InputError(
                    f"head angles: expected {batch.shape[0]} finite (yaw, pitch, roll) "
                    f"triples, got shape {np.shape(head)}",
                    code="bad_head_pose",
                )
            centroid = self._centroid
            out = np.einsum("fij,fkj->fki", head_rotation(angles), out - centroid) + centroid
        return out[0] if single else out


def _is_ict_archive(path: Path) -> bool:
    if path.is_file():
        return path.name == "ict_facekit.npz"
    return (path / "ict_facekit.npz").is_file() and not (path / "facecast.toml").exists()


def generic_source_rig() -> SourceRig:
    """facecast's shipped generic ARKit source set (``characters.generic``) as a source rig.

    Its 20 points are the ones a character uploaded as a file is paired with, so ARKit
    weights turned into points by it drive any such character (``tongueOut`` has no shape).
    """
    generic = generic_sources()
    return _from_named_points(generic.names, generic.points)


def _from_named_points(names: Sequence[str], points: np.ndarray) -> SourceRig:
    neutral = points[0]
    matched, unused = _match(names)
    deltas = np.zeros((NUM_ARKIT, *neutral.shape))
    for k, picks in enumerate(matched):
        for i in picks:
            deltas[k] += points[i] - neutral
    shapes = tuple(tuple(names[i] for i in picks) for picks in matched)
    if not any(shapes):
        raise ExampleSetError(
            "source rig: none of the set's names is an ARKit blendshape", code="no_arkit_shapes"
        )
    return SourceRig(neutral=neutral, deltas=deltas, shapes=shapes, unused=unused)


def _generic_layout_rig(path: Path) -> SourceRig | None:
    """A source rig from an .npz in the generic set's layout (``names``, ``points`` ...),
    such as ``generic_arkit/points.npz`` itself; None for any other file."""
    if not (path.is_file() and path.suffix.lower() == ".npz"):
        return None
    try:
        with NPY_READS, path.open("rb") as handle, np.load(handle, allow_pickle=False) as data:
            if not is_generic_layout(data.files):
                return None
            names = tuple(str(n) for n in data["names"])
            points = np.asarray(data["points"], dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise ExampleSetError(
            f"{path.name}: not a readable source set ({type(exc).__name__})", code="bad_file"
        ) from None
    if points.ndim != 3 or points.shape[0] != len(names) or points.shape[2] != 3 or not names:
        raise ExampleSetError(
            f"{path.name}: points must be (len(names), K, 3), got {points.shape}",
            code="bad_file",
        )
    if names[0] != "neutral":
        raise ExampleSetError(f"{path.name}: the first name must be 'neutral'", code="bad_file")
    return _from_named_points(names, points)


def names_generic_set(spec: SourceRig | str | os.PathLike[str] | None) -> bool:
    """Whether ``spec`` (as ``load_source_rig`` takes it) is facecast's generic set: its
    word, or an .npz in its layout. Such a set's points are the landmark layout's, in
    order, so a rig fitted on the layout's earlier version takes its first K."""
    if spec is None or isinstance(spec, SourceRig):
        return False
    if str(spec) == GENERIC_SOURCE_NAME and not Path(spec).exists():
        return True
    path = Path(spec)
    if not (path.is_file() and path.suffix.lower() == ".npz"):
        return False
    try:
        with NPY_READS, path.open("rb") as handle, np.load(handle, allow_pickle=False) as data:
            return is_generic_layout(data.files)
    except (OSError, ValueError):
        return False


def load_source_rig(path: str | os.PathLike[str]) -> SourceRig:
    """A source rig from an ARKit-named example set on disk, or facecast's generic set.

    Parameters
    ----------
    path : path-like
        ``"generic"`` (facecast's shipped generic ARKit set, what characters uploaded as
        files are paired with), an .npz in that set's layout (``generic_arkit/points.npz``),
        anything ``load_example_set`` reads (e.g. the folder ``facecast import
        ict-facekit`` writes), or the ICT-FaceKit archive ``ict_facekit.npz`` / its folder
        (ICT's own shape names, default landmarks).

    Raises
    ------
    ExampleSetError
    """
    if str(path) == GENERIC_SOURCE_NAME and not Path(path).exists():
        return generic_source_rig()
    path = Path(path)
    if _is_ict_archive(path):
        return SourceRig.from_example_set(ict_example_set(path))
    generic_layout = _generic_layout_rig(path)
    if generic_layout is not None:
        return generic_layout
    return SourceRig.from_example_set(load_example_set(path))
