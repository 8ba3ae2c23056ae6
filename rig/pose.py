"""Rigid and similarity alignment of feature-point frames (Kabsch / Umeyama), batched.

Used to remove head pose from tracker input and to calibrate a performer; no fitting here.

Head-pose removal has two steps. ``align_points`` maps each frame onto the neutral by the
transform fitted on the stable points alone: exact only when the expression leaves them
still, and no feature point is perfectly still (on ICT-FaceKit every landmark moves
0.07-4 cm in some shape). ``refine_pose`` then solves for the remaining small rigid
motion jointly with the expression: the frame minus the neutral must lie in the span of
the examples' displacements, so the part of it outside that span (``expression_complement``)
that a small rotation and translation explain is head motion (Gauss-Newton on the six
pose parameters, the expression eliminated by the projection). A frame that is an example
under any rigid motion then comes back as that example to rounding.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "POSE_REFINE_MAX_CONDITION",
    "align_points",
    "expression_complement",
    "pose_condition",
    "pose_jacobian",
    "refine_pose",
    "similarity_transform",
]

#: Largest condition number of the projected pose Jacobian (at the neutral) for which the
#: refinement is used; above it the rigid motions are nearly expressions of the rig.
POSE_REFINE_MAX_CONDITION = 1e6
# Gauss-Newton steps: near the solution the error squares each step (on ICT-FaceKit 4-5
# steps reach rounding from the stable-point alignment); a frame far from any expression
# takes more, hence the cap. A step below the tolerance ends the loop early.
_REFINE_STEPS = 20
_REFINE_TOLERANCE = 1e-12


def similarity_transform(
    moving: np.ndarray, reference: np.ndarray, *, scale: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares rotation (+ optional uniform scale) taking ``moving`` onto ``reference``.

    Parameters
    ----------
    moving : (B, N, 3) float
    reference : (N, 3) float
    scale : bool
        Also solve a uniform scale (Umeyama 1991); otherwise rigid (Kabsch).

    Returns
    -------
    rotation : (B, 3, 3), scales : (B,), translation : (B, 3)
        ``reference ≈ scales * moving @ rotation.T + translation`` per frame.
    """
    mu_m = moving.mean(axis=1)  # (B, 3)
    mu_r = reference.mean(axis=0)  # (3,)
    xm = moving - mu_m[:, None, :]
    xr = reference - mu_r
    cov = np.einsum("bni,nj->bji", xm, xr)  # (B, 3, 3): sum_n xr_n xm_n^T
    u, s, vt = np.linalg.svd(cov)
    det = np.linalg.det(u @ vt)
    d = np.ones_like(s)
    d[:, 2] = np.sign(det)
    d[d == 0] = 1.0
    rotation = (u * d[:, None, :]) @ vt
    if scale:
        var_m = np.einsum("bni,bni->b", xm, xm)
        scales = np.where(var_m > 0, (s * d).sum(axis=1) / np.where(var_m > 0, var_m, 1), 1.0)
    else:
        scales = np.ones(moving.shape[0])
    translation = mu_r - scales[:, None] * np.einsum("bij,bj->bi", rotation, mu_m)
    return rotation, scales, translation


def align_points(
    points: np.ndarray,
    reference: np.ndarray,
    *,
    stable: np.ndarray | None = None,
    scale: bool = False,
) -> np.ndarray:
    """Remove head pose: map each frame onto ``reference`` by the transform fitted on ``stable``.

    Parameters
    ----------
    points : (B, K, 3) float
    reference : (K, 3) float
    stable : (S,) int, optional
        Indices of feature points that expressions barely move (nose bridge, temples...);
        all points when omitted.
    scale : bool
        Also remove uniform scale (distance to the camera).

    Returns
    -------
    (B, K, 3) float64
    """
    idx = slice(None) if stable is None else stable
    rotation, scales, translation = similarity_transform(
        points[:, idx, :], reference[idx], scale=scale
    )
    moved = np.einsum("bij,bkj->bki", rotation, points)
    moved *= scales[:, None, None]
    moved += translation[:, None, :]
    return moved


def expression_complement(directions: np.ndarray, *, rtol: float = 1e-9) -> np.ndarray:
    """Orthonormal basis of the displacements that no combination of ``directions`` makes.

    Parameters
    ----------
    directions : (D, 3K) float
        Rows spanning the expression displacements (a rig's mean and principal axes).
    rtol : float
        Singular values below ``rtol`` times the largest count as zero.

    Returns
    -------
    (C, 3K) float64, C = 3K - rank(directions); rows orthonormal and orthogonal to every row
    of ``directions``.
    """
    directions = np.asarray(directions, dtype=np.float64)
    width = directions.shape[1]
    _, singular, vt = np.linalg.svd(directions, full_matrices=True)
    top = singular[0] if singular.size and singular[0] > 0 else 1.0
    rank = int((singular > rtol * top).sum())
    return vt[rank:width].copy()


def pose_condition(complement: np.ndarray, reference: np.ndarray, *, scale: bool = False) -> float:
    """Condition number of the projected pose Jacobian at ``reference`` (inf if too few rows).

    Large means some rigid motion of the neutral is (nearly) an expression of the rig, so
    ``refine_pose`` cannot tell the two apart.
    """
    columns = 7 if scale else 6
    if complement.shape[0] < columns:
        return float("inf")
    projected = complement @ pose_jacobian(reference[None], scale=scale)[0]
    return float(np.linalg.cond(projected))


def pose_jacobian(points: np.ndarray, *, scale: bool = False) -> np.ndarray:
    """Derivative of flattened points under a small rotation, translation (and scale).

    Parameters
    ----------
    points : (B, K, 3) float
    scale : bool
        Add a seventh column: uniform scale about the centroid.

    Returns
    -------
    (B, 3K, 6) or (B, 3K, 7) float64
        Columns: rotation vector (x, y, z) about the frame's centroid, translation (x, y, z),
        [scale]: d/dθ of ``R(θ) (p - c) + c + t`` at θ = 0.
    """
    b, k, _ = points.shape
    y = points - points.mean(axis=1, keepdims=True)
    jac = np.zeros((b, k, 3, 7 if scale else 6))
    # d(omega x y)/d omega = -[y]_x
    jac[:, :, 0, 1], jac[:, :, 0, 2] = y[:, :, 2], -y[:, :, 1]
    jac[:, :, 1, 0], jac[:, :, 1, 2] = -y[:, :, 2], y[:, :, 0]
    jac[:, :, 2, 0], jac[:, :, 2, 1] = y[:, :, 1], -y[:, :, 0]
    jac[:, :, 0, 3] = jac[:, :, 1, 4] = jac[:, :, 2, 5] = 1.0
    if scale:
        jac[:, :, :, 6] = y
    return jac.reshape(b, 3 * k, -1)


def refine_pose(
    points: np.ndarray, reference: np.ndarray, complement: np.ndarray, *, scale: bool = False
) -> np.ndarray:
    """Remove the rigid motion (and scale) that the expressions cannot explain.

    Parameters
    ----------
    points : (B, K, 3) float
        Frames already roughly aligned to ``reference`` (by ``align_points``).
    reference : (K, 3) float
        The neutral the expressions displace.
    complement : (C, 3K) float
        ``expression_complement`` of the rig's displacement directions (in the frames'
        space), C >= 6 (7 with ``scale``).
    scale : bool

    Returns
    -------
    (B, K, 3) float64
        Each frame moved by the small rigid transform that minimises the part of
        ``frame - reference`` outside the expression span.
    """
    out = np.array(points, dtype=np.float64)
    finite = np.isfinite(out).all(axis=(1, 2))
    # Non-finite frames pass through unchanged for the caller to report.
    x = out[finite] if not finite.all() else out
    b = x.shape[0]
    flat_reference = reference.reshape(-1)
    for _ in range(_REFINE_STEPS if b else 0):
        residual = (x.reshape(b, -1) - flat_reference) @ complement.T  # (B, C)
        projected = np.einsum("cj,bjp->bcp", complement, pose_jacobian(x, scale=scale))
        # Least squares through the pseudo-inverse: a degenerate frame (all points at one
        # place) gets no rotation instead of a singular-matrix error.
        step = -np.einsum("bpc,bc->bp", np.linalg.pinv(projected, rcond=1e-12), residual)
        centroid = x.mean(axis=1, keepdims=True)
        rotation = Rotation.from_rotvec(step[:, :3]).as_matrix()
        factor = 1.0 + step[:, 6, None, None] if scale else 1.0
        x = factor * np.einsum("bij,bkj->bki", rotation, x - centroid) + centroid
        x += step[:, None, 3:6]
        if not np.abs(step).max() > _REFINE_TOLERANCE:
            break
    if x is not out:
        out[finite] = x
        return out
    return x
