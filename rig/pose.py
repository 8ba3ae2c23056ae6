"""Rigid and similarity alignment of feature-point frames (Kabsch / Umeyama), batched.

Used to remove head pose from tracker input and to calibrate a performer; no fitting here.
"""

from __future__ import annotations

import numpy as np

__all__ = ["align_points", "similarity_transform"]


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
