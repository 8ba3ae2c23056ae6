"""Another shape with a known truth: a smooth map applied to a face and to all its shapes.

For measuring deformation transfer where ICT's identities cannot: ICT adds the same deltas
to every identity, so its taller eyes' true blinks leave the lids apart. A map of space
applied to every shape keeps what meets meeting (two points at one place go to one place),
so a face whose eyes are stretched this way has a true blink that closes its lids. Pure
array code, no files, no fitting.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["motion_centre", "stretch_about"]


def motion_centre(neutral: npt.ArrayLike, shape: npt.ArrayLike) -> np.ndarray:
    """(3,) the mean of ``neutral``'s vertices weighted by how far ``shape`` moves them."""
    rest = np.asarray(neutral, dtype=np.float64)
    motion = np.linalg.norm(np.asarray(shape, dtype=np.float64) - rest, axis=1)
    centre: np.ndarray = (rest * motion[:, None]).sum(axis=0) / motion.sum()
    return centre


def stretch_about(
    points: npt.ArrayLike,
    centres: npt.ArrayLike,
    *,
    factor: float,
    reach: float,
    axis: int = 1,
) -> np.ndarray:
    """``points`` (..., 3) stretched ``factor`` × along ``axis`` about each of ``centres``
    (C, 3), fading out smoothly ((1 − (r / reach)²)²) within ``reach`` of each centre.

    With ``factor`` − 1 small beside 1 the map is one to one (its derivative along
    ``axis`` stays positive), so it is a change of shape, not a fold.
    """
    moved = np.array(points, dtype=np.float64)
    for centre in np.asarray(centres, dtype=np.float64).reshape(-1, 3):
        r = np.linalg.norm(moved - centre, axis=-1)
        fade = np.where(r < reach, (1.0 - (r / reach) ** 2) ** 2, 0.0)
        moved[..., axis] += (factor - 1.0) * (moved[..., axis] - centre[axis]) * fade
    return moved
