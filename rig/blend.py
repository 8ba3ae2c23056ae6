"""Eq. 3.14's product ``weights @ basis``, done with only the basis rows a batch's weights use.

Bounded weights (``clamp``) are mostly exactly 0, and most of a head never moves: the
blend reads only what a frame needs. Arrays in, arrays out; ``Rig.blend`` validates.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import scipy.sparse

__all__ = ["blend_into", "blend_plan", "moving_vertices"]

Plan = Literal["dense", "gathered", "sparse"]


def moving_vertices(basis: np.ndarray) -> np.ndarray:
    """Indices of the vertices that some example moves: (N,) int64, increasing.

    Parameters
    ----------
    basis : (M, 3V) float32
        Row 0 the neutral T_B, rows i > 0 the deltas T_i - T_B (``Rig.blend_basis``).

    A vertex is moving when any coordinate of any delta is not exactly 0; every other
    vertex is T_B in every blend, bit for bit (T_B + sum of exact zeros).
    """
    moved = (basis[1:] != 0).any(axis=0)
    return np.flatnonzero(moved.reshape(-1, 3).any(axis=1))


def blend_plan(weights: np.ndarray) -> tuple[Plan, np.ndarray]:
    """How ``blend_into`` multiplies these (B, M) weights, and the basis rows they use.

    A blend only streams basis rows from memory, so each way is costed in rows read:
    the dense product reads all M rows once for the whole batch; a gathered product
    copies the U rows some frame uses (written, read back) and multiplies them, ~3U;
    the sparse (CSR) product reads one row per non-zero weight. The cheapest is taken
    (ICT's moving columns, M = 56, bounded weights with ~7 non-zero a frame, measured
    on a loaded 2-core machine: 2 frames of different sessions 210 µs a frame sparse,
    305 gathered, 600 dense; 5 frames 130 / 150 / 230; 16 frames 370 / 135 / 110).
    """
    used = np.flatnonzero(weights.any(axis=0))
    nonzero = int(np.count_nonzero(weights))
    costs: dict[Plan, int] = {"dense": weights.shape[1], "gathered": 3 * used.size}
    costs["sparse"] = nonzero
    return min(costs, key=costs.__getitem__), used


def blend_into(weights: np.ndarray, basis: np.ndarray, out: np.ndarray | None) -> np.ndarray:
    """``weights @ basis``, reading only the basis rows the weights need.

    Parameters
    ----------
    weights : (B, M) float32
        Blend weights, column 0 set to 1 (it multiplies the neutral row).
    basis : (M, C) float32, C-contiguous
    out : (B, C) float32, C-contiguous, or None
        Where to write the product; None returns a new array (for a caller that only
        reads it: the sparse product is then not copied into a scratch buffer).

    Sparse, gathered and dense products of the same weights agree to float rounding
    (other summation orders), not bit for bit; so may products over different column
    sets (BLAS blocks columns by position), which is why ``Rig.blend`` takes every
    output, full or moving, from the one product over the moving columns.
    """
    plan, used = blend_plan(weights)
    if plan == "dense":
        return np.matmul(weights, basis, out=out)
    if plan == "gathered":
        # Gather the used rows once and let BLAS read them once for every frame.
        return np.matmul(weights[:, used], basis[used], out=out)
    # scipy's CSR product adds w_i * row_i for each frame's non-zero weights straight
    # from the basis, with no gathered copy. The CSR arrays are built here: scipy's own
    # conversion of a dense array goes through COO (33 µs a frame against 10).
    frames, examples = np.nonzero(weights)
    indptr = np.zeros(weights.shape[0] + 1, np.int64)
    np.cumsum(np.bincount(frames, minlength=weights.shape[0]), out=indptr[1:])
    sparse = scipy.sparse.csr_array((weights[frames, examples], examples, indptr), weights.shape)
    product: np.ndarray = sparse @ basis
    if out is None:
        return product
    np.copyto(out, product)
    return out
