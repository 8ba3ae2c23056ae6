"""Which target triangle corresponds to which source triangle: markers, then closest points.

Sumner & Popović 2004, section 4: the source neutral is deformed onto the target by a
sequence of sparse least-squares problems (smoothness, identity and closest-point terms,
markers held), then triangles whose centroids lie close and whose normals agree are
paired. It must not transfer expressions (that is ``solve``) or read meshes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from ..errors import CorrespondenceError
from .automatic import place_by_closest_points, similarity
from .markers import MIN_MARKERS, check_markers, read_markers
from .mesh import (
    check_mesh,
    closest_points,
    edge_length,
    face_normals,
    frame_inverses,
    vertex_normals,
)
from .solve import frame_rows

__all__ = [
    "MIN_MARKERS",
    "Correspondence",
    "CorrespondenceWeights",
    "check_markers",
    "fit_correspondence",
    "identity_correspondence",
    "read_markers",
]

# The closest-point phase has converged when the fitted source's vertices lie, by median,
# within this many target edge lengths of the target surface.
_CONVERGED_EDGES = 1.0
# ... and when no more than this fraction of its triangles turned over on the way (markers
# that name the wrong places fold the source onto itself).
_FOLDED = 0.05


@dataclass(frozen=True)
class CorrespondenceWeights:
    """The paper's weights (section 4): smoothness, identity, and the closest-point ramp.

    The first step fits with markers only (w_C = 0); then ``steps`` steps raise w_C
    geometrically from ``closest_start`` to ``closest_end``. Distances are measured with
    both meshes scaled to a unit target diagonal (of its box along its principal axes), so
    the weights depend on neither the meshes' units nor their pose.
    """

    smoothness: float = 1.0
    identity: float = 0.001
    closest_start: float = 1.0
    closest_end: float = 5000.0
    steps: int = 4
    #: A number m: markers held in the first step only, then pulled to their places with
    #: weight m × w_C (beyond the paper), so a marker a fraction of an edge off its place no
    #: longer drags its neighbourhood along; 0.01 measured better than holding on every
    #: bench case (README). None: held exactly in every step, as the paper does.
    marker_weight: float | None = 0.01

    def __post_init__(self) -> None:
        values = (self.smoothness, self.identity, self.closest_start, self.closest_end)
        if not all(np.isfinite(v) and v > 0 for v in values) or self.steps < 1:
            raise CorrespondenceError(
                "correspondence weights must be positive and finite, with steps >= 1",
                code="bad_weights",
            )
        if self.marker_weight is not None and not (
            np.isfinite(self.marker_weight) and self.marker_weight > 0
        ):
            raise CorrespondenceError(
                f"marker_weight must be positive (or None to hold the markers), got "
                f"{self.marker_weight!r}",
                code="bad_weights",
            )

    def schedule(self) -> list[float]:
        ramp = np.geomspace(self.closest_start, self.closest_end, self.steps)
        return [0.0, *(float(w) for w in ramp)]


@dataclass(frozen=True, eq=False)
class Correspondence:
    """The result: the paper's triangle pairs M and the vertex map of the naive baseline.

    Attributes
    ----------
    pairs : (P, 2) int64
        (source triangle, target triangle).
    vertex_map : (Vt, Vs) scipy.sparse.csr_matrix
        Each target vertex's corresponding source point as barycentric weights on the
        source's vertices; empty rows for target vertices no source triangle reaches.
    fitted_source : (Vs, 3) float64
        The source neutral deformed onto the target (target units); for
        ``identity_correspondence`` the target's vertices of the same indices.
    residual : float
        Median distance of the fitted source's vertices to the target surface, in target
        edge lengths (0 for the identity).
    method : str
        "identity" (same topology), "markers" (markers, then closest points) or
        "automatic" (a similarity fitted to closest points, then closest points).
    rotation : (3, 3) float64
        The rotation that turns the source's axes into the target's (the markers'
        similarity; for ``identity_correspondence`` that of the shared vertices).
    scale : float
        Target units per source unit (the same similarity's scale).
    """

    pairs: np.ndarray
    vertex_map: sp.csr_matrix
    fitted_source: np.ndarray
    residual: float
    method: str = "markers"
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    scale: float = 1.0

    @property
    def reached_targets(self) -> np.ndarray:
        """(Ft_reached,) target triangles in at least one pair."""
        reached: np.ndarray = np.unique(self.pairs[:, 1])
        return reached


def identity_correspondence(
    source_vertices: np.ndarray,
    source_faces: np.ndarray,
    target_vertices: np.ndarray,
    target_faces: np.ndarray,
) -> Correspondence | None:
    """The correspondence of a target sharing the source's topology, or None if it does not.

    The target shares it when every source triangle is also one of the target's, with the
    same vertex numbers and winding (the source may be a part of the target, as ICT's face
    area is of ICT's head): those pair one to one, and each source vertex maps to the
    target vertex of the same index. The target may be the source in other units and
    pose (an avatar in metres at head height, ICT in centimetres at the origin): the
    similarity of the shared vertices (Umeyama) gives the correspondence's ``scale`` and
    ``rotation``, so the displacements the transfer copies (``still``, placing pieces)
    arrive in the target's units and axes.
    """
    vs, vt = source_vertices.shape[0], target_vertices.shape[0]
    if vt < vs:
        return None
    source_keys = _triangle_keys(source_faces, vt)
    target_keys = _triangle_keys(target_faces, vt)
    order = np.argsort(target_keys, kind="stable")
    where = np.searchsorted(target_keys[order], source_keys)
    where = np.minimum(where, len(order) - 1)
    if not np.array_equal(target_keys[order][where], source_keys):
        return None
    pairs = np.stack([np.arange(len(source_faces)), order[where]], axis=1)
    vertex_map = sp.csr_matrix((np.ones(vs), (np.arange(vs), np.arange(vs))), shape=(vt, vs))
    # The source placed on the target: each source vertex where its target vertex is.
    scale, rotation, _ = similarity(source_vertices, target_vertices[:vs])
    return Correspondence(
        pairs, vertex_map, target_vertices[:vs].copy(), 0.0, "identity", rotation, scale
    )


def _triangle_keys(faces: np.ndarray, count: int) -> np.ndarray:
    """One integer per triangle, equal for the same vertices in the same cyclic order."""
    start = np.argmin(faces, axis=1)
    # int64 whatever the faces' type: the key is up to count^3 (int32 faces overflow it).
    turned = np.take_along_axis(faces, (start[:, None] + np.arange(3)) % 3, axis=1)
    turned = turned.astype(np.int64, copy=False)
    keys: np.ndarray = (turned[:, 0] * count + turned[:, 1]) * count + turned[:, 2]
    return keys


def _adjacent_triangles(faces: np.ndarray) -> np.ndarray:
    """(E, 2) pairs of triangles sharing an edge."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(faces.shape[0]), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    edges, owner = edges[order], owner[order]
    same = (edges[1:] == edges[:-1]).all(axis=1)
    pairs: np.ndarray = np.stack([owner[:-1][same], owner[1:][same]], axis=1)
    return pairs


def fit_correspondence(
    source_vertices: npt.ArrayLike,
    source_faces: npt.ArrayLike,
    target_vertices: npt.ArrayLike,
    target_faces: npt.ArrayLike,
    markers: npt.ArrayLike | None,
    *,
    weights: CorrespondenceWeights | None = None,
    threshold: float | None = None,
) -> Correspondence:
    """Deform the source neutral onto the target and pair their triangles (section 4).

    Parameters
    ----------
    source_vertices, source_faces : (Vs, 3), (Fs, 3)
    target_vertices, target_faces : (Vt, 3), (Ft, 3)
    markers : (N, 2) int or None
        (source vertex, target vertex) pairs, N >= ``MIN_MARKERS``. None: automatic, the
        source placed by a similarity fitted to closest points
        (``automatic.place_by_closest_points``; the faces must look the same way), then
        the closest-point steps without markers (method "automatic").
    weights : CorrespondenceWeights, optional
        Default: the paper's (w_S 1, w_I 0.001, w_C 0 then 1 ... 5000 in 4 steps), with the
        markers pulled (0.01 × w_C) rather than held after the first step.
    threshold : float, optional
        Largest distance from a triangle's centroid to its partner, in target units.
        Default: twice the larger of the two meshes' median edge lengths (after fitting).

    Raises
    ------
    MeshError, MarkerError
        Bad meshes or markers.
    CorrespondenceError
        ``not_converged``: the fitted source stays far from the target surface (markers
        that name different places, or meshes too different); ``no_triangle_pairs``.
    """
    weights = weights or CorrespondenceWeights()
    src, sfaces = check_mesh(source_vertices, source_faces, what="source mesh")
    tgt, tfaces = check_mesh(target_vertices, target_faces)
    if markers is None:
        pairs = np.zeros((0, 2), dtype=np.int64)
    else:
        pairs = check_markers(markers, src.shape[0], tgt.shape[0], source=src)
    # Work with the target scaled to a unit diagonal (of its box along its principal axes)
    # and the source placed on it by the markers' similarity: the weights are then free of
    # the meshes' units and pose.
    centred = tgt - tgt.mean(axis=0)
    axes = np.linalg.svd(centred, full_matrices=False)[2]
    unit = float(np.linalg.norm(np.ptp(centred @ axes.T, axis=0)))
    target = centred / unit
    if markers is None:
        scale, rotation, shift = place_by_closest_points(src, sfaces, target, tfaces)
    else:
        scale, rotation, shift = similarity(src[pairs[:, 0]], target[pairs[:, 1]])
    placed = scale * src @ rotation.T + shift
    fitted = _fit_closest(placed, sfaces, target, tfaces, pairs, weights)
    target_edge = float(np.median(edge_length(target, tfaces)))
    near = closest_points(fitted, target, tfaces, normals=vertex_normals(fitted, sfaces))
    distances = near.distance[near.found]
    residual = float(np.median(distances)) / target_edge if distances.size else np.inf
    turned = np.einsum("fc,fc->f", face_normals(fitted, sfaces), face_normals(placed, sfaces))
    folded = float(np.mean(turned < 0.0)) if np.isfinite(fitted).all() else 1.0
    if not residual <= _CONVERGED_EDGES or folded > _FOLDED:
        if markers is None:
            raise CorrespondenceError(
                f"the source did not settle on the target without markers: its vertices stay "
                f"{residual:.3g} target edge lengths from the surface (median; "
                f"{_CONVERGED_EDGES:g} allowed) and {100 * folded:.1f}% of its triangles "
                f"turned over ({100 * _FOLDED:g}% allowed). Turn the target to face +z with "
                "y up, or give markers",
                code="not_converged",
            )
        raise CorrespondenceError(
            f"the source did not settle on the target: its vertices stay {residual:.3g} "
            f"target edge lengths from the surface (median; {_CONVERGED_EDGES:g} allowed) "
            f"and {100 * folded:.1f}% of its triangles turned over ({100 * _FOLDED:g}% "
            "allowed). Check that each marker pair names the same facial feature on both "
            "meshes (0-based indices, source first), and add markers where the shapes "
            "differ most",
            code="not_converged",
        )
    if threshold is None:
        reach = 2.0 * max(target_edge, float(np.median(edge_length(fitted, sfaces))))
    else:
        reach = float(threshold) / unit
    triangle_pairs = _triangle_pairs(fitted, sfaces, target, tfaces, reach)
    if triangle_pairs.size == 0:
        raise CorrespondenceError(
            "no target triangle lies within reach of the fitted source; raise the threshold "
            "or check the markers",
            code="no_triangle_pairs",
        )
    vertex_map = _vertex_map(fitted, sfaces, target, tfaces, reach)
    restored = fitted * unit + tgt.mean(axis=0)
    method = "markers" if markers is not None else "automatic"
    return Correspondence(
        triangle_pairs, vertex_map, restored, residual, method, rotation, scale * unit
    )


def _fit_closest(
    placed: np.ndarray,
    faces: np.ndarray,
    target: np.ndarray,
    target_faces: np.ndarray,
    markers: np.ndarray,
    weights: CorrespondenceWeights,
) -> np.ndarray:
    """The source deformed onto the target: one sparse solve per step of the w_C ramp."""
    vs, fs = placed.shape[0], faces.shape[0]
    rows = frame_rows(frame_inverses(placed, faces), faces, vs)  # (3Fs, Vs + Fs)
    adjacent = _adjacent_triangles(faces)
    difference = sp.csr_matrix(
        (
            np.tile([1.0, -1.0], len(adjacent)),
            (np.repeat(np.arange(len(adjacent)), 2), adjacent.ravel()),
        ),
        shape=(len(adjacent), fs),
    )
    smooth = sp.kron(difference, sp.identity(3), format="csr") @ rows  # E_S rows
    identity_rhs = np.tile(np.eye(3), (fs, 1))  # row 3t + k, column i: I[i, k]
    fixed = markers[:, 0]
    fixed_values = target[markers[:, 1]]
    free = np.setdiff1d(np.arange(vs + fs), fixed)
    base = (weights.smoothness * (smooth.T @ smooth) + weights.identity * (rows.T @ rows)).tocsr()
    base_rhs = weights.identity * (rows.T @ identity_rhs)
    tree = cKDTree(target[target_faces].mean(axis=1))
    current = np.concatenate([placed, placed[faces].mean(axis=1)])  # v4s: any start
    current[fixed] = fixed_values
    for w_closest in weights.schedule():
        if w_closest == 0 and fixed.size == 0:
            continue  # no markers: the closest points alone (a source already placed)
        normal = base.copy()
        rhs = base_rhs.copy()
        if w_closest > 0:
            near = closest_points(
                current[:vs], target, target_faces,
                normals=vertex_normals(current[:vs], faces), tree=tree,
            )  # fmt: skip
            found = np.flatnonzero(near.found)
            select = sp.csr_matrix(
                (np.full(found.size, w_closest), (found, found)), shape=(vs + fs, vs + fs)
            )
            normal = normal + select
            rhs[found] += w_closest * near.points[found]
        if w_closest > 0 and weights.marker_weight is not None:
            # Soft markers: every vertex is free, markers pulled like strong closest points.
            pull = weights.marker_weight * w_closest
            normal = normal + sp.csr_matrix(
                (np.full(fixed.size, pull), (fixed, fixed)), shape=normal.shape
            )
            rhs[fixed] += pull * fixed_values
            current = _factor_solve(normal, rhs)
            if not np.isfinite(current).all():
                break
            continue
        # Markers are held: move their columns to the right-hand side.
        rhs_free = rhs[free] - normal[free][:, fixed] @ fixed_values
        current[free] = _factor_solve(normal[free][:, free], rhs_free)
        if not np.isfinite(current).all():
            break
    fitted: np.ndarray = current[:vs]
    return fitted


def _factor_solve(normal: sp.spmatrix, rhs: np.ndarray) -> np.ndarray:
    """Solve one step's symmetric positive definite system (symmetric ordering, no pivots)."""
    lu = splu(
        normal.tocsc(),
        permc_spec="MMD_AT_PLUS_A",
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )
    solved: np.ndarray = lu.solve(rhs)
    return solved


def _triangle_pairs(
    source: np.ndarray,
    source_faces: np.ndarray,
    target: np.ndarray,
    target_faces: np.ndarray,
    reach: float,
) -> np.ndarray:
    """Pairs of compatible triangles: one holds the other's centroid's closest point.

    Both ways, as the paper does: each target triangle pairs with the source triangle
    nearest its centroid and each source triangle with the target triangle nearest its
    centroid, if within ``reach`` and with normals within 90°. (The paper compares
    centroids with centroids; the closest point on the surface picks the triangle that
    covers the centroid, which is what the centroid test approximates, and it matters
    when the two meshes' triangles differ much in size.)
    """
    found = []
    for mesh, faces, other, other_faces, flip in (
        (target, target_faces, source, source_faces, True),
        (source, source_faces, target, target_faces, False),
    ):
        near = closest_points(
            mesh[faces].mean(axis=1), other, other_faces, normals=face_normals(mesh, faces)
        )
        mine = np.flatnonzero(near.found & (near.distance <= reach))
        theirs = near.triangle[mine]
        found.append(np.stack([theirs, mine], axis=1) if flip else np.stack([mine, theirs], 1))
    pairs: np.ndarray = np.unique(np.concatenate(found), axis=0)
    return pairs


def _vertex_map(
    source: np.ndarray,
    source_faces: np.ndarray,
    target: np.ndarray,
    target_faces: np.ndarray,
    reach: float,
) -> sp.csr_matrix:
    """(Vt, Vs) barycentric weights of each target vertex's closest fitted-source point."""
    near = closest_points(
        target, source, source_faces, normals=vertex_normals(target, target_faces)
    )
    ok = np.flatnonzero(near.found & (near.distance <= reach))
    corners = source_faces[near.triangle[ok]]
    return sp.csr_matrix(
        (near.barycentric[ok].ravel(), (np.repeat(ok, 3), corners.ravel())),
        shape=(target.shape[0], source.shape[0]),
    )
