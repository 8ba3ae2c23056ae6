"""``facecast bench transfer``: deformation transfer's cost and accuracy on ICT-FaceKit.

Cost: ICT's 51 ARKit shapes onto remeshed ICT faces of about 10k and 50k vertices
(correspondence, the one factorisation, the solves), each solve beside a floor measured in
the same run (one product with the factors). Accuracy: targets with a known truth (other
ICT identities; ICT's face decimated or re-triangulated, its shapes carried over), the
transfer beside the naive baseline, and a real take cloned through generated and true
examples (eq. 4.1), and the lids' gap each transferred blink leaves, with the lids pulled
together and without. It must not tune the method to the figures.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import cKDTree

from facecast.cli.bench.engine import _paired_seconds
from facecast.cli.errors import CommandError
from facecast.cli.render import save_side_by_side
from facecast.rig.evaluation.remesh import carry_shapes, decimate, sqrt3_retriangulate
from facecast.rig.evaluation.reshape import motion_centre, stretch_about
from facecast.rig.evaluation.transfer import (
    BLINKS,
    end_to_end,
    lids_gap,
    relative_errors,
    score_transfer,
)
from facecast.rig.examples import ExampleSet
from facecast.rig.sources.ict import ict_example_set, locate_ict
from facecast.rig.sources.ict_arkit import arkit_example_set
from facecast.rig.sources.trackers import read_livelink_csv
from facecast.rig.transfer import (
    CorrespondenceWeights,
    DeformationTransfer,
    ict_source_expressions,
    transfer_expressions,
)
from facecast.rig.transfer.contact import LID_CONTACT
from facecast.rig.transfer.expressions import weld
from facecast.rig.transfer.mesh import nearest_vertices

if TYPE_CHECKING:
    from scipy.sparse.linalg import SuperLU

    from facecast.rig.evaluation.remesh import Remeshed
    from facecast.rig.transfer.expressions import SourceExpressions

# Landmark noise (std per coordinate, cm) for the end-to-end runs: none, and 0.5 mm.
NOISES = (0.0, 0.05)
TAKE = Path(__file__).resolve().parents[2] / "tests" / "data" / "livelink" / "llv_dao.csv"


def run(args: argparse.Namespace) -> int:

    archive = locate_ict(args.ict) if args.ict else locate_ict()
    if archive is None:
        raise CommandError(
            "ICT-FaceKit not found (the transfer's source): set FACECAST_ICT, pass --ict PATH "
            "or place it in ../shared/data/ict-facekit"
        )

    source = ict_source_expressions(archive)
    landmarks = ict_example_set(archive).feature_indices
    assert landmarks is not None  # ICT's example set is made of meshes and their landmarks
    report: dict[str, Any] = {}
    if not args.accuracy_only:
        report["cost"] = _cost(
            source, landmarks, repeat=args.repeat, still=None if args.paper_solve else args.still
        )
    if not args.cost_only:
        take = Path(args.take) if args.take else TAKE
        if not take.is_file():
            raise CommandError(f"{take}: no such take (a Live Link Face CSV)")
        report["accuracy"], shown = _accuracy(
            archive, source, landmarks, take,
            marker_weight=None if args.hold_markers else args.marker_weight,
            still=None if args.paper_solve else args.still,
            lid_contact=() if args.no_lid_contact else LID_CONTACT,
        )  # fmt: skip
        if args.sheet:
            print(f"wrote {_sheet(args.sheet, source, shown)}")
    report["marker_weight"] = None if args.hold_markers else args.marker_weight
    report["still"] = None if args.paper_solve else args.still
    report["lid_contact"] = not (args.paper_solve or args.no_lid_contact)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=float))
        print(f"wrote {args.json}")
    return 0


# -- cost -------------------------------------------------------------------------------


def _cost_targets(source: SourceExpressions) -> list[tuple[str, Remeshed]]:

    face, faces = source.vertices[0], source.faces
    small = sqrt3_retriangulate(*_mesh(decimate(face, faces, 3400)))
    large = sqrt3_retriangulate(*_mesh(sqrt3_retriangulate(*_mesh(decimate(face, faces, 5600)))))
    return [("~10k", small), ("~50k", large)]


def _mesh(remeshed: Remeshed) -> tuple[np.ndarray, np.ndarray]:
    return remeshed.vertices, remeshed.faces


def _cost(
    source: SourceExpressions, landmarks: np.ndarray, *, repeat: int, still: float | None
) -> list[dict[str, Any]]:

    rows = []
    print("cost: ICT-FaceKit's 51 ARKit shapes (9,409-vertex face) -> remeshed ICT faces")
    for label, target in _cost_targets(source):
        markers = np.stack([landmarks, nearest_vertices(source.vertices[0][landmarks],
                                                        target.vertices)], axis=1)  # fmt: skip
        generated = transfer_expressions(
            source, target.vertices, target.faces, markers=markers, still=still
        )
        started = time.perf_counter()
        transfer = DeformationTransfer(  # the paper's solve, factored here
            source.vertices[0], source.faces, target.vertices, target.faces,
            generated.correspondence.pairs, vertex_map=generated.correspondence.vertex_map,
            rotation=generated.correspondence.rotation, scale=generated.correspondence.scale,
        )  # fmt: skip
        factor_again = time.perf_counter() - started
        lu = transfer.factor
        rhs = np.random.default_rng(0).normal(size=(transfer.unknowns, 3))
        shape = source.vertices[1]

        def one_expression(
            shape: np.ndarray = shape, transfer: DeformationTransfer = transfer
        ) -> None:
            transfer.transfer(shape)

        def floor(lu: SuperLU = lu, rhs: np.ndarray = rhs) -> None:
            lu.L @ (lu.U @ rhs)

        per_expression, floor_s = _paired_seconds(one_expression, floor, repeat=repeat)
        row = {
            "target": label,
            "vertices": int(target.vertices.shape[0]),
            "triangles": int(target.faces.shape[0]),
            "unknowns": transfer.unknowns,
            "factor_nonzeros": transfer.nonzeros,
            "correspondence_s": generated.seconds["correspondence"],
            "factor_s": generated.seconds["factor"],
            "factor_again_s": factor_again,
            "solve_all_s": generated.seconds["solve"],
            "per_expression_s": per_expression,
            "floor_s": floor_s,
            "ratio": per_expression / floor_s,
            "residual_edges": generated.correspondence.residual,
            "still": still,
            "factorizations": generated.factorizations,
        }
        rows.append(row)
        print(
            f"  {label:5s} {row['vertices']:6d} vertices: correspondence "
            f"{row['correspondence_s']:6.1f} s, set-up {row['factor_s']:5.2f} s; the paper's "
            f"solve: factor {factor_again:.2f} s ({row['unknowns']} unknowns, "
            f"{row['factor_nonzeros']:,} nonzeros in L+U), one expression "
            f"{1e3 * per_expression:6.1f} ms beside the floor {1e3 * floor_s:5.1f} ms "
            f"(one product with L and U, 3 columns) = {row['ratio']:.1f}x; 51 solves as "
            f"run {row['solve_all_s']:5.2f} s"
        )
        if still is not None:
            # Each expression factors the unknowns its still points leave: at most the whole
            # system, whose factorisation (timed above for the paper's solve) is its floor.
            each = generated.seconds["solve"] / (len(source.names) - 1)
            print(
                f"        still points held ({still:g}): the 51 solves above factor "
                f"{generated.factorizations} systems, {1e3 * each:.0f} ms per expression "
                f"beside one factorisation of the whole system {1e3 * factor_again:.0f} ms "
                f"= {each / factor_again:.2f}x; the one-expression figure is the paper's solve"
            )
    return rows


# -- accuracy ---------------------------------------------------------------------------


def _exact_markers(
    source_vertices: np.ndarray, landmarks: np.ndarray, target: np.ndarray
) -> np.ndarray:
    """Markers a careful user would place: for each landmark, the nearest target vertex
    that coincides with a source vertex (a decimation leaves many where they were)."""

    distance, match = cKDTree(source_vertices).query(target)
    exact = np.flatnonzero(distance < 1e-9)
    pairs = []
    for mark in landmarks:
        best = exact[np.argmin(np.linalg.norm(target[exact] - source_vertices[mark], axis=1))]
        pairs.append((int(match[best]), int(best)))
    return np.unique(np.asarray(pairs), axis=0)


def _accuracy(
    archive: Path,
    source: SourceExpressions,
    landmarks: np.ndarray,
    take: Path,
    *,
    marker_weight: float | None = 0.01,
    still: float | None = None,
    lid_contact: tuple[str, ...] = LID_CONTACT,
) -> tuple[list[dict[str, Any]], list[tuple[str, Any, np.ndarray]]]:

    livelink = read_livelink_csv(take)
    face = source.vertices[0]
    # (label, truth, markers, target faces, the landmarks' true places on the target)
    cases: list[tuple[str, ExampleSet, Any, np.ndarray, np.ndarray | None]] = []
    for identity in ("person01", "person10"):
        truth = arkit_example_set(archive, identity=identity)
        cases.append((f"(a) ICT {identity}, same topology (identity map)", truth, None,
                      truth.target_faces, None))  # fmt: skip
    # The same faces with their vertices renumbered, so the markers' path runs.
    for identity, markers in (("person01", "landmarks"), ("person01", "auto"),
                              ("person10", "auto")):  # fmt: skip
        truth = arkit_example_set(archive, identity=identity)
        order = np.random.default_rng(0).permutation(truth.num_vertices)
        new_index = np.argsort(order)
        renumbered = ExampleSet(names=truth.names, source_points=truth.source_points,
                                target_vertices=truth.target_vertices[:, order],
                                target_faces=new_index[truth.target_faces])  # fmt: skip
        if markers == "auto":
            label = f"(a) ICT {identity} renumbered, automatic (no markers) + closest points"
            given: Any = "auto"
        else:
            label = (
                f"(a) ICT {identity} renumbered, {len(landmarks)} landmark markers + closest points"
            )
            given = np.stack([landmarks, new_index[landmarks]], axis=1)
        cases.append((label, renumbered, given, renumbered.target_faces,
                      truth.target_vertices[0, landmarks]))  # fmt: skip
    decimated = decimate(face, source.faces, 4000)
    sqrt3 = sqrt3_retriangulate(face, source.faces)
    for label, remeshed, kind in (
        ("(b) ICT face decimated to 4,000 vertices, exact markers", decimated, "exact"),
        ("(b) ICT face decimated to 4,000 vertices, nearest-vertex markers", decimated, "nearest"),
        ("(b) ICT face decimated to 4,000 vertices, automatic (no markers)", decimated, "auto"),
        ("(b) ICT face sqrt3-retriangulated (27,870 vertices), exact markers", sqrt3, "exact"),
    ):
        shapes = carry_shapes(remeshed, source.vertices, source.faces)
        truth_set = ExampleSet(names=source.names, source_points=source.points,
                               target_vertices=shapes, target_faces=remeshed.faces)  # fmt: skip
        if kind == "exact":
            given = _exact_markers(face, landmarks, remeshed.vertices)
        elif kind == "nearest":
            given = np.stack([landmarks, nearest_vertices(face[landmarks], remeshed.vertices)], 1)
        else:
            given = "auto"
        cases.append((label, truth_set, given, remeshed.faces, face[landmarks]))
    # Another face's shape and another topology at once: person10's eyes are taller than the
    # source's, so its blinks are where the two shapes differ. √3 keeps the original
    # vertices' numbers, so the landmarks name the same places on it.
    person10 = arkit_example_set(archive, identity="person10")
    other = sqrt3_retriangulate(person10.target_neutral, person10.target_faces)
    carried = carry_shapes(other, person10.target_vertices, person10.target_faces)
    cases.append(
        (
            f"(c) ICT person10 sqrt3-retriangulated (another shape and topology), {len(landmarks)} "
            "landmark markers",
            ExampleSet(names=person10.names, source_points=person10.source_points,
                       target_vertices=carried, target_faces=other.faces),
            np.stack([landmarks, landmarks], axis=1), other.faces,
            person10.target_vertices[0, landmarks],
        )
    )  # fmt: skip
    # A differently shaped eye whose true blink closes (ICT's identities' do not: the same
    # deltas on a taller eye): the generic face and all its shapes with each eye stretched
    # 1.25 x vertically about where its blink moves, fading out within 2.5 cm; then √3.
    centres = [motion_centre(face, source.vertices[source.names.index(name)]) for name in BLINKS]
    tall = stretch_about(source.vertices, centres, factor=1.25, reach=2.5)
    other = sqrt3_retriangulate(tall[0], source.faces)
    cases.append(
        (
            f"(d) ICT face, eyes 1.25x taller (its true blinks close), sqrt3, {len(landmarks)} "
            "landmark markers",
            ExampleSet(names=source.names, source_points=source.points,
                       target_vertices=carry_shapes(other, tall, source.faces),
                       target_faces=other.faces),
            np.stack([landmarks, landmarks], axis=1), other.faces, tall[0, landmarks],
        )
    )  # fmt: skip

    rows = []
    shown = []
    held = "held" if marker_weight is None else f"pulled with {marker_weight:g} x w_C"
    solve = "the paper's (one vertex held)" if still is None else f"still points held ({still:g})"
    if still is not None:
        solve += f", lids pulled together on {', '.join(lid_contact)}" if lid_contact else ""
    print(f"markers {held}; solve: {solve}")
    print("accuracy: error relative to the true displacement (sum over vertices), and a real "
          f"take ({take.name}) cloned through generated vs true examples (eq. 4.1, worst axis)")  # fmt: skip
    for label, truth_set, markers, faces, true_landmarks in cases:
        generated = transfer_expressions(
            source, truth_set.target_neutral, faces, markers=markers,
            weights=CorrespondenceWeights(marker_weight=marker_weight), still=still,
            lid_contact=lid_contact,
        )  # fmt: skip
        truth_vertices = truth_set.target_vertices
        if faces is not truth_set.target_faces:
            truth_set = ExampleSet(names=truth_set.names, source_points=truth_set.source_points,
                                   target_vertices=truth_vertices, target_faces=faces)  # fmt: skip
        score = score_transfer(generated, source, truth_vertices)
        if label.startswith("(a) ICT person01, same") or "nearest" in label:
            shown.append((label, generated, truth_vertices))
        ends = [end_to_end(generated, truth_set, livelink.weights, livelink.fps, noise=n)
                for n in NOISES]  # fmt: skip
        worse = [
            n for n, t, v in zip(score.names, score.transfer, score.naive, strict=True) if t >= v
        ]
        landmark_mm = None
        if isinstance(markers, str) and true_landmarks is not None:
            # The automatic fit's landmarks against their true places (ICT's cm -> mm).
            fitted = generated.correspondence.fitted_source[landmarks]
            landmark_mm = 10.0 * np.linalg.norm(fitted - true_landmarks, axis=1)
        gaps = lids_gap(generated, truth_vertices)
        apart = _blinks_apart(source, generated, truth_vertices, lid_contact, still)
        row = {
            "case": label,
            "markers": markers if isinstance(markers, str) or markers is None else len(markers),
            "landmark_error_mm": None
            if landmark_mm is None
            else {
                "median": float(np.median(landmark_mm)),
                "max": float(landmark_mm.max()),
                "per_landmark": landmark_mm.tolist(),
            },
            "residual_edges": generated.correspondence.residual,
            **score.as_dict(),
            "transfer_not_below_naive": worse,
            "lids_gap": [vars(gap) for gap in gaps],
            "blinks_without_lid_contact": apart,
            "end_to_end": ends,
        }
        rows.append(row)
        worst = score.names[int(np.argmax(score.transfer))]
        print(f"  {label}")
        if landmark_mm is not None:
            print(
                f"    automatic fit: the {len(landmark_mm)} landmarks {np.median(landmark_mm):.2f} mm from their "
                f"true places (median; {landmark_mm.max():.2f} mm at most), residual "
                f"{generated.correspondence.residual:.3f} target edges"
            )
        print(
            f"    transfer {100 * score.transfer_overall:5.1f}%  naive {100 * score.naive_overall:5.1f}%"
            f"  (transfer below naive on {len(score.names) - len(worse)} of {len(score.names)}; "
            f"worst {worst} {100 * score.transfer.max():.0f}%; median "
            f"{100 * np.median(score.transfer):.1f}% vs {100 * np.median(score.naive):.1f}%)"
        )
        print(
            "    lids' gap / the neutral's on the vertex pairs the true blink closes: "
            + "; ".join(
                f"{gap.name} {gap.generated:.2f} (truth {gap.truth:.2f}, {gap.pairs} "
                f"pair{'' if gap.pairs == 1 else 's'})"
                if gap.pairs
                else f"{gap.name}: the true shape closes no pair"
                for gap in gaps
            )
        )
        if apart is not None:
            blinks = [score.names.index(name) for name in BLINKS]
            print(
                "      without the lids pulled together: "
                + "; ".join(
                    f"{name} {gap:.2f}" for name, gap in zip(BLINKS, apart["gap"], strict=True)
                )
                + "; the blinks' error "
                + " / ".join(f"{100 * score.transfer[i]:.1f}%" for i in blinks)
                + " (without: "
                + " / ".join(f"{100 * e:.1f}%" for e in apart["error"])
                + ")"
            )
        for end in ends:
            true_e = max(end["true"]["eq41_percent"].values())
            gen_e = max(end["generated"]["eq41_percent"].values())
            print(
                f"    take, noise {end['noise']:g} cm: eq. 4.1 through true examples "
                f"{true_e:.4f}%, through generated {gen_e:.4f}% ({gen_e / true_e:.3g}x)"
            )
    return rows, shown


def _blinks_apart(
    source: SourceExpressions,
    generated: Any,
    truth: np.ndarray,
    lid_contact: tuple[str, ...],
    still: float | None,
) -> dict[str, list[float]] | None:
    """The blinks solved again on the same correspondence without the lids pulled together:
    their lids' gap and error, for the comparison (None when none were pulled)."""

    if still is None or not set(BLINKS) <= set(lid_contact):
        return None
    welded, welded_faces, index = weld(generated.target_vertices[0], generated.target_faces)
    correspondence = generated.correspondence
    if len(welded) != correspondence.vertex_map.shape[0]:  # not welded for the solve
        welded, welded_faces = generated.target_vertices[0], generated.target_faces
        index = np.arange(len(welded))
    transfer = DeformationTransfer(
        source.vertices[0], source.faces, welded, welded_faces, correspondence.pairs,
        vertex_map=correspondence.vertex_map, rotation=correspondence.rotation,
        scale=correspondence.scale, still=still,
    )  # fmt: skip
    blinks = [source.names.index(name) for name in BLINKS]
    moved = transfer.transfer(source.vertices[blinks])[:, index]
    picked = [generated.names.index(name) for name in BLINKS]
    alone = type(generated)(
        names=("neutral", *BLINKS),
        target_vertices=np.concatenate([generated.target_vertices[:1], moved]),
        target_faces=generated.target_faces,
        source_points=generated.source_points[[0, *picked]],
        stable_points=None,
        correspondence=correspondence,
    )
    true = truth[[0, *picked]]
    errors, _ = relative_errors(alone.target_vertices, true)
    return {
        "gap": [gap.generated for gap in lids_gap(alone, true)],
        "error": errors.tolist(),
    }


SHEET_NAMES = (
    "jawOpen",
    "eyeBlinkLeft",
    "mouthSmileLeft",
    "mouthPucker",
    "browInnerUp",
    "cheekPuff",
)


def _front(
    vertices: np.ndarray, faces: np.ndarray, neutral: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The triangles in front of the ears (ICT's axes, cm: the nose tip is at z = 13)."""
    keep = (neutral[faces][:, :, 2] > 4.0).all(axis=1)
    return vertices, faces[keep]


def _sheet(path: str, source: SourceExpressions, shown: list[tuple[str, Any, np.ndarray]]) -> Path:
    """Rows of expressions: the source, then per shown case the truth and the transfer
    (only the front of the face, so the lids and lips show)."""

    rows = []
    for name in SHEET_NAMES:
        shape = source.vertices[source.names.index(name)]
        row = [(f"ICT: {name}", *_front(shape, source.faces, source.vertices[0]))]
        for label, generated, truth in shown:
            short = label.replace("decimated to 4,000 vertices", "decimated 4k").split(",")[0]
            short = short.replace("(a) ICT ", "").replace("(b) ICT face ", "")
            index = generated.names.index(name)
            faces = generated.target_faces
            row.append((f"{short}: true", *_front(truth[index], faces, truth[0])))
            row.append(
                (
                    f"{short}: transferred",
                    *_front(generated.target_vertices[index], faces, truth[0]),
                )
            )
        rows.append(row)
    return save_side_by_side(
        path, rows, panel_size=(210, 230), view="front",
        title="ICT-FaceKit's shapes transferred (Sumner & Popovic 2004) beside the true ones",
    )  # fmt: skip
