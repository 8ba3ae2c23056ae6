"""``facecast import ict-facekit``: ICT-FaceKit -> an ARKit-named example set folder.

The folder's source side (feature points per ARKit shape) is what Live Link Face bridges
use as a source rig; its target side is the same ICT meshes, so it is also a complete
example set. Reads and writes files only; it must not fit or serve anything.

Input: a checkout of the public ICT-VGL/ICT-FaceKit repository (its ``FaceXModel``
folder: ``generic_neutral_mesh.obj``, one OBJ per expression, ``vertex_indices.json``)
or the converted ``ict_facekit.npz`` / its folder. Shapes are renamed by
``source_rig.arkit_from_ict`` (as ``rig.sources.ict_arkit`` does): ICT's left/right
``browInnerUp`` and ``cheekPuff`` halves are summed into ARKit's single shapes; ICT has no
``tongueOut``, so the set has 51 ARKit shapes.

Output::

    DIR/facecast.toml           [source] neutral and stable_points, [target] neutral,
                                [examples] 51 pairs
    DIR/source/<name>.npy       (K, 3) feature points
    DIR/target/<name>.obj       the face area (vertices [0, 9409)) or the full head
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from facecast.cli.errors import CommandError

if TYPE_CHECKING:  # numpy and the rig load when the command runs, not for --help
    from collections.abc import Sequence

    import numpy as np

    from facecast.cli.commands import Subparsers
    from facecast.rig.examples import ExampleSet

    #: (names, neutral (V, 3), shapes (N, V, 3), faces (F, 3), landmarks68 (68,))
    IctMeshes = tuple[list[str], np.ndarray, np.ndarray, np.ndarray, np.ndarray]

#: ICT-FaceKit vertex of each Multi-PIE 68 landmark (the topology of the public
#: repository's FaceXModel meshes; the same list as ``landmarks68`` in ict_facekit.npz).
ICT_LANDMARKS68 = (
    1225, 1888, 1052, 367, 1719, 1722, 2199, 1447, 966, 3661, 4390, 3927, 3924, 2608, 3272,
    4088, 3443, 268, 493, 1914, 2044, 1401, 3615, 4240, 4114, 2734, 2509, 978, 4527, 4942,
    4857, 1140, 2075, 1147, 4269, 3360, 1507, 1542, 1537, 1528, 1518, 1511, 3742, 3751, 3756,
    3721, 3725, 3732, 5708, 5695, 2081, 0, 4275, 6200, 6213, 6346, 6461, 5518, 5957, 5841,
    5702, 5711, 5533, 6216, 6207, 6470, 5517, 5966,
)  # fmt: skip
ICT_VERTEX_COUNT = 26_719
#: Vertices [0, 9409) of an ICT mesh are the face area (ICT's own layout).
ICT_FACE_VERTEX_COUNT = 9_409


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "import",
        help="convert third-party face data into a facecast example set",
        description="Convert third-party face data into a facecast example set folder.",
    )
    sub = parser.add_subparsers(dest="kind", metavar="KIND", required=True)
    ict = sub.add_parser(
        "ict-facekit",
        help="ICT-FaceKit (checkout or ict_facekit.npz) -> ARKit-named example set",
        description=(
            "Write an example set whose examples are named after the ARKit blendshapes "
            "(eyeBlinkLeft, jawOpen, ...), with feature points at Multi-PIE landmarks of "
            "the ICT face: a source rig for 'facecast bridge livelink' and a full "
            "example set for 'facecast fit'."
        ),
    )
    ict.add_argument(
        "path", metavar="PATH", help="ICT-FaceKit checkout (or its FaceXModel), or ict_facekit.npz"
    )
    ict.add_argument("-o", "--output", required=True, metavar="DIR", help="folder to write")
    ict.add_argument(
        "--landmarks",
        metavar="LIST",
        help="comma-separated Multi-PIE 68 positions (0-67) to use as feature points "
        "(default the 24 of facecast.rig.sources.ict.DEFAULT_LANDMARKS)",
    )
    ict.add_argument(
        "--target",
        choices=("face", "full"),
        default="face",
        help="target meshes: the face area (default, 9,409 vertices) or the full head",
    )
    ict.add_argument("--force", action="store_true", help="write into a non-empty folder")
    ict.set_defaults(func=run)


def _landmarks(text: str | None) -> tuple[int, ...]:
    from facecast.rig.sources.ict import DEFAULT_LANDMARKS

    if text is None:
        return tuple(DEFAULT_LANDMARKS)
    try:
        chosen = tuple(int(t) for t in text.replace(" ", "").split(",") if t)
    except ValueError:
        raise CommandError(f"--landmarks: expected integers 0-67, got {text!r}") from None
    if not chosen or any(not 0 <= i < 68 for i in chosen) or len(set(chosen)) != len(chosen):
        raise CommandError(f"--landmarks: expected distinct integers 0-67, got {text!r}")
    return chosen


def read_ict(path: Path) -> IctMeshes:
    """(names, neutral (V,3), shapes (N,V,3), faces, landmarks68) from a checkout or archive."""
    import numpy as np

    from facecast.rig.errors import ExampleSetError

    if path.is_file() and path.suffix == ".npz":
        return _read_archive(path)
    if path.is_dir() and (path / "ict_facekit.npz").is_file():
        return _read_archive(path / "ict_facekit.npz")
    model = path / "FaceXModel" if (path / "FaceXModel").is_dir() else path
    index_file = model / "vertex_indices.json"
    if not (model / "generic_neutral_mesh.obj").is_file() or not index_file.is_file():
        raise ExampleSetError(
            f"{path}: not ICT-FaceKit (expected ict_facekit.npz, or a checkout whose "
            "FaceXModel folder has generic_neutral_mesh.obj and vertex_indices.json)",
            code="missing_file",
        )
    from facecast.rig.io.meshio import read_obj, read_obj_vertices

    try:
        names = json.loads(index_file.read_text(encoding="utf-8"))["expressions"]
        if not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
            raise TypeError("'expressions' is not a list of names")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ExampleSetError(f"{index_file}: unreadable ({exc})", code="bad_example_set") from None
    neutral, faces = read_obj(model / "generic_neutral_mesh.obj")
    if neutral.shape[0] != ICT_VERTEX_COUNT:
        raise ExampleSetError(
            f"{model}: the neutral has {neutral.shape[0]} vertices, ICT-FaceKit's has "
            f"{ICT_VERTEX_COUNT}",
            code="vertex_count_mismatch",
        )
    shapes = np.empty((len(names), *neutral.shape))
    for i, name in enumerate(names):
        shapes[i] = read_obj_vertices(model / f"{name}.obj")
        if shapes[i].shape != neutral.shape:
            raise ExampleSetError(f"{model / name}.obj: vertex count differs from the neutral")
    return names, neutral, shapes, faces, np.asarray(ICT_LANDMARKS68)


def _read_archive(path: Path) -> IctMeshes:
    import numpy as np

    from facecast.rig.errors import ExampleSetError

    keys = ("neutral", "faces", "expressions", "expression_names", "landmarks68")
    try:
        with path.open("rb") as handle, np.load(handle, allow_pickle=False) as archive:
            data = {k: archive[k] for k in keys}
    except KeyError as exc:
        raise ExampleSetError(f"{path}: not an ICT-FaceKit archive (missing {exc})") from None
    except Exception as exc:  # zipfile/zlib/numpy raise many types on a corrupt file
        raise ExampleSetError(f"{path}: not readable ({type(exc).__name__}: {exc})") from None
    names = [str(n) for n in data["expression_names"]]
    return (
        names,
        data["neutral"].astype(np.float64),
        data["expressions"].astype(np.float64),
        data["faces"],
        data["landmarks68"],
    )


def arkit_example_set(
    path: Path, landmarks: Sequence[int], target: str
) -> tuple[ExampleSet, np.ndarray]:
    """The ARKit-named ``ExampleSet`` of an ICT-FaceKit source, and the vertex indices used."""
    import numpy as np

    from facecast.rig.errors import ExampleSetError
    from facecast.rig.examples import ExampleSet
    from facecast.rig.sources.ict import stable_positions
    from facecast.rig.sources.source_rig import arkit_from_ict

    names, neutral, shapes, faces, landmarks68 = read_ict(path)
    feature = np.asarray(landmarks68)[np.asarray(landmarks)].astype(np.int64)
    try:
        out_names, vertices = arkit_from_ict(names, neutral, shapes, strict=True)
    except ExampleSetError as exc:
        raise ExampleSetError(f"{path}: {exc}") from None
    faces = np.asarray(faces, dtype=np.int64)
    stable = stable_positions(landmarks)
    if target == "face":
        count = min(ICT_FACE_VERTEX_COUNT, vertices.shape[1])
        faces = faces[(faces < count).all(axis=1)]
        target_vertices = vertices[:, :count]
    else:
        target_vertices = vertices
    example_set = ExampleSet(
        names=out_names,
        source_points=vertices[:, feature],
        target_vertices=target_vertices,
        target_faces=faces,
        stable_points=None if stable is None else np.asarray(stable, dtype=np.int64),
    )
    return example_set, feature


def write_example_folder(example_set: ExampleSet, folder: Path, comment: str) -> None:
    """``facecast.toml`` + ``source/*.npy`` points + ``target/*.obj`` meshes."""
    import numpy as np

    from facecast.rig.io.meshio import write_obj

    (folder / "source").mkdir(parents=True, exist_ok=True)
    (folder / "target").mkdir(exist_ok=True)
    lines = [comment, "[source]", 'neutral = "source/neutral.npy"']
    if example_set.stable_points is not None:
        # Positions among the feature points: where head-pose removal aligns first.
        lines.append(f"stable_points = {example_set.stable_points.tolist()}")
    lines.append("[target]")
    lines += ['neutral = "target/neutral.obj"', "[examples]"]
    for i, name in enumerate(example_set.names):
        np.save(folder / "source" / f"{name}.npy", example_set.source_points[i])
        write_obj(
            folder / "target" / f"{name}.obj",
            example_set.target_vertices[i],
            example_set.target_faces,
        )
        if i:
            lines.append(f'{name} = ["source/{name}.npy", "target/{name}.obj"]')
    (folder / "facecast.toml").write_text("\n".join(lines) + "\n", encoding="utf-8")


def run(args: argparse.Namespace) -> int:
    from facecast.rig.sources.ict import DEFAULT_STABLE_LANDMARKS

    out = Path(args.output)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not args.force)):
        raise CommandError(
            f"{out} exists and is not an empty folder (use --force to write into it)"
        )
    landmarks = _landmarks(args.landmarks)
    example_set, feature = arkit_example_set(Path(args.path), landmarks, args.target)
    comment = (
        f"# ICT-FaceKit ({args.path}) as ARKit-named examples, written by facecast import.\n"
        f"# Feature points: Multi-PIE 68 positions {list(landmarks)}\n"
        f"# = ICT vertices {feature.tolist()}"
    )
    if example_set.stable_points is None:
        comment += (
            "\n# No stable points: --landmarks holds fewer than 3 of Multi-PIE "
            f"{list(DEFAULT_STABLE_LANDMARKS)}, so head-pose alignment would use all of them."
        )
    else:
        stable = [landmarks[i] for i in example_set.stable_points]
        comment += f"\n# Stable points (head-pose alignment): Multi-PIE positions {stable}"
    write_example_folder(example_set, out, comment)
    if example_set.stable_points is None:
        print(
            "facecast import: warning: --landmarks names fewer than 3 of the stable landmarks "
            f"{list(DEFAULT_STABLE_LANDMARKS)} (inner brows, lower lids, nose tip); the set "
            "has no stable points, so head-pose removal would align on jaw and lips too "
            "(give 'facecast fit' --stable-points)",
            file=sys.stderr,
        )
    print(
        f"facecast import: wrote {out} ({example_set.num_examples} examples, "
        f"K={example_set.num_points}, target V={example_set.num_vertices})",
        file=sys.stderr,
    )
    return 0
