"""Eq. 3.14's product ``weights @ basis``, done with only the basis rows a batch's weights use.

Bounded weights (``clamp``) are mostly exactly 0, and most of a head never moves: the
blend reads only what a frame needs. Arrays in, arrays out; ``Rig.blend`` validates.
Small batches go to the compiled row blend (``rig.kernel.blend_rows``), which reads each
basis row some frame uses once per batch; without it numpy's and scipy's products do.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse

from .kernel import blend_rows, place_columns

__all__ = ["Placement", "blend_into", "blend_plan", "moving_vertices"]

Plan = Literal["rows", "dense", "gathered", "sparse"]


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


@dataclass(frozen=True)
class Placement:
    """Where a product's columns go in a wider output: ``out[:, columns] = product``.

    Attributes
    ----------
    columns : (C,) int64, increasing
    runs : (R, 3) int64
        The runs of consecutive ``columns``: (product column, out column, count) each.
    """

    columns: np.ndarray
    runs: np.ndarray

    @classmethod
    def of(cls, columns: np.ndarray) -> Placement:
        """The placement of ``columns`` ((C,) int, increasing), its runs found."""
        columns = np.asarray(columns, dtype=np.int64)
        starts = np.flatnonzero(np.diff(columns, prepend=-2) != 1)
        counts = np.diff(starts, append=columns.size)
        runs = np.stack([starts, columns[starts], counts], axis=1).astype(np.int64)
        return cls(columns, np.ascontiguousarray(runs))


def blend_plan(weights: np.ndarray, *, compiled: bool | None = None) -> tuple[Plan, np.ndarray]:
    """How ``blend_into`` multiplies these (B, M) weights, and the basis rows they use.

    Parameters
    ----------
    weights : (B, M) float32
    compiled : bool, optional
        Whether the compiled row blend may be taken; by default whether it is built and
        not disabled (``rig.kernel.blend_rows``).

    The plan depends on the weights alone, never on where the product goes: a full blend
    and a moving blend of the same weights must take the same arithmetic (``Rig.blend``
    promises them equal bit for bit). A full blend's scatter would favour the rows more
    (numpy's scatter of the moving columns: ~0.2 M row reads for one frame, ~0.6 M a
    frame for more), but only where BLAS wins anyway (7 or more frames of dense weights).

    A blend streams basis rows from memory, so each way is costed in reads of one row.
    With the compiled row blend ("rows"), a batch reads the U rows some frame uses once,
    and adds each non-zero weight's row from the cache: measured on ICT's moving columns
    (M = 56, 62,181 columns, 14 MB; the whole mesh's 80,157 scale alike) on a loaded
    2-core machine, one OpenBLAS thread, it costs about 0.8 U + 0.25 (non-zero weights)
    row reads, BLAS's dense product M (1.75 + 0.1 B) for B > 1 (it packs the basis first)
    and, for one frame (a matrix-vector product), 1.08 M on that machine but about 0.8 M
    on another of the same kind (below): 0.9 M is taken, so one frame of exact weights
    goes to BLAS (a tie on the first machine, 22 % less on the second), one of bounded
    weights to the rows. Per frame, µs, rows / dense (the first machine):

    ===========  ==========  ==========  ==========  ==========  ==========  ==========
    B            1           2           4           8           16          32
    exact        510 / 523   301 / 470   200 / 255   160 / 141   145 / 90    153 / 83
    bounded      322 / 537   156 / 512   135 / 265   105 / 148   94 / 102    85 / 76
    ===========  ==========  ==========  ==========  ==========  ==========  ==========

    (exact weights: all 56 rows; bounded, ``fit(..., noise=0.01, clamp="nonneg")``: ~30
    non-zero a frame, 33 rows for one frame, ~48 for 4 or more.) So dense weights take
    the rows from 2 up to 6 frames, bounded ones up to about 24. On the second machine
    (AMD EPYC, 2026-12-02, quiet, the basis evicted from the cache before each product,
    the row blend with 64 columns of partial sums):

    ===========  ==========  ==========  ==========  ==========  ==========  ==========
    B            1           2           4           8           16          32
    exact        515 / 401   290 / 538   200 / 269   155 / 170   131 / 120   123 / 94
    bounded      415 / 475   248 / 546   152 / 271   132 / 170   95 / 124    83 / 103
    ===========  ==========  ==========  ==========  ==========  ==========  ==========

    The gathered and CSR products lose to the rows everywhere (2 frames: 889 and 725 µs
    exact, 408 and 370 bounded) and are taken only without the extension: then the dense
    product is costed M for any batch, a gathered product (U rows copied, written, read
    back and multiplied) ~3U, the CSR product one row per non-zero weight (ICT's moving
    columns, bounded weights with ~7 non-zero a frame, measured on a loaded 2-core
    machine: 2 frames of different sessions 210 µs a frame sparse, 305 gathered, 600
    dense; 5 frames 130 / 150 / 230; 16 frames 370 / 135 / 110).
    """
    batch, m = weights.shape
    used = np.flatnonzero(weights.any(axis=0))
    nonzero = int(np.count_nonzero(weights))
    if compiled is None:
        compiled = blend_rows() is not None
    if compiled:
        rows = 0.8 * used.size + 0.25 * nonzero
        dense = m * (0.9 if batch == 1 else 1.75 + 0.1 * batch)
        return ("rows" if rows <= dense else "dense"), used
    costs: dict[Plan, int] = {"dense": m, "gathered": 3 * used.size}
    costs["sparse"] = nonzero
    return min(costs, key=costs.__getitem__), used


def blend_into(
    weights: np.ndarray,
    basis: np.ndarray,
    out: np.ndarray | None,
    *,
    placement: Placement | None = None,
) -> np.ndarray:
    """``weights @ basis``, reading only the basis rows the weights need.

    Parameters
    ----------
    weights : (B, M) float32
        Blend weights, column 0 set to 1 (it multiplies the neutral row).
    basis : (M, C) float32, C-contiguous
    out : (B, C) float32, C-contiguous, or None
        Where to write the product; None returns a new array (for a caller that only
        reads it: the sparse product is then not copied into a scratch buffer).
    placement : Placement, optional
        Write the product's columns into these columns of ``out`` (B, wider), leaving
        its others as they are; the row blend writes them in place, the other products
        are scattered there (numpy's scatter of ICT's 62k moving columns into a batch
        costs ~300 µs a frame).

    Row, sparse, gathered and dense products of the same weights agree to float rounding
    (other summation orders), not bit for bit; so may products over different column
    sets (BLAS blocks columns by position; the row blend does not, but the plan depends
    on the weights only), which is why ``Rig.blend`` takes every output, full or moving,
    from the one product over the moving columns.
    """
    kernel = blend_rows()
    plan, used = blend_plan(weights, compiled=kernel is not None)
    if plan == "rows":
        assert kernel is not None
        if out is None:
            out = np.empty((weights.shape[0], basis.shape[1]), np.float32)
        runs = None if placement is None else placement.runs
        kernel(np.ascontiguousarray(weights, dtype=np.float32), basis, out, runs)
        return out
    if placement is not None:
        if out is None:
            raise ValueError("blend_into: a placement needs out")
        product = _product(plan, used, weights, basis, None)
        place = place_columns()
        if place is not None:
            place(np.ascontiguousarray(product, dtype=np.float32), out, placement.runs)
        elif weights.shape[0] == 1:  # numpy's 1-d scatter is ~1.5x its 2-d one
            out.reshape(-1)[placement.columns] = product.reshape(-1)
        else:
            out[:, placement.columns] = product
        return out
    return _product(plan, used, weights, basis, out)


def _product(
    plan: Plan, used: np.ndarray, weights: np.ndarray, basis: np.ndarray, out: np.ndarray | None
) -> np.ndarray:
    """numpy's or scipy's ``weights @ basis`` the way ``plan`` says (not "rows")."""
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
