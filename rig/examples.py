"""The example set: M paired key-expressions, source feature points and target meshes.

Validates and normalises every array once, up front (shapes, dtypes, finiteness), so
the fitting code can assume clean input. It does no file I/O; see ``loaders``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from .errors import ExampleSetError

__all__ = ["MIN_NEUTRAL_RADIUS", "ExampleSet", "check_stable_points", "face_index_dtype"]

#: The source neutral must have extent: its radius (the RMS distance of its K points from
#: their centroid) must exceed this fraction of its largest coordinate's magnitude, else
#: the set is refused (``degenerate_neutral``). float32, in which points reach a rig,
#: resolves about 1e-7 of a coordinate; a neutral 100 times finer than that, or of one
#: point, or of K equal points, gives a rig whose point range (``rig.POINT_RANGE``, a
#: multiple of that radius) refuses every frame but the neutral itself. A face's neutral
#: is about 0.3 of its largest coordinate near the origin, 0.05 two metres away from it.
MIN_NEUTRAL_RADIUS = 1e-5


def face_index_dtype(num_vertices: int) -> type[np.signedinteger[Any]]:
    """The smallest signed integer type that indexes ``num_vertices`` vertices: int32 below
    2^31 (every mesh the limits let in), else int64. Triangles are held in it from the
    reader to the rig: a 2 M-triangle face is 24 MB of int32, 48 of int64."""
    return np.int32 if num_vertices <= np.iinfo(np.int32).max else np.int64


def _finite_array(
    name: str, value: npt.ArrayLike, dtype: npt.DTypeLike, ndim: int, where: str = ""
) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise ExampleSetError(f"{name}{where}: not a numeric array ({exc})") from None
    if array.ndim != ndim:
        raise ExampleSetError(f"{name}{where}: expected {ndim} dimensions, got shape {array.shape}")
    return array


def _face_array(name: str, value: npt.ArrayLike, num_vertices: int, where: str) -> np.ndarray:
    """(F, 3) triangles with indices in [0, num_vertices), as ``face_index_dtype``.

    Integer arrays are checked as given and converted once (int32 ones are not copied);
    anything else goes through int64, as it always did."""
    try:
        array = np.asarray(value)
        if not np.issubdtype(array.dtype, np.integer):
            array = np.asarray(value, dtype=np.int64)
    except (TypeError, ValueError) as exc:
        raise ExampleSetError(f"{name}: not a numeric array ({exc})") from None
    if array.ndim != 2:
        raise ExampleSetError(f"{name}: expected 2 dimensions, got shape {array.shape}")
    if array.size and array.shape[1] != 3:
        raise ExampleSetError(f"{name}: expected shape (F, 3), got {array.shape}")
    if array.size and (array.min() < 0 or array.max() >= num_vertices):
        raise ExampleSetError(
            f"{name}: indices must lie in [0, {num_vertices}){where}, "
            f"got [{array.min()}, {array.max()}]"
        )
    return array.astype(face_index_dtype(num_vertices), copy=False).reshape(-1, 3)


def _check_finite(name: str, array: np.ndarray, names: Sequence[str] | None = None) -> None:
    """Raise naming the first example (or the array) holding a NaN or Inf."""
    if np.isfinite(array).all():
        return
    if names is not None and array.ndim >= 2:
        flat = np.isfinite(array.reshape(array.shape[0], -1)).all(axis=1)
        bad = int(np.flatnonzero(~flat)[0])
        raise ExampleSetError(
            f"{name}: example {names[bad]!r} has NaN or Inf coordinates", code="non_finite"
        )
    raise ExampleSetError(f"{name}: NaN or Inf coordinates", code="non_finite")


def _check_neutral_extent(neutral: np.ndarray, name: str) -> None:
    """Refuse a source neutral (K, 3) without extent (see ``MIN_NEUTRAL_RADIUS``)."""
    d = neutral - neutral.mean(axis=0)
    radius = float(np.sqrt(np.vdot(d, d) / neutral.shape[0]))
    scale = float(np.abs(neutral).max())
    if not radius > MIN_NEUTRAL_RADIUS * scale:
        raise ExampleSetError(
            f"source_points: the neutral {name!r} has no extent (radius {radius:.3g}, the RMS "
            f"distance of its {neutral.shape[0]} points from their centroid, is not above "
            f"{MIN_NEUTRAL_RADIUS:g} of its largest coordinate {scale:.3g}): a rig needs "
            "at least two distinct feature points in its neutral",
            code="degenerate_neutral",
        )


def check_stable_points(value: npt.ArrayLike, num_points: int) -> np.ndarray:
    """Stable points as distinct positions in [0, K), at least 3 of them, or an error."""
    try:
        stable = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise ExampleSetError(
            f"stable_points: not an array ({exc})", code="bad_stable_points"
        ) from None
    if stable.ndim != 1 or stable.size < 3 or not np.issubdtype(stable.dtype, np.integer):
        raise ExampleSetError(
            f"stable_points: expected at least 3 feature-point positions (integers), got "
            f"{stable.tolist()!r}",
            code="bad_stable_points",
        )
    if stable.min() < 0 or stable.max() >= num_points:
        raise ExampleSetError(
            f"stable_points: positions must lie in [0, {num_points}) (the feature points, not "
            f"mesh vertices), got [{stable.min()}, {stable.max()}]",
            code="bad_stable_points",
        )
    if np.unique(stable).size != stable.size:
        raise ExampleSetError("stable_points: a point is named twice", code="bad_stable_points")
    return stable.astype(np.int64)


def _magnitude(array: np.ndarray) -> float:
    """The largest magnitude in ``array`` (NaN if it holds one), without a temporary."""
    return float(np.maximum(array.max(initial=0.0), -array.min(initial=0.0)))


def _displacements(
    given: Sequence[npt.ArrayLike], neutral: np.ndarray, names: Sequence[str]
) -> tuple[np.ndarray, ...]:
    """``target_displacements`` checked: M - 1 finite (V, 3) float arrays (float32 kept as
    float32, not copied), each of which keeps ``neutral + displacement`` finite."""
    if len(given) != len(names) - 1:
        raise ExampleSetError(
            f"target_displacements: expected {len(names) - 1} for {len(names)} examples, "
            f"got {len(given)}"
        )
    reach = _magnitude(neutral)
    out = []
    for name, value in zip(names[1:], given, strict=True):
        array = np.asarray(value)
        if array.dtype not in (np.float32, np.float64):
            array = _finite_array("target_displacements", array, np.float64, 2)
        if array.shape != neutral.shape:
            raise ExampleSetError(
                f"target_displacements: {name!r} has shape {array.shape}, the neutral "
                f"{neutral.shape}"
            )
        # Finite, and finite once added to the neutral (float64): their largest magnitudes'
        # sum bounds every sum's, without a temporary of the sums.
        if not np.isfinite(reach + _magnitude(array)):
            raise ExampleSetError(
                f"target_vertices: example {name!r} has NaN or Inf coordinates", code="non_finite"
            )
        out.append(array)
    return tuple(out)


@dataclass(frozen=True, eq=False)
class ExampleSet:
    """M paired key-expressions; example 0 is always the neutral pair.

    Parameters
    ----------
    names : sequence of M str
        Key-expression names, unique; ``names[0]`` is the neutral.
    source_points : (M, K, 3) float
        Feature points of each source example; ``source_points[0]`` is the source
        neutral S_B (thesis eq. 3.1).
    target_vertices : (M, V, 3) float
        Each target example's vertices; ``target_vertices[0]`` is the target base T_B.
    target_faces : (F, 3) int
        Triangles of the target mesh, 0-based; held as ``face_index_dtype`` (int32 below
        2^31 vertices).
    source_vertices : (M, Vs, 3) float, optional
        Full source meshes, when known (used for pictures and to select feature
        points from source animations given as meshes).
    source_faces : (Fs, 3) int, optional
    feature_indices : (K,) int, optional
        Vertex indices of the feature points in ``source_vertices``.
    stable_points : (S,) int, optional
        Positions among the K feature points that expressions move least (no jaw, no
        lips), S >= 3: where head-pose removal aligns each frame first (``fit`` keeps them
        on the rig).
    target_displacements : tuple of M - 1 (V, 3) float, optional
        The targets as displacements of the neutral, which is then ``target_vertices``'s
        only row (shape (1, V, 3)): target i is ``T_B + target_displacements[i - 1]``,
        added in float64. Each is kept as given (float32 or float64, not copied), so a set
        built from a character holds its morph targets once, not a float64 copy of the
        face per example; ``fit`` reads them example by example (``targets``), and
        ``target_examples`` makes the (M, V, 3) array for whoever needs it whole.
    """

    names: tuple[str, ...]
    source_points: np.ndarray
    target_vertices: np.ndarray
    target_faces: np.ndarray
    source_vertices: np.ndarray | None = None
    source_faces: np.ndarray | None = None
    feature_indices: np.ndarray | None = None
    stable_points: np.ndarray | None = None
    target_displacements: tuple[np.ndarray, ...] | None = None

    def __post_init__(self) -> None:
        names = tuple(str(n) for n in self.names)
        if len(names) < 2:
            raise ExampleSetError(
                f"need at least 2 examples (the neutral and one key-expression), got {len(names)}",
                code="too_few_examples",
            )
        seen: set[str] = set()
        for name in names:
            if not name:
                raise ExampleSetError("example names must not be empty")
            if name in seen:
                raise ExampleSetError(f"example name {name!r} appears twice")
            seen.add(name)
        m = len(names)

        src = _finite_array("source_points", self.source_points, np.float64, 3)
        if src.shape[0] != m or src.shape[2] != 3:
            raise ExampleSetError(
                f"source_points: expected shape ({m}, K, 3) for {m} examples, got {src.shape}"
            )
        if src.shape[1] < 1:
            raise ExampleSetError("source_points: need at least one feature point")
        _check_finite("source_points", src, names)

        tgt = _finite_array("target_vertices", self.target_vertices, np.float64, 3)
        displacements = self.target_displacements
        rows = m if displacements is None else 1
        if tgt.shape[0] != rows or tgt.shape[2] != 3:
            raise ExampleSetError(
                f"target_vertices: expected shape ({rows}, V, 3) for {m} examples, got {tgt.shape}"
            )
        _check_finite("target_vertices", tgt, names)
        if displacements is not None:
            displacements = _displacements(displacements, tgt[0], names)

        faces = _face_array("target_faces", self.target_faces, tgt.shape[1], "")

        src_vertices = self.source_vertices
        src_faces = self.source_faces
        indices = self.feature_indices
        if src_vertices is not None:
            src_vertices = _finite_array("source_vertices", src_vertices, np.float64, 3)
            if src_vertices.shape[0] != m or src_vertices.shape[2] != 3:
                raise ExampleSetError(
                    f"source_vertices: expected shape ({m}, Vs, 3), got {src_vertices.shape}"
                )
            _check_finite("source_vertices", src_vertices, names)
        if src_faces is not None:
            if src_vertices is None:
                raise ExampleSetError("source_faces given without source_vertices")
            src_faces = _face_array(
                "source_faces", src_faces, src_vertices.shape[1], " (of source_vertices)"
            )
        if indices is not None:
            indices = _finite_array("feature_indices", indices, np.int64, 1)
            if indices.shape[0] != src.shape[1]:
                raise ExampleSetError(
                    f"feature_indices: {indices.shape[0]} indices for {src.shape[1]} feature points"
                )
            if src_vertices is not None and (
                indices.min() < 0 or indices.max() >= src_vertices.shape[1]
            ):
                raise ExampleSetError(
                    f"feature_indices: indices must lie in [0, {src_vertices.shape[1]}), "
                    f"got [{indices.min()}, {indices.max()}]",
                    code="index_out_of_range",
                )

        stable = self.stable_points
        if stable is not None:
            stable = check_stable_points(stable, src.shape[1])
        # Shapes first: a set whose arrays do not even pair up is told so before this.
        _check_neutral_extent(src[0], names[0])

        object.__setattr__(self, "names", names)
        object.__setattr__(self, "source_points", src)
        object.__setattr__(self, "target_vertices", tgt)
        object.__setattr__(self, "target_faces", faces)
        object.__setattr__(self, "source_vertices", src_vertices)
        object.__setattr__(self, "source_faces", src_faces)
        object.__setattr__(self, "feature_indices", indices)
        object.__setattr__(self, "stable_points", stable)
        object.__setattr__(self, "target_displacements", displacements)

    @classmethod
    def from_source_meshes(
        cls,
        names: Sequence[str],
        source_vertices: npt.ArrayLike,
        feature_indices: npt.ArrayLike,
        target_vertices: npt.ArrayLike,
        target_faces: npt.ArrayLike,
        *,
        source_faces: npt.ArrayLike | None = None,
        stable_points: npt.ArrayLike | None = None,
    ) -> ExampleSet:
        """Build from full source meshes (M, Vs, 3) and 0-based feature vertex indices (K,)."""
        src = _finite_array("source_vertices", source_vertices, np.float64, 3)
        idx = _finite_array("feature_indices", feature_indices, np.int64, 1)
        if idx.size == 0:
            raise ExampleSetError("feature_indices: need at least one index")
        if idx.min() < 0 or idx.max() >= src.shape[1]:
            raise ExampleSetError(
                f"feature_indices: indices must lie in [0, {src.shape[1]}) for a source mesh "
                f"of {src.shape[1]} vertices, got [{idx.min()}, {idx.max()}]",
                code="index_out_of_range",
            )
        # Converted as __post_init__ would (it checks them again, cheaply): the fields are
        # arrays.
        return cls(
            names=tuple(names),
            source_points=src[:, idx, :],
            target_vertices=_finite_array("target_vertices", target_vertices, np.float64, 3),
            target_faces=np.asarray(target_faces),
            source_vertices=src,
            source_faces=None if source_faces is None else np.asarray(source_faces),
            feature_indices=idx,
            stable_points=None
            if stable_points is None
            else check_stable_points(stable_points, idx.size),
        )

    # -- derived views -----------------------------------------------------------------
    @property
    def num_examples(self) -> int:
        return len(self.names)

    @property
    def num_points(self) -> int:
        return int(self.source_points.shape[1])

    @property
    def num_vertices(self) -> int:
        return int(self.target_vertices.shape[1])

    @property
    def source_neutral(self) -> np.ndarray:
        """(K, 3) source base feature points S_B."""
        neutral: np.ndarray = self.source_points[0]
        return neutral

    @property
    def target_neutral(self) -> np.ndarray:
        """(V, 3) target base vertices T_B."""
        neutral: np.ndarray = self.target_vertices[0]
        return neutral

    @property
    def targets(self) -> np.ndarray | tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """The target examples as ``basis.build_blend_basis`` reads them: (M, V, 3) float64,
        or (T_B, displacements) for a set of ``target_displacements``."""
        if self.target_displacements is None:
            return self.target_vertices
        return self.target_vertices[0], self.target_displacements

    def target_examples(self) -> np.ndarray:
        """(M, V, 3) float64 target examples: ``target_vertices``, or made from the neutral
        and ``target_displacements`` (a new array each call)."""
        if self.target_displacements is None:
            return self.target_vertices
        neutral = self.target_vertices[0]
        out = np.empty((self.num_examples, *neutral.shape))
        out[:] = neutral
        for row, displacement in enumerate(self.target_displacements, start=1):
            out[row] += displacement
        return out

    def subset(self, names: Sequence[str]) -> ExampleSet:
        """A new set keeping the neutral and the named examples, in the given order."""
        index = {n: i for i, n in enumerate(self.names)}
        missing = [n for n in names if n not in index]
        if missing:
            raise ExampleSetError(f"no example named {missing[0]!r}")
        keep = [0] + [index[n] for n in names if index[n] != 0]
        pick = np.asarray(keep)
        displacements = self.target_displacements
        return ExampleSet(
            names=tuple(self.names[i] for i in keep),
            source_points=self.source_points[pick],
            target_vertices=self.target_vertices[pick] if displacements is None else
            self.target_vertices,
            target_faces=self.target_faces,
            source_vertices=None if self.source_vertices is None else self.source_vertices[pick],
            source_faces=self.source_faces,
            feature_indices=self.feature_indices,
            stable_points=self.stable_points,
            target_displacements=None if displacements is None else
            tuple(displacements[i - 1] for i in keep[1:]),
        )  # fmt: skip

    def save_npz(self, path: str | os.PathLike[str]) -> None:
        """Write the set as one ``.npz`` (no pickles), readable by ``load_example_set``."""
        arrays = {
            "names": np.asarray(self.names, dtype=str),
            "source_points": self.source_points,
            "target_vertices": self.target_examples().astype(np.float32),
            "target_faces": self.target_faces.astype(np.int32),
        }
        if self.source_vertices is not None:
            arrays["source_vertices"] = self.source_vertices.astype(np.float32)
        if self.source_faces is not None:
            arrays["source_faces"] = self.source_faces.astype(np.int32)
        if self.feature_indices is not None:
            arrays["feature_indices"] = self.feature_indices.astype(np.int64)
        if self.stable_points is not None:
            arrays["stable_points"] = self.stable_points.astype(np.int64)
        # allow_pickle=False: none of these is an object array (and saying so lets mypy see
        # that ``arrays`` cannot hold the flag).
        np.savez_compressed(path, allow_pickle=False, **arrays)
