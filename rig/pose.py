"""Rigid and similarity alignment of feature-point frames (Kabsch / Umeyama), batched.

Used to remove head pose from tracker input and to calibrate a performer; no fitting here.

Head-pose removal has two steps. ``align_points`` maps each frame onto the neutral by the
transform fitted on the stable points alone: exact only when the expression leaves them
still, and no feature point is perfectly still (on ICT-FaceKit every landmark moves
0.07-4 cm in some shape). ``refine_pose`` then solves for the remaining small rigid
motion jointly with the expression: the frame minus the neutral must lie in the span of
the examples' displacements (``expression_basis``), so the part of it outside that span
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
    "expression_basis",
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
# takes more, hence the cap. A step below the tolerance leaves an error of about its
# square, rounding, so it ends the loop.
_REFINE_STEPS = 20
_REFINE_TOLERANCE = 1e-8


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
    moved: np.ndarray = np.einsum("bij,bkj->bki", rotation, points)
    moved *= scales[:, None, None]
    moved += translation[:, None, :]
    return moved


def expression_basis(directions: np.ndarray, *, rtol: float = 1e-9) -> np.ndarray:
    """Orthonormal basis of the span of ``directions`` (the displacements expressions make).

    Parameters
    ----------
    directions : (D, 3K) float
        Rows spanning the expression displacements (a rig's mean and principal axes).
    rtol : float
        Singular values below ``rtol`` times the largest count as zero.

    Returns
    -------
    (R, 3K) float64, R = rank(directions) <= D: orthonormal rows (a thin SVD, so the cost
    grows with D, not with 3K).
    """
    directions = np.asarray(directions, dtype=np.float64)
    _, singular, vt = np.linalg.svd(directions, full_matrices=False)
    top = singular[0] if singular.size and singular[0] > 0 else 1.0
    return vt[: int((singular > rtol * top).sum())].copy()


def pose_jacobian(centred: np.ndarray, *, scale: bool = False) -> np.ndarray:
    """Derivative of flattened frames under a small rotation, translation (and scale).

    Parameters
    ----------
    centred : (B, K, 3) float
        Frames minus their centroids.
    scale : bool
        Add a seventh column: uniform scale about the centroid.

    Returns
    -------
    (B, 3K, 6) or (B, 3K, 7) float64
        Columns: rotation vector (x, y, z) about the centroid, translation (x, y, z),
        [scale]: d/dθ of ``vec(R(θ) y + t)`` (times ``1 + s``) at θ = 0.
    """
    b, k, _ = centred.shape
    y = centred
    jac = np.zeros((b, k, 3, 7 if scale else 6))
    # d(w x y)/dw = -[y]x
    jac[:, :, 0, 1], jac[:, :, 0, 2] = y[:, :, 2], -y[:, :, 1]
    jac[:, :, 1, 0], jac[:, :, 1, 2] = -y[:, :, 2], y[:, :, 0]
    jac[:, :, 2, 0], jac[:, :, 2, 1] = y[:, :, 1], -y[:, :, 0]
    jac[:, :, 0, 3] = jac[:, :, 1, 4] = jac[:, :, 2, 5] = 1.0
    if scale:
        jac[:, :, :, 6] = y
    return jac.reshape(b, 3 * k, -1)


def _outside(basis: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """The part of each column of (B, 3K, P) ``vectors`` outside the span of ``basis`` (R, 3K)."""
    outside: np.ndarray = vectors - basis.T @ (basis @ vectors)  # matmul broadcasts over B
    return outside


def pose_condition(basis: np.ndarray, reference: np.ndarray, *, scale: bool = False) -> float:
    """Condition number of the pose Jacobian outside the expressions, at ``reference``.

    inf when the expressions leave fewer than 6 (7 with ``scale``) directions free; large
    when some rigid motion of the neutral is nearly an expression. Either way
    ``refine_pose`` could not tell head motion from expression.
    """
    columns = 7 if scale else 6
    if reference.size - basis.shape[0] < columns:
        return float("inf")
    centred = reference[None] - reference.mean(axis=0)
    return float(np.linalg.cond(_outside(basis, pose_jacobian(centred, scale=scale))[0]))


def refine_pose(
    points: np.ndarray, reference: np.ndarray, basis: np.ndarray, *, scale: bool = False
) -> np.ndarray:
    """Remove the rigid motion (and scale) that the expressions cannot explain.

    Gauss-Newton on the pose parameters θ: minimise |Q (x(θ) - reference)|, Q the projection
    outside the expression span, so the expression part of the frame costs nothing.

    Parameters
    ----------
    points : (B, K, 3) float
        Frames already roughly aligned to ``reference`` (by ``align_points``).
    reference : (K, 3) float
        The neutral the expressions displace.
    basis : (R, 3K) float
        ``expression_basis`` of the rig's displacement directions, in the frames' space,
        with ``pose_condition`` finite.
    scale : bool

    Returns
    -------
    (B, K, 3) float64
    """
    out = np.array(points, dtype=np.float64)
    finite = np.isfinite(out).all(axis=(1, 2))
    # Non-finite frames pass through unchanged for the caller to report.
    x = out[finite] if not finite.all() else out
    b = x.shape[0]
    for _ in range(_REFINE_STEPS if b else 0):
        centroid = x.mean(axis=1, keepdims=True)
        centred = x - centroid
        residual = _outside(basis, (x - reference).reshape(b, -1, 1))[:, :, 0]  # (B, 3K)
        projected = _outside(basis, pose_jacobian(centred, scale=scale))  # (B, 3K, 6|7)
        step = _least_squares_step(projected, residual)
        rotation = Rotation.from_rotvec(step[:, :3]).as_matrix()
        factor = 1.0 + step[:, 6, None, None] if scale else 1.0
        x = factor * np.einsum("bij,bkj->bki", rotation, centred) + centroid
        x += step[:, None, 3:6]
        if not np.abs(step).max() > _REFINE_TOLERANCE:
            break
    if x is not out:
        out[finite] = x
        return out
    return x


def _least_squares_step(projected: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """argmin |P θ + r| per frame: normal equations (6 x 6), the pseudo-inverse if singular.

    P's conditioning at the neutral is checked at fit (``pose_condition``); a degenerate
    frame (all points at one place) makes it singular, and then gets no rotation.
    """
    normal = np.einsum("bjp,bjq->bpq", projected, projected)
    rhs = -np.einsum("bjp,bj->bp", projected, residual)
    step: np.ndarray
    try:
        step = np.linalg.solve(normal, rhs[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        step = -np.einsum("bpj,bj->bp", np.linalg.pinv(projected, rcond=1e-12), residual)
    return step
