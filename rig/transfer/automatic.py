"""The source placed on a target without markers: a similarity fitted to closest points.

For ``fit_correspondence`` with no markers: the source neutral is scaled and moved onto the
target by their centroids and spreads, then turned, scaled and moved by iterated closest
points (Umeyama's similarity of each step's trimmed pairs). It assumes the two faces look
the same way (ICT's axes: y up, the face towards +z, as glTF's and VRM 1.0's do); it must
not deform the source (that is ``correspondence``'s closest-point phase).
"""

from __future__ import annotations

import numpy as np

from ..errors import CorrespondenceError
from .mesh import closest_points, edge_length, vertex_normals

__all__ = ["place_by_closest_points", "similarity"]

#: Closest-point steps of the similarity fit (it settles within about 15 on ICT's faces).
STEPS = 30
# A pair counts if its distance is below this many times the step's median distance
# (trims what only one mesh has: a neck, the back of a head).
_TRIM = 3.0
# The fit's scale may differ from the spreads' ratio by this factor at most: beyond it the
# source has shrunk onto a patch of the target (or grown past it), which is no face's fit
# (ICT's identities stay within 3 %).
_SCALE_DRIFT = 2.0


def similarity(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R, translation t minimising |s R source + t - target| (Umeyama)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    a, b = source - mu_s, target - mu_t
    u, sigma, vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(u @ vt))
    flip = np.array([1.0, 1.0, d])
    rotation = (u * flip) @ vt
    scale = float((sigma * flip).sum() / (a**2).sum())
    return scale, rotation, mu_t - scale * rotation @ mu_s


def place_by_closest_points(
    source: np.ndarray,
    source_faces: np.ndarray,
    target: np.ndarray,
    target_faces: np.ndarray,
    *,
    steps: int = STEPS,
) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (s, R, t) placing ``source`` on ``target``'s surface, no markers.

    Start: centroids matched, scaled by the ratio of the root-mean-square distances to
    them, axes unchanged. Then ``steps`` times: each source vertex's closest compatible
    point on the target (normals within 90°), pairs beyond ``_TRIM`` × their median
    distance (and one target edge) dropped, the similarity of the rest composed on.

    Raises
    ------
    CorrespondenceError
        ``not_converged``: the scale drifted more than ``_SCALE_DRIFT`` times from the
        spreads' ratio (the source shrank onto a part of the target: not a face, or not
        one seen the way ICT's is).
    """
    centre_s, centre_t = source.mean(axis=0), target.mean(axis=0)
    spread_s = np.sqrt(((source - centre_s) ** 2).sum(axis=1).mean())
    spread_t = np.sqrt(((target - centre_t) ** 2).sum(axis=1).mean())
    scale = float(spread_t / spread_s)
    rotation = np.eye(3)
    shift = centre_t - scale * centre_s
    edge = float(np.median(edge_length(target, target_faces)))
    for _ in range(steps):
        placed = scale * source @ rotation.T + shift
        near = closest_points(placed, target, target_faces,
                              normals=vertex_normals(placed, source_faces))  # fmt: skip
        found = np.flatnonzero(near.found)
        if found.size < 3:
            break
        distance = near.distance[found]
        keep = found[distance <= max(_TRIM * float(np.median(distance)), edge)]
        s, r, t = similarity(placed[keep], near.points[keep])
        scale, rotation, shift = s * scale, r @ rotation, s * r @ shift + t
    drift = scale * spread_s / spread_t
    if not 1.0 / _SCALE_DRIFT <= drift <= _SCALE_DRIFT:
        raise CorrespondenceError(
            f"without markers the source face was scaled by {drift:.3g} times the ratio of the "
            "two meshes' sizes to fit the target: the target does not look like a face facing "
            "+z with y up (or holds much more than the face). Turn or crop it, or give markers",
            code="not_converged",
        )
    return scale, rotation, shift
