"""Deformation transfer's linear solve: a source's per-triangle deformations onto a target.

Sumner & Popović 2004, section 3: the target's deformed vertices are the least-squares fit
of its triangles' transformations to those of their corresponding source triangles. The
matrix depends only on the target neutral and the correspondence, so the paper's system is
factored once and every expression is one back-substitution; with ``still`` each
expression holds the target points whose source point barely moves and factors what is
left, and may keep the pairs it brings together together (``contact``). It must not read
files or find the correspondence (that is ``correspondence``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.linalg import SuperLU, splu

from ..errors import CorrespondenceError, InputError
from .contact import CONTACT_WEIGHT, contacts
from .mesh import check_mesh, frame_inverses, triangle_frames, vertex_components

__all__ = ["STILL", "DeformationTransfer", "check_still", "frame_rows", "source_gradients"]

# Expressions solved together: one back-substitution with 3 x _CHUNK right-hand sides.
_CHUNK = 8
#: Default ``still``: a target point whose corresponding source point moves less than this
#: fraction of the expression's largest source displacement is held (README, measured).
STILL = 0.01


def check_still(still: float | None) -> float | None:
    """``still`` as a float in (0, 1), or None; a ``CorrespondenceError`` otherwise."""
    if still is None:
        return None
    if not (isinstance(still, (int, float)) and np.isfinite(still) and 0.0 < still < 1.0):
        raise CorrespondenceError(
            f"still: expected a fraction in (0, 1) or None, got {still!r}", code="bad_weights"
        )
    return float(still)


def frame_rows(inverses: np.ndarray, faces: np.ndarray, num_vertices: int) -> sp.csr_matrix:
    """The (3F, V + F) matrix taking vertices and fourth vertices to transformations.

    Row 3t + k of the product with one coordinate of the unknowns (V vertices, then one
    fourth vertex per triangle) is column k of that coordinate's row of triangle t's
    transformation Ṽ V⁻¹ (eq. 3 with the frames of ``triangle_frames``): the same matrix
    serves x, y and z.
    """
    f = faces.shape[0]
    columns = np.stack(
        [faces[:, 0], faces[:, 1], faces[:, 2], num_vertices + np.arange(f)], axis=1
    )  # (F, 4): v1, v2, v3, v4
    # d/dv2, d/dv3, d/dv4 of column k are the rows of V⁻¹; d/dv1 is minus their sum.
    coefficients = np.empty((f, 3, 4))
    coefficients[:, :, 1:] = inverses.transpose(0, 2, 1)
    coefficients[:, :, 0] = -inverses.sum(axis=1)
    rows = np.repeat(np.arange(3 * f), 4)
    cols = np.repeat(columns, 3, axis=0).ravel()
    matrix: sp.csr_matrix = sp.csr_matrix(
        (coefficients.ravel(), (rows, cols)), shape=(3 * f, num_vertices + f)
    )
    return matrix


def source_gradients(
    source_neutral: np.ndarray, source_deformed: np.ndarray, faces: np.ndarray
) -> np.ndarray:
    """(..., F, 3, 3) transformations Q = Ṽ V⁻¹ of every source triangle (eq. 3)."""
    gradients: np.ndarray = triangle_frames(source_deformed, faces) @ frame_inverses(
        source_neutral, faces
    )
    return gradients


class DeformationTransfer:
    """The transfer onto one target neutral for one triangle correspondence, factored once.

    Parameters
    ----------
    source_neutral : (Vs, 3) float
    source_faces : (Fs, 3) int
    target_neutral : (Vt, 3) float
    target_faces : (Ft, 3) int
    pairs : (P, 2) int
        (source triangle, target triangle) correspondences, the paper's set M. A target
        triangle in several pairs is fitted to all of them; one in none keeps its neutral
        shape (its transformation is fitted to the identity).
    vertex_map : (Vt, Vs) sparse, optional
        Each target vertex's corresponding source point as interpolation weights (rows of
        unmatched vertices empty). It fixes each connected piece's translation, which the
        gradients leave free: the piece moves as its mapped vertices' source points do (median).
        Without it every piece's first vertex stays where it is.
    rotation : (3, 3) float, optional
        The rotation from the source's axes to the target's (``Correspondence.rotation``):
        transformations are turned into the target's frame, R (Q − I) Rᵀ.
    scale : float
        Target units per source unit, for the source displacements ``vertex_map`` reads.
    still : float or None
        With ``vertex_map``: for each expression, the target vertices whose corresponding
        source point moves less than ``still`` times the expression's largest source
        displacement are held where that point goes (the solve's boundary conditions, so
        the parts the expression leaves still do not drift with what least squares could
        not fit elsewhere); the rest is solved with those held, one factorisation per
        expression of the unknowns they leave. None: the paper's system, factored once,
        one vertex held per connected piece and each piece then placed by the median.
    source_on_target : (Vs, 3) float, optional
        The source's vertices placed on the target (``Correspondence.fitted_source``); with
        ``still``, ``transfer(..., contact=...)`` keeps the pairs an expression brings
        together together there (``contact.contacts``).
    contact_weight : float
        Each contact pair's weight, times the median diagonal entry of the normal matrix.

    Notes
    -----
    The unknowns are the displacements of the Vt vertices and of one fourth vertex per
    target triangle; one vertex per connected piece is held, so the normal matrix is
    positive definite and its sparse LU (``splu``) is computed once, here (with ``still``,
    only if ``factor`` is asked for: each expression factors its own smaller system).
    """

    def __init__(
        self,
        source_neutral: npt.ArrayLike,
        source_faces: npt.ArrayLike,
        target_neutral: npt.ArrayLike,
        target_faces: npt.ArrayLike,
        pairs: npt.ArrayLike,
        *,
        vertex_map: sp.spmatrix | None = None,
        rotation: npt.ArrayLike | None = None,
        scale: float = 1.0,
        still: float | None = None,
        source_on_target: npt.ArrayLike | None = None,
        contact_weight: float = CONTACT_WEIGHT,
    ) -> None:
        self.source_neutral, self.source_faces = check_mesh(
            source_neutral, source_faces, what="source mesh"
        )
        self.target_neutral, self.target_faces = check_mesh(target_neutral, target_faces)
        vs, fs = self.source_neutral.shape[0], self.source_faces.shape[0]
        vt, ft = self.target_neutral.shape[0], self.target_faces.shape[0]
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        if pairs.size == 0:
            raise CorrespondenceError(
                "no triangle of the target corresponds to a source triangle; give markers "
                "that place the source face on the target's face",
                code="no_triangle_pairs",
            )
        if (
            pairs[:, 0].min() < 0
            or pairs[:, 0].max() >= fs
            or pairs[:, 1].min() < 0
            or (pairs[:, 1].max() >= ft)
        ):
            raise CorrespondenceError("triangle pairs out of range", code="bad_pairs")
        if vertex_map is not None and vertex_map.shape != (vt, vs):
            raise CorrespondenceError(
                f"vertex_map: expected shape ({vt}, {vs}), got {vertex_map.shape}",
                code="bad_pairs",
            )
        self.pairs = pairs
        self.rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        if self.rotation.shape != (3, 3) or not np.allclose(
            self.rotation @ self.rotation.T, np.eye(3), atol=1e-9
        ):
            raise CorrespondenceError("rotation: expected a (3, 3) rotation", code="bad_pairs")
        if not (np.isfinite(scale) and scale > 0):
            raise CorrespondenceError(f"scale: expected > 0, got {scale!r}", code="bad_pairs")
        self.scale = float(scale)
        still = check_still(still)
        self.vertex_map = None if vertex_map is None else sp.csr_matrix(vertex_map)
        self.still = None if self.vertex_map is None else still
        self.source_on_target = (
            None
            if source_on_target is None
            else np.asarray(source_on_target, dtype=np.float64).reshape(vs, 3)
        )
        if not (np.isfinite(contact_weight) and contact_weight > 0):
            raise CorrespondenceError(
                f"contact_weight: expected > 0, got {contact_weight!r}", code="bad_weights"
            )
        self.contact_weight = float(contact_weight)
        self._source_inverses = frame_inverses(self.source_neutral, self.source_faces)
        # Sums of source transformations per target triangle: G = P (S - I).
        self._pair_sum = sp.csr_matrix(
            (np.ones(len(pairs)), (pairs[:, 1], pairs[:, 0])), shape=(ft, fs)
        )
        counts = np.bincount(pairs[:, 1], minlength=ft).astype(np.float64)
        self.reached = counts > 0
        weights = np.repeat(np.where(self.reached, counts, 1.0), 3)

        rows = frame_rows(frame_inverses(self.target_neutral, self.target_faces),
                          self.target_faces, vt)  # fmt: skip
        labels = vertex_components(vt, self.target_faces)
        _, first = np.unique(labels, return_index=True)
        self._labels = labels
        free = np.ones(vt + ft, dtype=bool)
        free[first] = False
        self._free = np.flatnonzero(free)
        self._first = first
        self._rows_t = rows.T.tocsr()  # (Vt + Ft, 3Ft): rhs = Aᵀ W r
        self._normal = (self._rows_t @ sp.diags(weights) @ rows).tocsr()
        self._typical = float(np.median(self._normal.diagonal()))
        self.factorizations = 0
        # The held solve factors its own systems: the whole one only when asked for.
        self._lu: SuperLU | None = None
        if self.still is None:
            self._lu = self.factor
        self.unknowns = int(self._free.size)

    @property
    def factor(self) -> SuperLU:
        """The factorisation every ``transfer`` reuses (read-only; ``bench transfer`` times
        a product with its L and U as the solve's floor)."""
        if self._lu is None:
            self._lu = self._factor(self._normal[self._free][:, self._free].tocsc())
        return self._lu

    @property
    def nonzeros(self) -> int:
        """Nonzeros in the whole system's factors L and U."""
        return int(self.factor.L.nnz + self.factor.U.nnz)

    def _factor(self, normal: sp.csc_matrix) -> SuperLU:
        self.factorizations += 1
        # The matrix is symmetric positive definite: symmetric ordering, no pivoting.
        return splu(
            normal,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )

    def transfer(
        self,
        source_deformed: npt.ArrayLike,
        *,
        contact: npt.ArrayLike | None = None,
        progress: Callable[[int], object] | None = None,
    ) -> np.ndarray:
        """The target's vertices under each source deformation.

        Parameters
        ----------
        source_deformed : (Vs, 3) or (M, Vs, 3) float
            Deformed source meshes (the source neutral's topology).
        contact : (M,) bool, optional
            The meshes whose closing vertex pairs are kept together on the target
            (``contact.contacts``); needs ``still`` and ``source_on_target``.
        progress : callable, optional
            Called with the number of meshes done after each batch of them (a tqdm bar's
            ``update``).

        Returns
        -------
        (Vt, 3) or (M, Vt, 3) float64
        """
        deformed = np.asarray(source_deformed, dtype=np.float64)
        single = deformed.ndim == 2
        deformed = deformed.reshape(-1, *deformed.shape[-2:])
        vs = self.source_neutral.shape[0]
        if deformed.shape[1:] != (vs, 3):
            raise InputError(
                f"source_deformed: expected shape (M, {vs}, 3), got {deformed.shape}",
                code="wrong_vertex_count",
            )
        if not np.isfinite(deformed).all():
            raise InputError("source_deformed: NaN or Inf coordinates", code="non_finite")
        touching = np.zeros(deformed.shape[0], dtype=bool)
        if contact is not None:
            touching[:] = np.asarray(contact, dtype=bool).reshape(-1)
            if touching.any() and (self.still is None or self.source_on_target is None):
                raise InputError(
                    "contact: needs the held solve (still) and the source placed on the "
                    "target (source_on_target)",
                    code="no_contact",
                )
        out = np.empty((deformed.shape[0], *self.target_neutral.shape))
        if self.still is not None:
            for index, shape in enumerate(deformed):
                out[index] = self._transfer_held(shape, contact=bool(touching[index]))
                if progress is not None:
                    progress(1)
            return out[0] if single else out
        for start in range(0, deformed.shape[0], _CHUNK):
            chunk = deformed[start : start + _CHUNK]
            out[start : start + len(chunk)] = self._transfer_chunk(chunk)
            if progress is not None:
                progress(len(chunk))
        return out[0] if single else out

    def _target_rhs(self, source_deformed: np.ndarray) -> np.ndarray:
        """(Vt + Ft, 3C) Aᵀ W (the paired source transformations − I) of C deformed sources.

        Column 3c + i: coordinate i of expression c.
        """
        ft = self.target_faces.shape[0]
        c = source_deformed.shape[0]
        gradients = triangle_frames(source_deformed, self.source_faces) @ self._source_inverses
        gradients -= np.eye(3)
        gradients = self.rotation @ gradients @ self.rotation.T  # into the target's frame
        # (Fs, C * 9) -> the summed transformations - I of each target triangle (Ft, C, 3, 3).
        flat = gradients.transpose(1, 0, 2, 3).reshape(-1, c * 9)
        summed = (self._pair_sum @ flat).reshape(ft, c, 3, 3)
        # Row 3t + k, column 3c + i: entry (i, k) of expression c's transformation of t.
        rhs: np.ndarray = self._rows_t @ summed.transpose(0, 3, 1, 2).reshape(3 * ft, 3 * c)
        return rhs

    def _transfer_held(self, source_deformed: np.ndarray, *, contact: bool = False) -> np.ndarray:
        """(Vt, 3) for one deformed source, the vertices where the source is still held.

        Held: each mapped target vertex whose corresponding source point moves less than
        ``still`` × the largest such motion, at that point's displacement; and in a piece
        with no such vertex, its first vertex (the piece then placed by the median, as
        without ``still``). Unknowns: the other vertices and the fourth vertices of the
        triangles that touch them (a triangle whose corners are all held moves as they do).
        With ``contact``, the closing pairs' terms are added to the least squares.
        """
        assert self.vertex_map is not None and self.still is not None
        vt, ft = self.target_neutral.shape[0], self.target_faces.shape[0]
        copied = self.scale * (self.vertex_map @ (source_deformed - self.source_neutral))
        copied = copied @ self.rotation.T
        mapped = np.diff(self.vertex_map.indptr) > 0
        motion = np.linalg.norm(copied, axis=1)
        largest = float(motion[mapped].max()) if mapped.any() else 0.0
        held = mapped & (motion < self.still * largest)
        free_pieces = np.setdiff1d(np.arange(self._first.size), self._labels[held])
        placed_by_median = self._first[free_pieces]
        held[placed_by_median] = True
        displacement = np.zeros((vt + ft, 3))
        displacement[:vt][held] = copied[held]
        displacement[placed_by_median] = 0.0
        touched = ~held[self.target_faces].all(axis=1)
        unknown = np.concatenate([np.flatnonzero(~held), vt + np.flatnonzero(touched)])
        known = np.flatnonzero(held)
        if unknown.size:
            rhs = self._target_rhs(source_deformed[None])
            rhs = rhs[unknown] - self._normal[unknown][:, known] @ displacement[known]
            normal = self._normal[unknown][:, unknown]
            terms = None
            if contact:
                assert self.source_on_target is not None
                terms = contacts(
                    self.source_neutral, source_deformed, self.source_on_target,
                    self.target_neutral, self.target_faces, rotation=self.rotation,
                    scale=self.scale, source_faces=self.source_faces,
                )  # fmt: skip
            if terms is not None:
                # Pairs' places are on the target's vertices: zero columns for fourth vertices.
                rows = sp.hstack([terms.rows, sp.csr_matrix((len(terms.offsets), ft))]).tocsc()
                weight = self.contact_weight * self._typical
                on_unknown = rows[:, unknown]
                offsets = terms.offsets - rows[:, known] @ displacement[known]
                normal = normal + weight * (on_unknown.T @ on_unknown)
                rhs = rhs + weight * (on_unknown.T @ offsets)
            lu = self._factor(normal.tocsc())
            displacement[unknown] = lu.solve(rhs)
        moved = displacement[:vt]
        if free_pieces.size:
            source_displacement = source_deformed - self.source_neutral
            self._place_pieces(
                moved, self.scale * source_displacement @ self.rotation.T, pieces=free_pieces
            )
        result: np.ndarray = self.target_neutral + moved
        return result

    def _transfer_chunk(self, source_deformed: np.ndarray) -> np.ndarray:
        """(C, Vt, 3) for C deformed sources: one back-substitution for all 3C columns."""
        vt, ft = self.target_neutral.shape[0], self.target_faces.shape[0]
        c = source_deformed.shape[0]
        rhs = self._target_rhs(source_deformed)[self._free]
        displacement = np.zeros((vt + ft, 3 * c))
        displacement[self._free] = self.factor.solve(rhs)
        moved = displacement[:vt].reshape(vt, c, 3).transpose(1, 0, 2).copy()
        if self.vertex_map is not None:
            for index in range(c):
                displacement = source_deformed[index] - self.source_neutral
                self._place_pieces(moved[index], self.scale * displacement @ self.rotation.T)
        result: np.ndarray = self.target_neutral + moved
        return result

    def _place_pieces(
        self,
        moved: np.ndarray,
        source_displacement: np.ndarray,
        *,
        pieces: np.ndarray | None = None,
    ) -> None:
        """Shift each connected piece so its mapped vertices move as their source points do.

        The shift is the median, per axis, of the differences: the bulk of a piece that
        the expression leaves still stays still, whatever its moving part does. ``pieces``:
        only these piece labels (default all).
        """
        assert self.vertex_map is not None
        mapped = np.flatnonzero(np.diff(self.vertex_map.indptr) > 0)
        if mapped.size == 0:
            return
        differences = self.vertex_map[mapped] @ source_displacement - moved[mapped]
        if pieces is not None:
            mapped = mapped[np.isin(self._labels[mapped], pieces)]
            if mapped.size == 0:
                return
        labels = self._labels[mapped]
        order = np.argsort(labels, kind="stable")
        pieces, starts = np.unique(labels[order], return_index=True)
        for piece, chunk in zip(pieces, np.split(order, starts[1:]), strict=True):
            # The median per axis of the source's frame, so the result turns with the target.
            along_source = np.median(differences[chunk] @ self.rotation, axis=0)
            moved[self._labels == piece] += along_source @ self.rotation.T
