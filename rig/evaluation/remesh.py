"""Another topology on the same surface, with every new vertex's place on the old one known.

For measuring deformation transfer against a known truth: a mesh remeshed here carries its
source's shapes over by barycentric interpolation. Decimation (edge collapses) and √3
re-triangulation; pure array code on the inputs, no files, no fitting.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from ..errors import MeshError
from ..transfer.mesh import SurfacePoints, check_mesh, closest_points, face_normals

__all__ = ["Remeshed", "carry_shapes", "decimate", "sqrt3_retriangulate"]


class Remeshed:
    """A remeshed surface: its triangles and where each vertex lies on the original.

    Attributes
    ----------
    vertices : (V', 3) float64
        On the original surface.
    faces : (F', 3) int64
    on_original : SurfacePoints
        Original triangle and barycentric coordinates of each new vertex.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, on_original: SurfacePoints) -> None:
        self.vertices = vertices
        self.faces = faces
        self.on_original = on_original


def carry_shapes(remeshed: Remeshed, shapes: np.ndarray, original_faces: np.ndarray) -> np.ndarray:
    """(M, V', 3) the original's shapes (M, V, 3) at the remeshed vertices (barycentric)."""
    return remeshed.on_original.interpolate(shapes, original_faces)


def sqrt3_retriangulate(vertices: np.ndarray, faces: np.ndarray) -> Remeshed:
    """√3 re-triangulation without smoothing: a vertex at each centroid, original edges flipped.

    Each interior edge (a, b) between triangles t1 (a -> b) and t2 (b -> a) becomes the
    two triangles (a, c2, c1) and (b, c1, c2) on the centroids; a boundary edge keeps
    (a, b, c1). V + F vertices, every one on the surface; no triangle of the result is an
    original one.
    """
    v, f = check_mesh(vertices, faces, what="mesh")
    nv, nf = v.shape[0], f.shape[0]
    directed = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    owner = np.repeat(np.arange(nf), 3)
    twin_of: dict[tuple[int, int], int] = {}
    for index, (a, b) in enumerate(directed.tolist()):
        twin_of[(a, b)] = index
    triangles = []
    for index, (a, b) in enumerate(directed.tolist()):
        twin = twin_of.get((b, a))
        c1 = nv + owner[index]
        if twin is None:
            triangles.append((a, b, c1))
        elif a < b:
            c2 = nv + owner[twin]
            triangles += [(a, c2, c1), (b, c1, c2)]
    new_faces = np.asarray(triangles, dtype=np.int64)
    centroids = v[f].mean(axis=1)
    bary = np.zeros((nv + nf, 3))
    tri = np.empty(nv + nf, dtype=np.int64)
    # An original vertex is corner k of some triangle containing it.
    for k in range(3):
        tri[f[:, k]] = np.arange(nf)
    corner = (f[tri[:nv]] == np.arange(nv)[:, None]).argmax(axis=1)
    bary[np.arange(nv), corner] = 1.0
    tri[nv:] = np.arange(nf)
    bary[nv:] = 1.0 / 3.0
    points = np.concatenate([v, centroids])
    on = SurfacePoints(tri, bary, points, np.zeros(nv + nf))
    used = np.unique(new_faces)
    return _compact(points, new_faces, on, used)


def _compact(
    points: np.ndarray, faces: np.ndarray, on: SurfacePoints, used: np.ndarray
) -> Remeshed:
    """Drop vertices no triangle uses (renumbering the faces)."""
    renumber = np.full(points.shape[0], -1, dtype=np.int64)
    renumber[used] = np.arange(used.size)
    kept = SurfacePoints(
        on.triangle[used], on.barycentric[used], on.points[used], on.distance[used]
    )
    return Remeshed(points[used], renumber[faces], kept)


def decimate(vertices: np.ndarray, faces: np.ndarray, target_count: int) -> Remeshed:
    """Collapse the shortest interior edges to their midpoints until ``target_count`` vertices.

    Each pass collapses a batch of edges whose neighbourhoods do not touch, refusing a
    collapse that breaks the link condition (would make the mesh non-manifold) or turns a
    triangle over; boundary vertices stay. The result's vertices are then placed on the
    original surface (their closest points), which gives their barycentric coordinates.
    """
    v, f = check_mesh(vertices, faces, what="mesh")
    if not 4 <= target_count < v.shape[0]:
        raise MeshError(f"decimate: target_count must lie in [4, {v.shape[0]})")
    positions = v.copy()
    tris = f.copy()
    alive = np.zeros(v.shape[0], dtype=bool)
    alive[np.unique(f)] = True
    while alive.sum() > target_count:
        collapsed = _collapse_pass(positions, tris, int(alive.sum()) - target_count)
        if not collapsed:
            break
        keep_b = {b: a for a, b in collapsed}
        remap = np.arange(positions.shape[0])
        for b, a in keep_b.items():
            remap[b] = a
            alive[b] = False
        tris = remap[tris]
        degenerate = (
            (tris[:, 0] == tris[:, 1]) | (tris[:, 1] == tris[:, 2]) | (tris[:, 0] == tris[:, 2])
        )
        tris = tris[~degenerate]
    used = np.unique(tris)
    near = closest_points(positions[used], v, f)
    placed = positions.copy()
    placed[used] = near.points
    full = SurfacePoints(
        np.zeros(positions.shape[0], dtype=np.int64),
        np.zeros((positions.shape[0], 3)),
        placed,
        np.zeros(positions.shape[0]),
    )
    full.triangle[used] = near.triangle
    full.barycentric[used] = near.barycentric
    result = _compact(placed, tris, full, used)
    check_mesh(result.vertices, result.faces, what="decimated mesh")
    return result


def _collapse_pass(positions: np.ndarray, tris: np.ndarray, wanted: int) -> list[tuple[int, int]]:
    """Collapse up to ``wanted`` independent short edges in place; returns (kept, removed)."""
    edges = np.sort(tris[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = np.zeros(positions.shape[0], dtype=bool)
    boundary[unique[counts == 1].ravel()] = True
    interior = unique[(counts == 2) & ~boundary[unique].any(axis=1)]
    lengths = np.linalg.norm(positions[interior[:, 0]] - positions[interior[:, 1]], axis=1)
    order = np.argsort(lengths)
    star: dict[int, list[int]] = defaultdict(list)
    for t, (a, b, c) in enumerate(tris.tolist()):
        star[a].append(t)
        star[b].append(t)
        star[c].append(t)
    normals = face_normals(positions, tris)
    locked = np.zeros(positions.shape[0], dtype=bool)
    done: list[tuple[int, int]] = []
    for a, b in interior[order].tolist():
        if len(done) >= wanted:
            break
        if locked[a] or locked[b]:
            continue
        around = set(star[a]) | set(star[b])
        ring_a = set(tris[star[a]].ravel().tolist()) - {a}
        ring_b = set(tris[star[b]].ravel().tolist()) - {b}
        if len(ring_a & ring_b) != 2:  # link condition: only the two opposite vertices
            continue
        middle = 0.5 * (positions[a] + positions[b])
        kept = [t for t in around if not (a in tris[t] and b in tris[t])]
        moved = tris[kept].copy()
        moved[moved == b] = a
        corners = np.where(moved[..., None] == a, middle, positions[moved])
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        area = np.linalg.norm(cross, axis=1)
        if (area <= 0).any() or ((cross / area[:, None]) * normals[kept]).sum(axis=1).min() < 0.5:
            continue
        positions[a] = middle
        done.append((a, b))
        for t in around:
            locked[tris[t]] = True
    return done
