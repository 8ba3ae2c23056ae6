"""Triangle-mesh geometry deformation transfer needs: checks, frames, normals, closest points.

Validates a mesh once (``check_mesh``) and computes per-triangle quantities on clean arrays;
it must not solve anything or read files.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import MeshError

__all__ = [
    "SurfacePoints",
    "check_mesh",
    "closest_points",
    "edge_length",
    "face_normals",
    "frame_inverses",
    "triangle_frames",
    "vertex_components",
]

# Twice a triangle's area below this fraction of the squared median edge: too thin for its
# frame (eq. 3's V) to be inverted reliably.
_DEGENERATE = 1e-10
# Candidate triangles searched for a point's closest point (by centroid distance).
_CANDIDATES = 12
#: Points whose candidates are measured at once: their temporaries are ~15 arrays of
#: (points, candidates, 3) float64, ~4 kB a point (97,000 at once took 470 MB; 8,192, 35).
_POINTS_AT_ONCE = 8192


def check_mesh(
    vertices: npt.ArrayLike, faces: npt.ArrayLike, *, what: str = "target mesh"
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh as (V, 3) float64 and (F, 3) int64 arrays, or a ``MeshError`` saying what to fix.

    A mesh deformation transfer can use is a manifold triangle mesh (quads arrive split
    into two triangles by the readers): finite coordinates, at least one triangle, indices
    in range, no triangle repeating a vertex or of zero area, and no edge shared by more
    than two triangles. Vertices no triangle uses are allowed (they keep their place).

    Raises
    ------
    MeshError
        ``no_triangles``, ``non_finite``, ``index_out_of_range``, ``degenerate_triangles``
        or ``non_manifold``, naming the first offending triangle or edge.
    """
    try:
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{what}: not numeric arrays ({exc})") from None
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 3:
        raise MeshError(f"{what}: expected vertices of shape (V >= 3, 3), got {v.shape}")
    if not np.isfinite(v).all():
        row = int(np.flatnonzero(~np.isfinite(v).all(axis=1))[0])
        raise MeshError(f"{what}: vertex {row} has NaN or Inf coordinates", code="non_finite")
    if f.size == 0:
        raise MeshError(
            f"{what}: no triangles (a point cloud); give a mesh with faces",
            code="no_triangles",
        )
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"{what}: expected integer faces of shape (F, 3), got {f.shape} {f.dtype}")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise MeshError(
            f"{what}: face indices must lie in [0, {v.shape[0]}), got [{f.min()}, {f.max()}]",
            code="index_out_of_range",
        )
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    doubled_area = np.linalg.norm(face_cross(v, f), axis=1)
    scale = float(np.median(edge_length(v, f))) ** 2
    thin = repeated | (doubled_area <= _DEGENERATE * max(scale, np.finfo(float).tiny))
    if thin.any():
        bad = np.flatnonzero(thin)
        raise MeshError(
            f"{what}: {bad.size} degenerate triangle(s) (repeated vertex or zero area), the "
            f"first is face {int(bad[0])} {f[bad[0]].tolist()}; merge or delete them "
            "(e.g. 'merge by distance' and 'delete loose' in Blender)",
            code="degenerate_triangles",
        )
    edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    if counts.max() > 2:
        edge = unique[int(np.argmax(counts))]
        raise MeshError(
            f"{what}: not a manifold surface: edge ({edge[0]}, {edge[1]}) is shared by "
            f"{counts.max()} triangles ({int((counts > 2).sum())} such edges); split the "
            "non-manifold edges or export the face as one clean surface",
            code="non_manifold",
        )
    return v, f


def face_cross(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) cross products (v2 - v1) x (v3 - v1): normal times twice the area."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    cross: np.ndarray = np.cross(b - a, c - a)
    return cross


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) unit triangle normals."""
    cross = face_cross(vertices, faces)
    norms = np.linalg.norm(cross, axis=1, keepdims=True)
    normals: np.ndarray = cross / np.where(norms > 0, norms, 1.0)
    return normals


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) area-weighted unit vertex normals (zero for unused vertices)."""
    cross = face_cross(vertices, faces)
    normals = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(normals, faces[:, corner], cross)
    norms = np.linalg.norm(normals, axis=1, keepdims=True)
    out: np.ndarray = normals / np.where(norms > 0, norms, 1.0)
    return out


def edge_length(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(3F,) lengths of every triangle's three edges (shared edges counted twice)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    lengths: np.ndarray = np.linalg.norm(np.concatenate([b - a, c - b, a - c]), axis=1)
    return lengths


def triangle_frames(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(..., F, 3, 3) frames V = [v2 - v1, v3 - v1, v4 - v1] as columns (Sumner & Popović eq. 3).

    v4 = v1 + n / sqrt(|n|) with n = (v2 - v1) x (v3 - v1): the fourth vertex that makes
    the deformation of the triangle's normal part of its transformation. ``vertices`` may
    carry leading batch axes, (..., V, 3).
    """
    a = vertices[..., faces[:, 0], :]
    e1 = vertices[..., faces[:, 1], :] - a
    e2 = vertices[..., faces[:, 2], :] - a
    n = np.cross(e1, e2)
    n /= np.sqrt(np.linalg.norm(n, axis=-1, keepdims=True))
    frames: np.ndarray = np.stack([e1, e2, n], axis=-1)
    return frames


def frame_inverses(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3, 3) inverses of ``triangle_frames``: the rest shape each deformation refers to."""
    inverses: np.ndarray = np.linalg.inv(triangle_frames(vertices, faces))
    return inverses


def vertex_components(num_vertices: int, faces: np.ndarray) -> np.ndarray:
    """(V,) connected-component label of every vertex (an unused vertex is its own)."""
    rows = faces[:, [0, 1, 2]].ravel()
    cols = faces[:, [1, 2, 0]].ravel()
    graph = coo_matrix((np.ones(rows.size), (rows, cols)), shape=(num_vertices, num_vertices))
    labels: np.ndarray
    _, labels = connected_components(graph, directed=False)
    return labels


class SurfacePoints:
    """Closest points on one mesh's surface: which triangle, where in it, how far.

    Attributes
    ----------
    triangle : (P,) int64
    barycentric : (P, 3) float64
    points : (P, 3) float64
    distance : (P,) float64
        ``inf`` where no candidate triangle faced the right way.
    """

    def __init__(
        self,
        triangle: np.ndarray,
        barycentric: np.ndarray,
        points: np.ndarray,
        distance: np.ndarray,
    ) -> None:
        self.triangle = triangle
        self.barycentric = barycentric
        self.points = points
        self.distance = distance

    @property
    def found(self) -> np.ndarray:
        """(P,) bool: a compatible closest point exists."""
        found: np.ndarray = np.isfinite(self.distance)
        return found

    def interpolate(self, values: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """Per-vertex ``values`` (..., V, C) at these points: (..., P, C)."""
        corners = faces[self.triangle]  # (P, 3)
        out: np.ndarray = np.einsum("...pkc,pk->...pc", values[..., corners, :], self.barycentric)
        return out


def closest_points(
    points: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    tree: cKDTree | None = None,
) -> SurfacePoints:
    """Each point's closest point on the triangles of (``vertices``, ``faces``).

    The candidates are the ``_CANDIDATES`` triangles with the nearest centroids (exact for
    meshes of even triangle size; a close approximation otherwise). With ``normals``
    (P, 3), only triangles whose normal lies within 90 degrees of the point's normal count
    (the paper's "compatible" closest point).
    """
    if tree is None:
        tree = cKDTree(vertices[faces].mean(axis=1))
    k = min(_CANDIDATES, faces.shape[0])
    facing = None if normals is None else face_normals(vertices, faces)
    if len(points) <= _POINTS_AT_ONCE:
        return _closest_points(points, vertices, faces, k, tree, normals, facing)
    parts = [
        _closest_points(
            points[at : at + _POINTS_AT_ONCE], vertices, faces, k, tree,
            None if normals is None else normals[at : at + _POINTS_AT_ONCE], facing,
        )
        for at in range(0, len(points), _POINTS_AT_ONCE)
    ]  # fmt: skip
    return SurfacePoints(
        *(np.concatenate(field) for field in zip(
            *((p.triangle, p.barycentric, p.points, p.distance) for p in parts), strict=True
        ))
    )  # fmt: skip


def _closest_points(
    points: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    k: int,
    tree: cKDTree,
    normals: np.ndarray | None,
    facing: np.ndarray | None,
) -> SurfacePoints:
    """``closest_points`` of up to ``_POINTS_AT_ONCE`` points (``facing``: the mesh's face
    normals, with ``normals``)."""
    _, candidates = tree.query(points, k=k)
    candidates = np.asarray(candidates).reshape(len(points), k)
    a, b, c = (vertices[faces[candidates, i]] for i in range(3))  # (P, k, 3)
    bary = _closest_on_triangles(points[:, None, :], a, b, c)
    on_surface = bary[..., :1] * a + bary[..., 1:2] * b + bary[..., 2:] * c
    distance = np.linalg.norm(on_surface - points[:, None, :], axis=2)
    if normals is not None and facing is not None:
        facing_point = np.einsum("pkc,pc->pk", facing[candidates], normals)
        distance = np.where(facing_point > 0.0, distance, np.inf)
    best = np.argmin(distance, axis=1)
    rows = np.arange(len(points))
    return SurfacePoints(
        candidates[rows, best], bary[rows, best], on_surface[rows, best], distance[rows, best]
    )


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (..., 3) of the point of triangle abc closest to p.

    The Voronoi-region tests of Ericson, Real-Time Collision Detection 5.1.5, on arrays:
    np.select takes the first region that holds, in the book's order.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        total = va + vb + vc
        v_in, w_in = vb / total, vc / total
    zero, one = np.zeros_like(d1), np.ones_like(d1)
    conditions = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0),
    ]
    v_choice = [zero, one, t_ab, zero, zero, 1 - t_bc]
    w_choice = [zero, zero, zero, one, t_ac, t_bc]
    v = np.select(conditions, v_choice, default=v_in)
    w = np.select(conditions, w_choice, default=w_in)
    bary: np.ndarray = np.stack([1 - v - w, v, w], axis=-1)
    return bary


def nearest_vertices(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """(P,) index of each point's nearest vertex."""
    _, index = cKDTree(vertices).query(points)
    nearest: np.ndarray = np.asarray(index, dtype=np.int64)
    return nearest
