"""A neutral-only character's key-expressions: ICT-FaceKit's ARKit shapes transferred onto it.

Ties the pieces together: the source expression set (ICT's generic face), the
correspondence (same topology, markers or none, then closest points), one transfer for
every expression. Builds arrays; writing them as an example-set folder is ``folder``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..errors import ExampleSetError, MarkerError, MeshError
from ..io.gltf import read_gltf_mesh
from ..io.meshio import read_obj
from ..sources.ict import DEFAULT_LANDMARKS, stable_positions
from ..sources.ict_arkit import arkit_example_set
from .contact import LID_CONTACT
from .correspondence import (
    Correspondence,
    CorrespondenceWeights,
    check_markers,
    fit_correspondence,
    identity_correspondence,
)
from .mesh import check_mesh
from .solve import STILL, DeformationTransfer, check_still

__all__ = [
    "GeneratedExpressions",
    "SourceExpressions",
    "ict_source_expressions",
    "read_target_mesh",
    "transfer_expressions",
]

_GLTF_SUFFIXES = (".glb", ".gltf", ".vrm")


@dataclass(frozen=True, eq=False)
class SourceExpressions:
    """The expressions to transfer: meshes on one topology, and their feature points.

    Attributes
    ----------
    names : tuple of M str
        ``names[0]`` is "neutral".
    vertices : (M, Vs, 3) float64
    faces : (Fs, 3) int64
    points : (M, K, 3) float64
        Feature points of each expression (the example set's source files).
    stable_points : tuple of int, optional
        Positions among the K points that expressions move least.
    """

    names: tuple[str, ...]
    vertices: np.ndarray
    faces: np.ndarray
    points: np.ndarray
    stable_points: tuple[int, ...] | None = None


def ict_source_expressions(path: str | os.PathLike[str]) -> SourceExpressions:
    """ICT-FaceKit's generic face area with its ARKit-named shapes (``arkit_example_set``).

    51 shapes after the neutral (no ``tongueOut``) on the face area's 9,409 vertices (ICT's
    ``face`` region: the skin, ears included), with ICT's default 24 landmarks as feature
    points. Eyes, teeth, gums, the mouth socket and ICT's ``head_and_neck`` region are not
    part of it, so target triangles there pair with nothing and keep their neutral.
    """
    generic = arkit_example_set(path, identity=None)
    return SourceExpressions(
        names=generic.names,
        vertices=generic.target_vertices,
        faces=generic.target_faces,
        points=generic.source_points,
        stable_points=stable_positions(DEFAULT_LANDMARKS),
    )


def read_target_mesh(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """A character's neutral from an OBJ or a glTF/GLB/VRM file: (V, 3), (F, 3)."""
    path = Path(path)
    if path.suffix.lower() in _GLTF_SUFFIXES:
        return read_gltf_mesh(path)
    if path.suffix.lower() == ".obj":
        return read_obj(path)
    raise ExampleSetError(
        f"{path}: unknown mesh type {path.suffix!r} (expected .obj, .glb, .gltf or .vrm)",
        code="bad_mesh_type",
    )


@dataclass(frozen=True, eq=False)
class GeneratedExpressions:
    """Transferred expressions on the target, paired with the source's feature points.

    Attributes
    ----------
    names : tuple of M str
        "neutral" first.
    target_vertices : (M, Vt, 3) float64
        ``target_vertices[0]`` is the target neutral as given.
    target_faces : (Ft, 3) int64
    source_points : (M, K, 3) float64
    stable_points : tuple of int, optional
    correspondence : Correspondence
        On the welded target (see ``weld``).
    seconds : dict
        ``correspondence``, ``factor`` and ``solve`` (all expressions) wall-clock times.
    unknowns : int
        Unknowns of the factored system (target vertices and fourth vertices).
    factorizations : int
        Sparse factorisations made: 1 for the paper's solve; with ``still``, one per
        expression (each of the unknowns its still points leave) and none of the whole.
    """

    names: tuple[str, ...]
    target_vertices: np.ndarray
    target_faces: np.ndarray
    source_points: np.ndarray
    stable_points: tuple[int, ...] | None
    correspondence: Correspondence
    seconds: dict[str, float] = field(default_factory=dict)
    unknowns: int = 0
    factorizations: int = 1


def weld(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge vertices at identical positions (glTF splits them at UV seams).

    Returns the welded vertices, faces on them, and (V,) the welded index of each vertex.
    """
    welded, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    # Keep the file's order of first appearance (np.unique sorts by position).
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return welded[order], rank[inverse][faces], rank[inverse]


def _pick_names(source: SourceExpressions, names: Sequence[str] | None) -> list[int]:
    if names is None:
        return list(range(len(source.names)))
    index = {n: i for i, n in enumerate(source.names)}
    unknown = [n for n in names if n not in index]
    if unknown:
        raise ExampleSetError(
            f"no source expression named {unknown[0]!r}; expected ARKit names such as "
            f"{', '.join(source.names[1:4])} ({len(source.names) - 1} in all)",
            code="unknown_expression",
        )
    picked = [0] + [index[n] for n in dict.fromkeys(names) if index[n] != 0]
    if len(picked) < 2:
        raise ExampleSetError("--names: name at least one expression", code="unknown_expression")
    return picked


def transfer_expressions(
    source: SourceExpressions,
    target_vertices: npt.ArrayLike,
    target_faces: npt.ArrayLike,
    *,
    markers: npt.ArrayLike | str | None = None,
    names: Sequence[str] | None = None,
    weights: CorrespondenceWeights | None = None,
    still: float | None = STILL,
    lid_contact: Sequence[str] = LID_CONTACT,
    progress: Callable[[int], object] | None = None,
) -> GeneratedExpressions:
    """Transfer the source's expressions onto a target neutral (Sumner & Popović 2004).

    Parameters
    ----------
    source : SourceExpressions
        Usually ``ict_source_expressions``.
    target_vertices, target_faces : (Vt, 3), (Ft, 3)
        The character's neutral, a manifold triangle mesh (quads split).
    markers : (N, 2) int or "auto", optional
        (source vertex, target vertex) pairs; not needed when the target shares the
        source's topology (then the correspondence is the identity). "auto": none, the
        source placed by closest points alone (``fit_correspondence`` with None; the
        target must face +z with y up, as ICT does).
    names : sequence of str, optional
        The expressions to make (default: all of the source's).
    weights : CorrespondenceWeights, optional
    still : float or None
        Target points whose source point moves less than this fraction of the
        expression's largest motion are held there (``DeformationTransfer``'s ``still``;
        None: the paper's system, factored once for every expression).
    lid_contact : sequence of str
        With ``still``: the expressions whose closing vertex pairs (lids meeting) are kept
        together on the target, ending as the source's pairs end (``contact.contacts``;
        default the blinks, so a taller eye's lids meet; empty: none).
    progress : callable, optional
        Called with 1 after each expression.

    Raises
    ------
    MeshError, MarkerError, CorrespondenceError, ExampleSetError
        ``markers_needed`` when the topologies differ and no markers are given.
    """
    target, faces = check_mesh(target_vertices, target_faces)
    picked = _pick_names(source, names)
    still = check_still(still)
    automatic = isinstance(markers, str)
    if automatic and markers != "auto":
        raise MarkerError(
            f"markers: {markers!r} is neither marker pairs nor 'auto'", code="bad_markers"
        )
    welded, welded_faces, welded_index = weld(target, faces)
    try:
        check_mesh(welded, welded_faces)
    except MeshError:
        # Separate pieces that touch (an eyelash on a lid) would share edges once welded.
        welded, welded_faces, welded_index = target, faces, np.arange(len(target))
    started = time.perf_counter()
    correspondence = identity_correspondence(source.vertices[0], source.faces, welded, welded_faces)
    if correspondence is None:
        if markers is None:
            raise MarkerError(
                "the target's topology differs from the source's, so the correspondence needs "
                "markers: a file of 'source_vertex target_vertex' lines (0-based), at least 3, "
                "about 20 spread over the face (eye and mouth corners, lids, nose tip, brows, "
                "chin); or 'auto' for a fit without markers",
                code="markers_needed",
            )
        marker_pairs = None
        if not automatic:
            checked = check_markers(
                markers, source.vertices.shape[1], target.shape[0], source=source.vertices[0]
            )
            marker_pairs = np.stack([checked[:, 0], welded_index[checked[:, 1]]], axis=1)
        correspondence = fit_correspondence(
            source.vertices[0], source.faces, welded, welded_faces, marker_pairs, weights=weights
        )
    found = time.perf_counter()
    transfer = DeformationTransfer(
        source.vertices[0],
        source.faces,
        welded,
        welded_faces,
        correspondence.pairs,
        vertex_map=correspondence.vertex_map,
        rotation=correspondence.rotation,
        scale=correspondence.scale,
        still=still,
        source_on_target=correspondence.fitted_source,
    )
    factored = time.perf_counter()
    touching = [still is not None and source.names[i] in lid_contact for i in picked[1:]]
    moved = transfer.transfer(source.vertices[picked[1:]], contact=touching, progress=progress)
    solved = time.perf_counter()
    vertices = np.empty((len(picked), *target.shape))
    vertices[0] = target
    np.take(moved, welded_index, axis=1, out=vertices[1:])  # no temporary of them all
    del moved
    return GeneratedExpressions(
        names=tuple(source.names[i] for i in picked),
        target_vertices=vertices,
        target_faces=faces,
        source_points=source.points[picked],
        stable_points=source.stable_points,
        correspondence=correspondence,
        seconds={
            "correspondence": found - started,
            "factor": factored - found,
            "solve": solved - factored,
        },
        unknowns=transfer.unknowns,
        factorizations=transfer.factorizations,
    )
