"""A character's expressions paired with source points: the example set a rig is fitted from.

Pairs with facecast's generic ARKit source set (``characters.generic``) or a folder of point
files named by expression; the target side is the character's face mesh. It must not fit,
read the character file again or write anything.
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ExampleSetError
from ..examples import ExampleSet, check_stable_points
from ..io.meshio import read_points
from .character_model import Character, PairingReport, pair_report
from .expression_names import normalise_name
from .generic import (
    CHARACTER_FIT_DEFAULTS,
    DEPENDENT_RELATIVE,
    DRIVEN_SHARE,
    GENERIC_ATTRIBUTION,
    PART_COMPOSITIONS,
    PRESET_CHECK_ORDER,
    generic_sources,
    is_gaze,
)

__all__ = [
    "character_example_set",
    "character_fit_options",
    "folder_stable_points",
    "generic_pairing",
]

_POINT_SUFFIXES = (".npy", ".csv")
_MANIFEST = "facecast.toml"


def _no_expressions(label: str) -> ExampleSetError:
    return ExampleSetError(
        f"{label} has no expressions: no morph target and no VRM expression moves it, so "
        "there is nothing to drive. Make its key-expressions by deformation transfer with "
        "`facecast expressions CHARACTER -o FOLDER` (ICT-FaceKit's ARKit shapes carried onto "
        "its neutral) and fit that folder, or add ARKit-named morph targets in your modelling "
        "tool",
        code="no_expressions",
    )


def character_fit_options(given: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """``fit`` keyword arguments for a character paired with the generic ARKit set.

    ``given`` holds the options its uploader chose (``fit``'s keywords; a key absent or None
    is not chosen). Without a ``noise``, the rig is fitted for the noise of a live tracker,
    ``characters.generic.CHARACTER_FIT_DEFAULTS`` (and bounded as it says unless a ``clamp`` is
    given), so the character is live the moment it is uploaded; a given ``noise`` (0 too:
    exact interpolation) keeps ``fit``'s own default bound for it.
    """
    options = {key: value for key, value in (given or {}).items() if value is not None}
    if "noise" not in options:
        options["noise"] = CHARACTER_FIT_DEFAULTS["noise"]
        options.setdefault("clamp", CHARACTER_FIT_DEFAULTS["clamp"])
    return options


def folder_stable_points(folder: Path) -> np.ndarray | None:
    """``[source] stable_points`` of the ``facecast.toml`` in ``folder``, or of its parent's
    when that file's ``[source] neutral`` lies in ``folder`` (``facecast import``'s
    ``source/``); None when neither says."""
    for manifest in (folder / _MANIFEST, folder.parent / _MANIFEST):
        if not manifest.is_file():
            continue
        try:
            doc = tomllib.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            raise ExampleSetError(
                f"{manifest.name} beside the source folder is not readable TOML",
                code="bad_manifest",
            ) from None
        source = doc.get("source")
        if not isinstance(source, dict) or source.get("stable_points") is None:
            continue
        neutral = source.get("neutral")
        if manifest.parent == folder or (
            isinstance(neutral, str)
            and (manifest.parent / neutral).resolve().parent == folder.resolve()
        ):
            return np.asarray(source["stable_points"])
    return None


def _folder_sources(folder: Path) -> tuple[dict[str, np.ndarray], np.ndarray | None, str]:
    """Point files of ``folder`` by normalised name, the stable points its facecast.toml
    (or its parent's, when that names this folder's neutral) gives, and a description."""
    if not folder.is_dir():
        raise ExampleSetError(f"source folder {folder.name!r} not found", code="missing_file")
    points: dict[str, np.ndarray] = {}
    for file in sorted(folder.iterdir()):
        suffix = file.suffix.lower()
        if suffix == ".obj":
            raise ExampleSetError(
                f"source folder {folder.name!r} holds meshes (.obj): a character pairs with "
                "point files (.npy/.csv, K x 3 feature points each); for meshes write a "
                "facecast.toml with [target] gltf and [source] feature_points",
                code="bad_source",
            )
        if not file.is_file() or suffix not in _POINT_SUFFIXES:
            continue
        name = normalise_name(file.stem).name or file.stem
        if name in points:
            raise ExampleSetError(
                f"source folder {folder.name!r}: two files give {name!r}", code="bad_source"
            )
        try:
            points[name] = read_points(file)
        except ExampleSetError as exc:
            raise ExampleSetError(f"source {file.name}: {exc.message}", code=exc.code) from None
    if "neutral" not in points:
        raise ExampleSetError(
            f"source folder {folder.name!r} has no neutral (neutral.npy or neutral.csv)",
            code="missing_file",
        )
    stable = folder_stable_points(folder)
    return points, stable, f"source folder {folder.name!r}"


def _pair(
    expressions: Iterable[str],
    available: dict[str, np.ndarray],
    neutral: np.ndarray,
    described: str,
    missing_reason: str,
) -> tuple[dict[str, np.ndarray], dict[str, str], dict[str, str]]:
    """``(chosen {name: points}, paired {name: why}, unpaired {name: why})`` in order.

    An expression whose points equal an earlier one's (or the neutral's) is left out: a rig
    could not tell the two apart.
    """
    chosen: dict[str, np.ndarray] = {}
    paired: dict[str, str] = {}
    unpaired: dict[str, str] = {}
    for name in expressions:
        found = available.get(name)
        if found is None:
            unpaired[name] = missing_reason
            continue
        if found.shape != neutral.shape:
            raise ExampleSetError(
                f"source {name!r} has {found.shape[0]} points, the source neutral "
                f"{neutral.shape[0]}",
                code="point_count_mismatch",
            )
        twin = next(
            (n for n, s in (("neutral", neutral), *chosen.items()) if np.array_equal(s, found)),
            None,
        )
        if twin is not None:
            unpaired[name] = f"same source points as {twin!r}: a rig cannot tell them apart"
            continue
        chosen[name] = found
        paired[name] = f"paired with the {described.split(':')[0]}"
    return chosen, paired, unpaired


def _pair_generic(
    expressions: Iterable[str],
) -> tuple[dict[str, np.ndarray], dict[str, str], dict[str, str]]:
    """``_pair`` with facecast's generic ARKit set (VRM presets composed), gaze and presets
    the character's own ARKit shapes drive left out (``generic.GAZE_SHAPES``,
    ``generic.DRIVEN_SHARE``)."""
    generic = generic_sources()
    names = list(expressions)
    left_out: dict[str, str] = {}
    for name in names:
        if is_gaze(name):
            left_out[name] = (
                "gaze: the generic set's landmarks see the eyelids, not the eyes (a look down "
                "lowers the upper lid almost as a blink does, and fitted together a closed "
                "eye came out half open); the character's look-at turns its eyes"
            )
    own = [n for n in names if n in generic.names and n != "neutral" and n not in left_out]
    # VRoid's part clips drive the shapes of their part: a whole-face emotion they mostly
    # carry is left out as one the ARKit shapes carry is.
    clips = [n for n in names if n in PART_COMPOSITIONS]
    for name in names:
        share = generic.driven_share(name, own)
        if name not in left_out and share >= DRIVEN_SHARE:
            carried = ", ".join(s for s in generic.composition(name) or {} if s in own)
            left_out[name] = (
                f"driven by the character's own ARKit shapes ({carried}: {share:.0%} of its "
                "motion at the generic landmarks); paired too, it would drive that motion twice"
            )
            continue
        shapes = generic.composition(name) or {}
        parts = [c for c in clips if c != name and set(PART_COMPOSITIONS[c]) <= set(shapes)]
        share = generic.driven_share(
            name, [*own, *(s for c in parts for s in PART_COMPOSITIONS[c])]
        )
        if name not in left_out and name not in clips and parts and share >= DRIVEN_SHARE:
            left_out[name] = (
                f"driven by the character's own part clips ({', '.join(parts)}: with its ARKit "
                f"shapes, {share:.0%} of its motion at the generic landmarks); paired too, it would "
                "drive that motion twice"
            )
    neutral = generic.points[0]
    kept = [(generic.points[generic.names.index(n)] - neutral).ravel() for n in own]
    kept_names = list(own)
    checked = sorted(
        (n for n in names if n not in left_out and n in PRESET_CHECK_ORDER and n not in own),
        key=PRESET_CHECK_ORDER.index,
    )
    for name in checked:
        points = generic.source_points(name)
        assert points is not None  # every name of PRESET_CHECK_ORDER is composed
        displacement = (points - neutral).ravel()
        if kept:
            basis = np.stack(kept, axis=1)
            mix = np.linalg.lstsq(basis, displacement, rcond=None)[0]
            residual = displacement - basis @ mix
            if np.linalg.norm(residual) <= DEPENDENT_RELATIVE * np.linalg.norm(displacement):
                parts = [n for n, c in zip(kept_names, mix, strict=True) if abs(c) > 1e-3]
                named = ", ".join(parts[:6]) + (
                    f" and {len(parts) - 6} more" if len(parts) > 6 else ""
                )
                left_out[name] = (
                    f"the same motion at the generic landmarks as a mix of {named}: a rig "
                    "cannot tell them apart"
                )
                continue
        kept.append(displacement)
        kept_names.append(name)
    available = {
        n: p for n in names if n not in left_out and (p := generic.source_points(n)) is not None
    }
    chosen, paired, unpaired = _pair(
        [n for n in names if n not in left_out],
        available,
        generic.points[0],
        GENERIC_ATTRIBUTION,
        "no source points in the generic ARKit set (ARKit shapes, VRM presets)",
    )
    if "tongueOut" in unpaired:
        unpaired["tongueOut"] = (
            "no source: ICT-FaceKit has no tongue shape (and a tongue moves no landmark)"
        )
    return chosen, paired, {**unpaired, **left_out}


def generic_pairing(expressions: Iterable[str]) -> tuple[dict[str, str], dict[str, str]]:
    """Which of ``expressions`` (in order) the generic ARKit set pairs, and why the others
    are not: ``({name: why}, {name: why})``, as ``character_example_set`` decides."""
    _, paired, unpaired = _pair_generic(expressions)
    return paired, unpaired


def character_example_set(
    character: Character,
    source: str | os.PathLike[str] | None = None,
    *,
    label: str = "character",
    displaced: bool = False,
) -> tuple[ExampleSet, PairingReport]:
    """The character's expressions paired with source points, ready for ``fit``.

    Parameters
    ----------
    character : Character
    source : path, optional
        A folder of point files (``neutral.npy`` and ``<name>.npy|.csv``, names normalised
        as the character's are); its ``facecast.toml``, or its parent's that names this
        folder's neutral, gives ``[source] stable_points``. Default: facecast's generic
        ARKit set (composing VRM presets without an ARKit twin), with its stable points.
    label : str
        What errors call the character.
    displaced : bool
        Give the targets as the face mesh and each expression's ``face_displacement``
        (``ExampleSet.target_displacements``, views of the character's morph targets)
        instead of a float64 copy of the face per expression: for a caller that fits the
        set and nothing else (the server's uploads). The fitted rig is the same bit for bit.

    Returns
    -------
    (ExampleSet, PairingReport)
        Examples named "neutral" then the paired expressions in the character's order;
        targets are the face mesh plus each expression's ``face_displacement``. An
        expression whose source points equal an earlier one's is left out: a rig could
        not tell the two apart. With the generic set, gaze is left out too, and so are
        presets the character's own ARKit shapes drive or that mix those paired before
        them (VRM ``blinkLeft`` beside ARKit ``eyeBlinkLeft``; ``_pair_generic``).

    Raises
    ------
    ExampleSetError
        ``no_expressions`` (a neutral-only character: the message says how to make them),
        ``too_few_examples`` (none paired), and the source folder's errors.
    """
    if not character.expressions:
        raise _no_expressions(label)
    if source is None:
        generic = generic_sources()
        neutral = generic.points[0]
        stable: np.ndarray | None = generic.stable_points
        chosen, paired, unpaired = _pair_generic(character.expressions)
        described = GENERIC_ATTRIBUTION
    else:
        points, stable, described = _folder_sources(Path(source))
        neutral = points.pop("neutral")
        chosen, paired, unpaired = _pair(
            character.expressions,
            points,
            neutral,
            described,
            f"no file of this name in the {described}",
        )
    names = ["neutral", *chosen]
    sources = [neutral, *chosen.values()]
    displacements = tuple(character.expressions[name].face_displacement for name in chosen)
    if displaced:
        # The largest arrays of a character upload (SERVER.md "What an upload can cost"):
        # the fit makes each target from these, a chunk at a time (basis.py).
        targets = character.face_vertices[None]
    else:
        # Filled in place: a list of M arrays then stacked held the targets twice.
        targets = np.empty((len(names), *character.face_vertices.shape))
        targets[:] = character.face_vertices
        for row, displacement in enumerate(displacements, start=1):
            targets[row] += displacement
    report = pair_report(
        character.names,
        paired,
        unpaired,
        source=described,
        face_mesh=character.mesh_names[character.face_mesh],
    )
    if len(names) < 2:
        raise ExampleSetError(
            f"{label}: none of its {len(character.expressions)} expressions could be paired "
            f"with the {described.split(':')[0]} (names tried: ARKit, Perfect Sync, _L/_R, "
            "VRM 0.x/1.0 presets, VRoid Fcl_ clips); see `facecast fit`'s pairing report",
            code="too_few_examples",
        )
    if stable is not None:
        stable = check_stable_points(stable, neutral.shape[0])
    example_set = ExampleSet(
        names=tuple(names),
        source_points=np.stack(sources),
        target_vertices=targets,
        target_faces=character.face_faces,
        stable_points=stable,
        target_displacements=displacements if displaced else None,
    )
    return example_set, report
