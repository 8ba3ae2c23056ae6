"""Loading an ``ExampleSet`` from disk: a facecast.toml folder, an .npz, or a glTF target.

Resolves and checks every path and every file, naming the file or example at fault;
it must not fit or evaluate anything (that is ``fit``), nor read outside the set's folder.
"""

from __future__ import annotations

import dataclasses
import os
import re
import tomllib
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ..errors import ExampleSetError
from ..examples import ExampleSet
from ..io.meshio import read_obj, read_obj_vertices, read_points
from ..npy_reads import NPY_READS
from .character import load_character
from .character_examples import character_example_set, folder_stable_points
from .expression_names import normalise_name

__all__ = ["load_example_set"]

MANIFEST = "facecast.toml"
FEATURE_POINTS_FILE = "feature_points.txt"
_MESH_SUFFIXES = (".obj",)
_POINT_SUFFIXES = (".npy", ".csv")
_SOURCE_SUFFIXES = _MESH_SUFFIXES + _POINT_SUFFIXES
#: Files ``load_character`` reads: a character paired with the generic ARKit set.
CHARACTER_SUFFIXES = (".glb", ".gltf", ".vrm")

T = TypeVar("T")
_NPZ_REQUIRED = ("names", "source_points", "target_vertices", "target_faces")
_NPZ_OPTIONAL = ("source_vertices", "source_faces", "feature_indices", "stable_points")


def load_example_set(
    path: str | os.PathLike[str],
    *,
    source: str | os.PathLike[str] | None = None,
    allow_unpaired: bool = False,
) -> ExampleSet:
    """Load an example set from a folder, an ``.npz`` or a glTF/GLB target.

    Parameters
    ----------
    path : path-like
        One of:

        - a folder holding ``facecast.toml`` (or the toml file itself): ``[source]
          neutral`` and ``feature_points`` (0-based indices, for .obj sources),
          ``[target] neutral``, ``[examples] name = [source file, target file]``,
          paths relative to the folder; or ``[target] gltf`` + ``[source] folder``;
        - an ``.npz`` written by ``ExampleSet.save_npz``;
        - a character, ``.glb``/``.gltf``/``.vrm``, read by ``character.load_character``
          (expressions from every mesh and VRM binds, names normalised, the face mesh as
          the target; docs/characters.md): without ``source``, paired with facecast's
          generic ARKit source set (``character_examples.character_example_set``); with
          ``source``, with the files there whose names normalise alike (the form
          facecast.toml's ``[target] gltf`` uses too).
    source : path-like, optional
        For a character: the folder holding ``neutral.obj|.npy|.csv`` and one
        ``<name>.obj|.npy|.csv`` per expression (plus ``feature_points.txt`` or a
        ``facecast.toml`` with ``[source] feature_points`` when the files are meshes);
        ``[source] stable_points`` of a facecast.toml there, or of the parent's that
        names this folder's neutral, are kept.
    allow_unpaired : bool
        For a character with ``source``: skip, with a warning, expressions without a source file
        and source files without a morph target, instead of raising.

    Returns
    -------
    ExampleSet
        Example 0 is named ``"neutral"``.

    Raises
    ------
    ExampleSetError
        Any missing, unreadable, mismatched or unsafe input, naming the file or example.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if path.is_dir() or path.name == MANIFEST:
        if source is not None:
            raise ExampleSetError(f"{path}: `source` is only for glTF targets", code="bad_argument")
        return _load_manifest(path if path.is_dir() else path.parent, allow_unpaired)
    if suffix == ".npz":
        return _load_npz(path)
    if suffix in CHARACTER_SUFFIXES:
        if source is not None:
            return _load_gltf_pair(path, Path(source), allow_unpaired, feature_points=None)
        character = load_character(path, label=path.name)
        example_set, _ = character_example_set(character, label=path.name)
        return example_set
    if not path.exists():
        raise ExampleSetError(f"{path}: no such file or folder", code="missing_file")
    raise ExampleSetError(
        f"{path}: not an example set (expected a folder with {MANIFEST}, .npz, or a character: "
        ".glb, .gltf or .vrm)",
        code="bad_example_set",
    )


# -- (a) folder with facecast.toml -----------------------------------------------------


def _inside(folder: Path, relative: object, where: str) -> Path:
    """Resolve ``relative`` against ``folder``; refuse anything that leaves it."""
    if not isinstance(relative, str) or not relative:
        raise ExampleSetError(f"{where}: expected a relative file path, got {relative!r}")
    root = folder.resolve()
    resolved = (root / relative).resolve()
    if Path(relative).is_absolute() or not resolved.is_relative_to(root):
        raise ExampleSetError(
            f"{where}: path {relative!r} leaves the example-set folder {folder}",
            code="path_escape",
        )
    return resolved


def _table(
    doc: dict[str, Any], key: str, manifest: Path, *, required: bool = True
) -> dict[str, Any]:
    value = doc.get(key)
    if value is None and not required:
        return {}
    if not isinstance(value, dict):
        raise ExampleSetError(f"{manifest}: missing [{key}] table", code="bad_manifest")
    return value


def _read_manifest(manifest: Path) -> dict[str, Any]:
    try:
        with manifest.open("rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise ExampleSetError(f"{manifest}: file not found", code="missing_file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ExampleSetError(f"{manifest}: malformed TOML ({exc})", code="bad_manifest") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ExampleSetError(f"{manifest}: cannot read ({exc})", code="bad_manifest") from None


def _load_manifest(folder: Path, allow_unpaired: bool) -> ExampleSet:
    """Folder layout::

        [source]
        neutral = "source/neutral.obj"        # or .npy/.csv K x 3 points
        feature_points = [1225, 1888, 1052]   # or "source/feature_points.txt"; meshes only
        stable_points = [0, 1, 2]             # optional: feature-point positions for align
        [target]
        neutral = "target/neutral.obj"
        [examples]                            # name = [source file, target file]
        happy = ["source/happy.obj", "target/happy.obj"]

    or, for a glTF target, ``[target] gltf = "..."`` with ``[source] folder = "..."``.
    """
    manifest = folder / MANIFEST
    doc = _read_manifest(manifest)
    source = _table(doc, "source", manifest)
    target = _table(doc, "target", manifest)
    indices = _feature_indices(source.get("feature_points"), folder, manifest)
    stable = source.get("stable_points")

    if "gltf" in target:
        gltf = _inside(folder, target["gltf"], f"{manifest} [target] gltf")
        src_folder = _inside(folder, source.get("folder", "."), f"{manifest} [source] folder")
        example_set = _load_gltf_pair(gltf, src_folder, allow_unpaired, feature_points=indices)
        return _with_stable_points(example_set, stable, manifest)

    examples = _table(doc, "examples", manifest, required=False)
    names = ["neutral"]
    pairs = [
        (
            _inside(folder, source.get("neutral"), f"{manifest} [source] neutral"),
            _inside(folder, target.get("neutral"), f"{manifest} [target] neutral"),
        )
    ]
    for name, pair in examples.items():
        where = f"{manifest} [examples] {name}"
        if name == "neutral":
            raise ExampleSetError(
                f"{where}: 'neutral' is reserved for the [source]/[target] neutral",
                code="bad_manifest",
            )
        if not (isinstance(pair, list) and len(pair) == 2):
            raise ExampleSetError(
                f"{where}: expected [source file, target file], got {pair!r}", code="bad_manifest"
            )
        names.append(name)
        pairs.append((_inside(folder, pair[0], where), _inside(folder, pair[1], where)))
    if len(names) < 2:
        raise ExampleSetError(
            f"{manifest}: need at least 2 examples (the neutral and one in [examples]), "
            f"got {len(names)}",
            code="too_few_examples",
        )

    target_vertices, target_faces = _read_targets(names, [t for _, t in pairs])
    sources = _read_sources(names, [s for s, _ in pairs], indices, manifest)
    example_set = _build(names, sources, target_vertices, target_faces)
    return _with_stable_points(example_set, stable, manifest)


def _with_stable_points(example_set: ExampleSet, value: object, manifest: Path) -> ExampleSet:
    """The set with ``[source] stable_points`` (positions among the feature points)."""
    if value is None:
        return example_set
    if not (
        isinstance(value, list)
        and all(isinstance(i, int) and not isinstance(i, bool) for i in value)
    ):
        raise ExampleSetError(
            f"{manifest}: [source] stable_points must be a list of feature-point positions "
            f"(0-based, among the K feature points), got {value!r}",
            code="bad_stable_points",
        )
    try:
        return dataclasses.replace(example_set, stable_points=np.asarray(value, dtype=np.int64))
    except ExampleSetError as exc:
        raise ExampleSetError(f"{manifest}: [source] {exc.message}", code=exc.code) from None


def _feature_indices(value: object, folder: Path, manifest: Path | str) -> np.ndarray | None:
    if value is None:
        return None
    if isinstance(value, str):
        return _read_index_file(_inside(folder, value, f"{manifest} [source] feature_points"))
    if (
        not isinstance(value, list)
        or not value
        or not all(isinstance(i, int) and not isinstance(i, bool) for i in value)
    ):
        raise ExampleSetError(
            f"{manifest}: [source] feature_points must be a non-empty list of vertex indices",
            code="bad_manifest",
        )
    return np.asarray(value, dtype=np.int64)


def _read_index_file(path: Path) -> np.ndarray:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ExampleSetError(f"{path}: file not found", code="missing_file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ExampleSetError(f"{path}: cannot read ({exc})", code="bad_feature_points") from None
    tokens: list[str] = []
    for line in text.splitlines():
        tokens.extend(t for t in re.split(r"[\s,]+", line.split("#", 1)[0]) if t)
    try:
        indices = np.array([int(t) for t in tokens], dtype=np.int64)
    except ValueError:
        raise ExampleSetError(
            f"{path}: feature points must be integers (0-based vertex indices)",
            code="bad_feature_points",
        ) from None
    if indices.size == 0:
        raise ExampleSetError(f"{path}: no feature point indices", code="bad_feature_points")
    return indices


def _read(name: str, reader: Callable[[Path], T], path: Path) -> T:
    """``reader(path)``, with the example's name added to any error."""
    try:
        return reader(path)
    except ExampleSetError as exc:
        raise ExampleSetError(f"example {name!r}: {exc.message}", code=exc.code) from None


def _stack_examples(
    names: list[str],
    files: list[Path],
    neutral: np.ndarray,
    reader: Callable[[Path], np.ndarray],
    role: str,
    unit: str,
) -> np.ndarray:
    """Stack the neutral, already read from ``files[0]``, with every other example's file.

    Parameters
    ----------
    names, files : M each
        The examples and their files; ``files[0]`` is the neutral's.
    neutral : (N, 3) float
    reader : callable
        ``reader(path) -> (N', 3)`` for the other examples' files.
    role, unit : str
        How the error names the files ("source", "target") and their rows ("vertices",
        "points").

    Returns
    -------
    (M, N, 3) float64

    Raises
    ------
    ExampleSetError
        ``vertex_count_mismatch``/``point_count_mismatch`` naming the first example whose
        row count differs from the neutral's.
    """
    stacked = np.empty((len(names), *neutral.shape))
    stacked[0] = neutral
    for i in range(1, len(names)):
        example = _read(names[i], reader, files[i])
        if example.shape != neutral.shape:
            raise ExampleSetError(
                f"example {names[i]!r}: {role} {files[i]} has {example.shape[0]} {unit}, "
                f"the {role} neutral {files[0]} has {neutral.shape[0]}",
                code="vertex_count_mismatch" if unit == "vertices" else "point_count_mismatch",
            )
        stacked[i] = example
    return stacked


def _read_targets(names: list[str], files: list[Path]) -> tuple[np.ndarray, np.ndarray]:
    neutral, faces = _read(names[0], read_obj, files[0])
    vertices = _stack_examples(names, files, neutral, read_obj_vertices, "target", "vertices")
    return vertices, faces


def _read_sources(
    names: list[str], files: list[Path], indices: np.ndarray | None, manifest: Path | str
) -> _Sources:
    """Source points (and meshes) for each example: all meshes or all point files."""
    kinds = {f.suffix.lower() in _MESH_SUFFIXES for f in files}
    for name, f in zip(names, files, strict=True):
        if f.suffix.lower() not in _SOURCE_SUFFIXES:
            raise ExampleSetError(
                f"example {name!r}: source {f} is not .obj, .npy or .csv", code="bad_source"
            )
    if len(kinds) != 1:
        raise ExampleSetError(
            f"{manifest}: source files mix meshes (.obj) and point files (.npy/.csv)",
            code="bad_source",
        )
    meshes = kinds.pop()
    if meshes:
        if indices is None:
            raise ExampleSetError(
                f"{manifest}: source files are meshes, so [source] feature_points "
                "(0-based vertex indices) is required",
                code="bad_feature_points",
            )
        neutral, faces = _read(names[0], read_obj, files[0])
        vs = neutral.shape[0]
        if indices.min() < 0 or indices.max() >= vs:
            bad = int(indices[(indices < 0) | (indices >= vs)][0])
            raise ExampleSetError(
                f"{manifest}: feature point index {bad} is out of range for the source "
                f"neutral {files[0]} of {vs} vertices",
                code="index_out_of_range",
            )
        vertices = _stack_examples(names, files, neutral, read_obj_vertices, "source", "vertices")
        return _Sources(vertices[:, indices], vertices, faces, indices)
    if indices is not None:
        raise ExampleSetError(
            f"{manifest}: feature_points given but the source files are point files "
            "(.npy/.csv), which are the feature points already",
            code="bad_feature_points",
        )
    neutral = _read(names[0], read_points, files[0])
    points = _stack_examples(names, files, neutral, read_points, "source", "points")
    return _Sources(points)


@dataclasses.dataclass(frozen=True)
class _Sources:
    """What an example set's source files give: the feature points, and any meshes."""

    source_points: np.ndarray  # (M, K, 3)
    source_vertices: np.ndarray | None = None  # (M, Vs, 3)
    source_faces: np.ndarray | None = None  # (Fs, 3)
    feature_indices: np.ndarray | None = None  # (K,)


def _build(
    names: list[str], sources: _Sources, target_vertices: np.ndarray, target_faces: np.ndarray
) -> ExampleSet:
    return ExampleSet(
        names=tuple(names),
        source_points=sources.source_points,
        target_vertices=target_vertices,
        target_faces=target_faces,
        source_vertices=sources.source_vertices,
        source_faces=sources.source_faces,
        feature_indices=sources.feature_indices,
    )


# -- (b) .npz --------------------------------------------------------------------------


def _load_npz(path: Path) -> ExampleSet:
    try:
        # Our own handle: np.load leaks its file when the zip is corrupt.
        with NPY_READS, path.open("rb") as handle, np.load(handle, allow_pickle=False) as archive:
            missing = [k for k in _NPZ_REQUIRED if k not in archive.files]
            if missing:
                raise ExampleSetError(
                    f"{path}: not an example-set .npz (missing {', '.join(missing)})",
                    code="bad_npz",
                )
            arrays = {k: archive[k] for k in _NPZ_REQUIRED + _NPZ_OPTIONAL if k in archive.files}
    except ExampleSetError:
        raise
    except FileNotFoundError:
        raise ExampleSetError(f"{path}: file not found", code="missing_file") from None
    except Exception as exc:  # zipfile, zlib and numpy raise many types on a corrupt file
        raise ExampleSetError(
            f"{path}: not a readable .npz ({type(exc).__name__}: {exc})", code="bad_npz"
        ) from None
    names = arrays.pop("names")
    if names.ndim != 1 or names.dtype.kind not in "US":
        raise ExampleSetError(f"{path}: 'names' must be a 1-D array of strings", code="bad_npz")
    try:
        return ExampleSet(names=tuple(str(n) for n in names), **arrays)
    except ExampleSetError as exc:
        raise ExampleSetError(f"{path}: {exc.message}", code=exc.code) from None


# -- (c) glTF target paired by name with a source folder --------------------------------


def _load_gltf_pair(
    gltf: Path, folder: Path, allow_unpaired: bool, feature_points: np.ndarray | None
) -> ExampleSet:
    """A character (``load_character``: every mesh, VRM binds, names normalised, the face
    mesh by its rule) paired with the files of ``folder`` whose names normalise alike.

    Its own messages name the file and the folder by their names, not their paths (a
    server's upload folder is no one's business).
    """
    if not folder.is_dir():
        raise ExampleSetError(f"source folder {folder.name!r} not found", code="missing_file")
    character = load_character(gltf, label=gltf.name)

    by_name: dict[str, Path] = {}
    for file in sorted(folder.iterdir()):
        if file.is_file() and file.suffix.lower() in _SOURCE_SUFFIXES:
            name = normalise_name(file.stem).name or file.stem
            if name in by_name:
                raise ExampleSetError(
                    f"{folder}: two source files for {name!r} ({by_name[name].name}, {file.name})",
                    code="bad_source",
                )
            by_name[name] = file
    if "neutral" not in by_name:
        raise ExampleSetError(
            f"source folder {folder.name!r} has no source neutral (neutral.obj, neutral.npy or "
            "neutral.csv)",
            code="missing_file",
        )

    authored = {e.expression: e.authored for e in reversed(character.names) if e.expression}
    names = ["neutral"] + [n for n in character.expressions if n in by_name]
    unpaired_targets = [authored.get(n, n) for n in character.expressions if n not in by_name]
    unpaired_sources = [by_name[n].name for n in by_name if n not in names]
    rules = " (names compared as ARKit, Perfect Sync, _L/_R, VRM preset and Fcl_ names)"
    for kind, missing, hint in (
        (
            "morph target",
            unpaired_targets,
            f"has no source file in source folder {folder.name!r}{rules}",
        ),
        ("source file", unpaired_sources, f"has no morph target in {gltf.name}{rules}"),
    ):
        if not missing:
            continue
        message = f"{kind} {missing[0]!r} {hint}" + (
            f" (and {len(missing) - 1} more: {', '.join(missing[1:6])})" if len(missing) > 1 else ""
        )
        if not allow_unpaired:
            raise ExampleSetError(message, code="unpaired_example")
        warnings.warn(f"skipping unpaired examples: {message}", stacklevel=3)
    if len(names) < 2:
        raise ExampleSetError(
            f"{gltf.name}: need at least 2 examples (the neutral and one paired morph target), "
            f"got {len(names)}",
            code="too_few_examples",
        )

    files = [by_name[n] for n in names]
    if feature_points is None and files[0].suffix.lower() in _MESH_SUFFIXES:
        feature_points = _folder_feature_points(folder)
    sources = _read_sources(names, files, feature_points, folder)
    neutral = character.face_vertices
    targets = [neutral] + [neutral + character.expressions[n].face_displacement for n in names[1:]]
    example_set = _build(names, sources, np.stack(targets), character.face_faces)
    stable = folder_stable_points(folder)
    if stable is None:
        return example_set
    return _with_stable_points(example_set, stable.tolist(), folder / MANIFEST)


def _folder_feature_points(folder: Path) -> np.ndarray | None:
    index_file = folder / FEATURE_POINTS_FILE
    if index_file.is_file():
        return _read_index_file(index_file)
    manifest = folder / MANIFEST
    if manifest.is_file():
        source = _read_manifest(manifest).get("source", {})
        if isinstance(source, dict):
            return _feature_indices(source.get("feature_points"), folder, manifest)
    return None
