"""Lid contact: the vertex pairs an expression brings together, kept together on the target.

Deformation transfer copies each triangle's deformation, not where a surface ends up: on a
target whose eye opens wider than the source's, a blink moves each lid as far as the
source's lids move and leaves them apart (README, "The lids' gap after transfer"). For the
expressions named, the source vertex pairs the expression brings together are found, and
their places on the target are pulled to where the source's pair ends, relative to each
other. It must not solve (that
is ``solve``) or measure against a truth (``evaluation.transfer``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .mesh import closest_points, edge_length

__all__ = [
    "APART",
    "CLOSED",
    "CONTACT_WEIGHT",
    "LID_CONTACT",
    "MEET",
    "RESOLVED",
    "Contacts",
    "closing_pairs",
    "contacts",
]

#: The expressions whose closing pairs are kept together on the target by default: the
#: blinks (README: on every shape, the lips' contacts raised mouthRollLower's error).
LID_CONTACT = ("eyeBlinkLeft", "eyeBlinkRight")
#: A pair, in the source's units (ICT's centimetres): within MEET in the expression, at
#: least APART at neutral (so neighbours on one lid do not count), and closed to less than
#: CLOSED of its neutral distance.
MEET = 0.1
APART = 0.3
CLOSED = 0.1
#: Each pair's term in the solve weighs this many times the median diagonal entry of the
#: transfer's normal matrix (README, measured at 1, 3 and 10).
CONTACT_WEIGHT = 1.0
#: The contact is left off where the target's lids are meshed coarser than the source's:
#: the median, over the pairs' vertices, of the target's edge length where the vertex lies
#: over the source's around it (in the target's units) above this. A coarser triangle
#: cannot bring the places the source's lids meet at together without bending (README:
#: ICT's face decimated to 4,000 vertices, 1.7, its blinks' error 9 -> 14 % with it;
#: denser targets 0.6-1.1).
RESOLVED = 1.25


def closing_pairs(
    neutral: npt.ArrayLike, closed: npt.ArrayLike, *, meet: float, apart: float
) -> np.ndarray:
    """(P, 2) vertex pairs ``closed`` brings together: within ``meet`` there, ``apart`` at neutral.

    ``neutral``, ``closed`` : (V, 3), one mesh's vertices (the mesh's units). Pairs at least
    ``apart`` apart at neutral, so neighbours on one lid (or a seam's twins) do not count.
    """
    rest = np.asarray(neutral, dtype=np.float64)
    shut = np.asarray(closed, dtype=np.float64)
    pairs = cKDTree(shut).query_pairs(meet, output_type="ndarray").reshape(-1, 2)
    distance = np.linalg.norm(rest[pairs[:, 0]] - rest[pairs[:, 1]], axis=1)
    kept: np.ndarray = pairs[distance >= apart]
    return kept


def _barycentric_rows(
    triangle: np.ndarray, barycentric: np.ndarray, faces: np.ndarray, count: int
) -> sp.csr_matrix:
    """(P, count) each point's barycentric weights on the corners of its triangle."""
    corners = faces[triangle]
    return sp.csr_matrix(
        (barycentric.ravel(), (np.repeat(np.arange(len(triangle)), 3), corners.ravel())),
        shape=(len(triangle), count),
    )


def _mean_edges(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) each triangle's mean edge length."""
    mean: np.ndarray = edge_length(vertices, faces).reshape(3, -1).mean(axis=0)
    return mean


def _vertex_edges(vertices: np.ndarray, faces: np.ndarray, which: np.ndarray) -> np.ndarray:
    """(W,) the mean edge length of the triangles around each of the vertices ``which``."""
    around = np.repeat(_mean_edges(vertices, faces), 3)
    total = np.bincount(faces.ravel(), weights=around, minlength=len(vertices))
    count = np.bincount(faces.ravel(), minlength=len(vertices))
    mean: np.ndarray = total[which] / count[which]
    return mean


@dataclass(frozen=True, eq=False)
class Contacts:
    """Terms ``rows @ displacement ≈ offsets`` on the target's vertex displacements.

    Attributes
    ----------
    pairs : (P, 2) int64
        Source vertices the expression brings together.
    rows : (P, Vt) scipy.sparse.csr_matrix
        Each pair's first place on the target minus its second (barycentric weights).
    offsets : (P, 3) float64
        The relative displacement that leaves each pair's places on the target as the
        source's expression leaves the pair (its first vertex less its second, in the
        target's units and axes): that, less the places' separation at neutral.
    """

    pairs: np.ndarray
    rows: sp.csr_matrix
    offsets: np.ndarray


def contacts(
    source_neutral: np.ndarray,
    source_deformed: np.ndarray,
    source_on_target: np.ndarray,
    target_neutral: np.ndarray,
    target_faces: np.ndarray,
    *,
    rotation: np.ndarray | None = None,
    scale: float = 1.0,
    meet: float = MEET,
    apart: float = APART,
    closed: float = CLOSED,
    resolved: float = RESOLVED,
    source_faces: np.ndarray | None = None,
) -> Contacts | None:
    """The contact terms of one expression, or None when it brings no pair together (or
    the target is meshed too coarsely there to bring them together: ``resolved``).

    Parameters
    ----------
    source_neutral, source_deformed : (Vs, 3) float
    source_on_target : (Vs, 3) float
        The source's vertices placed on the target (``Correspondence.fitted_source``): each
        pair's places are their closest points on the target's surface.
    target_neutral : (Vt, 3) float
    target_faces : (Ft, 3) int
    rotation : (3, 3) float, optional
    scale : float
        The source's axes and units turned into the target's (``Correspondence``), for
        the pairs' separation in the expression.
    source_faces : (Fs, 3) int, optional
        For the meshes' resolution where the pairs lie (without them no check).
    """
    pairs = closing_pairs(source_neutral, source_deformed, meet=meet, apart=apart)
    if len(pairs) == 0:
        return None
    before = np.linalg.norm(source_neutral[pairs[:, 0]] - source_neutral[pairs[:, 1]], axis=1)
    after = np.linalg.norm(source_deformed[pairs[:, 0]] - source_deformed[pairs[:, 1]], axis=1)
    share = after / before
    keep = share < closed
    if not keep.any():
        return None
    pairs = pairs[keep]
    used, inverse = np.unique(pairs, return_inverse=True)
    near = closest_points(source_on_target[used], target_neutral, target_faces)
    if source_faces is not None:
        target_edges = _mean_edges(target_neutral, target_faces[near.triangle])
        source_edges = _vertex_edges(source_neutral, source_faces, used)
        if np.median(target_edges / (scale * source_edges)) > resolved:
            return None
    places = _barycentric_rows(near.triangle, near.barycentric, target_faces, len(target_neutral))
    inverse = inverse.reshape(pairs.shape)
    rows = (places[inverse[:, 0]] - places[inverse[:, 1]]).tocsr()
    closed_in_source = source_deformed[pairs[:, 0]] - source_deformed[pairs[:, 1]]
    turned = np.eye(3) if rotation is None else rotation
    wanted = scale * closed_in_source @ turned.T
    return Contacts(pairs, rows, wanted - rows @ target_neutral)
