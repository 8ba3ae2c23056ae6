"""Writing generated expressions as an example-set folder (facecast.toml, source/, target/).

All or nothing: the folder is assembled beside its destination and renamed into place, so
a failure leaves what was there untouched; a target example already present is kept
unless ``overwrite``. It must not compute expressions (that is ``expressions``).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path

from ..errors import ExampleSetError
from ..io.meshio import format_faces, format_obj, points_to_csv, read_obj_vertices
from .expressions import GeneratedExpressions

__all__ = ["WrittenSet", "write_expression_set"]

MANIFEST = "facecast.toml"


@dataclass(frozen=True)
class WrittenSet:
    """What ``write_expression_set`` did: the folder, and which examples it wrote or kept."""

    folder: Path
    written: tuple[str, ...]
    kept: tuple[str, ...]


def _existing_examples(folder: Path) -> dict[str, list[str]]:
    manifest = folder / MANIFEST
    if not manifest.is_file():
        return {}
    try:
        with manifest.open("rb") as handle:
            doc = tomllib.load(handle)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ExampleSetError(
            f"{manifest}: cannot read the existing manifest ({exc}); fix or remove it",
            code="bad_manifest",
        ) from None
    examples = doc.get("examples", {})
    if not isinstance(examples, dict):
        raise ExampleSetError(f"{manifest}: [examples] is not a table", code="bad_manifest")
    return {
        str(name): [str(p) for p in pair]
        for name, pair in examples.items()
        if isinstance(pair, list) and len(pair) == 2
    }


def _manifest_text(
    generated: GeneratedExpressions, examples: dict[str, list[str]], comment: str
) -> str:
    lines = [f"# {line}" for line in comment.splitlines()] + [
        "[source]",
        'neutral = "source/neutral.csv"',
    ]
    if generated.stable_points is not None:
        lines.append(f"stable_points = {list(generated.stable_points)}")
    lines += ["", "[target]", 'neutral = "target/neutral.obj"', "", "[examples]"]
    # JSON strings are TOML basic strings for these names and relative paths.
    lines += [f"{json.dumps(name)} = {json.dumps(pair)}" for name, pair in examples.items()]
    return "\n".join(lines) + "\n"


def write_expression_set(
    folder: str | os.PathLike[str],
    generated: GeneratedExpressions,
    *,
    overwrite: bool = False,
    comment: str = "made by facecast expressions (deformation transfer)",
) -> WrittenSet:
    """Write ``generated`` as an example-set folder ready for ``facecast fit``.

    Layout: ``source/<name>.csv`` (the source's K feature points), ``target/<name>.obj``
    (the target's topology), and ``facecast.toml`` pairing them. When ``folder`` exists,
    every file in it is carried over; a target example whose file exists there is kept
    (an artist's edit) unless ``overwrite``, and examples the manifest lists that were not
    generated stay listed.

    Raises
    ------
    ExampleSetError
        ``target_mismatch``: the folder's target neutral has another vertex count; or an
        unreadable existing manifest. Nothing is written then.
    OSError
        The file system refused; the folder is left as it was.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ExampleSetError(f"{folder}: exists and is not a folder", code="bad_output")
    existing = _existing_examples(folder) if folder.is_dir() else {}
    neutral_file = folder / "target" / "neutral.obj"
    if neutral_file.is_file() and not overwrite:
        count = read_obj_vertices(neutral_file).shape[0]
        if count != generated.target_vertices.shape[1]:
            raise ExampleSetError(
                f"{neutral_file}: holds another target ({count} vertices, this one has "
                f"{generated.target_vertices.shape[1]}); choose another folder or pass "
                "--overwrite",
                code="target_mismatch",
            )
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        if folder.is_dir():
            shutil.copytree(folder, staging, dirs_exist_ok=True)
        (staging / "source").mkdir(exist_ok=True)
        (staging / "target").mkdir(exist_ok=True)
        faces_text = format_faces(generated.target_faces)
        written, kept = [], []
        examples = dict(existing)
        for i, name in enumerate(generated.names):
            target_file = f"target/{name}.obj"
            source_file = f"source/{name}.csv"
            if i > 0:
                present = name in existing and (folder / existing[name][1]).is_file()
                if not present and (folder / target_file).is_file():
                    present = True
                if present and not overwrite:
                    kept.append(name)
                    examples.setdefault(name, [source_file, target_file])
                    if not (staging / examples[name][0]).is_file():
                        (staging / source_file).write_text(
                            points_to_csv(generated.source_points[i]), encoding="ascii"
                        )
                    continue
                examples[name] = [source_file, target_file]
                written.append(name)
            (staging / source_file).write_text(
                points_to_csv(generated.source_points[i]), encoding="ascii"
            )
            (staging / target_file).write_text(
                "# facecast\n" + format_obj(generated.target_vertices[i], faces_text),
                encoding="ascii",
            )
        (staging / MANIFEST).write_text(
            _manifest_text(generated, examples, comment), encoding="utf-8"
        )
        _swap_into_place(staging, folder)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return WrittenSet(folder, tuple(written), tuple(kept))


def _swap_into_place(staging: Path, folder: Path) -> None:
    """Rename ``staging`` to ``folder``; an existing folder is moved aside, then removed."""
    if not folder.exists():
        staging.rename(folder)
        return
    aside = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old.", dir=folder.parent))
    aside.rmdir()
    folder.rename(aside)
    try:
        staging.rename(folder)
    except BaseException:
        aside.rename(folder)
        raise
    shutil.rmtree(aside, ignore_errors=True)
