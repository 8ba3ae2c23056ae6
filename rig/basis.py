"""The (M, 3V) float32 blend basis of eq. 3.14, built whole or shared between two threads.

Pure array code on the target examples, which releases the GIL: ``fit`` builds the basis
in a worker thread beside its math. Nothing here knows about the math or the rig.
"""

from __future__ import annotations

import threading
import time

import numpy as np

__all__ = ["BASIS_BUFFER", "BASIS_CHUNK_BYTES", "BasisBuild", "Targets", "build_blend_basis"]

#: Target examples as the basis reads them: (M, V, 3) float64, or the neutral T_B (V, 3)
#: float64 and M - 1 displacements (V, 3) float32 or float64 (``ExampleSet.targets``),
#: target i being ``T_B + displacements[i - 1]`` added in float64.
Targets = np.ndarray | tuple[np.ndarray, tuple[np.ndarray, ...]]

#: Values in each chunk of the basis's buffered cast: 16 kB of float64, which stays in a
#: core's L1 data cache beside the chunk of float32 it is rounded into.
BASIS_BUFFER = 2048
#: Float64 bytes of target examples read by each share of a basis built by two threads:
#: ICT's 55 rows go in 4 shares of 16. Each share costs its thread a GIL hand-over, so
#: fewer, larger shares; measured on ICT (fit wall time) 4.3 ms at 14-19 rows a share,
#: 4.7 at 10, 5.4 at 4, 5.6 for the whole basis in the worker.
BASIS_CHUNK_BYTES = 10 << 20


def build_blend_basis(target_vertices: Targets) -> np.ndarray:
    """The blend basis of target examples: row 0 T_B, rows i > 0 T_i - T_B (eq. 3.14).

    Parameters
    ----------
    target_vertices : (M, V, 3) float64, or (T_B, displacements) (``Targets``)
        The target examples, the neutral T_B first.

    Returns
    -------
    (M, 3V) float32, each row equal to ``(T_i - T_B).astype(np.float32)`` bit for bit,
    T_i the float64 target whichever way it is given.
    """
    basis = _new_basis(target_vertices)
    _fill_rows(target_vertices, basis, 1, len(basis))
    return basis


def _new_basis(target_vertices: Targets) -> np.ndarray:
    if isinstance(target_vertices, tuple):
        neutral, displacements = target_vertices
        m, v = len(displacements) + 1, len(neutral)
    else:
        neutral = target_vertices[0]
        m, v, _ = target_vertices.shape
    basis = np.empty((m, 3 * v), dtype=np.float32)
    basis[0] = neutral.reshape(-1)
    return basis


#: float64 values of a displaced target made at a time (``_fill_displaced``): 512 kB.
DISPLACED_CHUNK = 1 << 16


def _fill_displaced(
    neutral: np.ndarray, displacements: tuple[np.ndarray, ...], basis: np.ndarray, start: int,
    stop: int,
) -> None:  # fmt: skip
    """Rows start:stop of the basis of a displaced set, example by example and a chunk of
    ``DISPLACED_CHUNK`` values at a time: T_i = T_B + D_i in float64 (as a whole set's
    target is made, ``ExampleSet.target_examples``), then T_i - T_B rounded once to
    float32, so the rows equal a whole set's bit for bit with no float64 copy of a target."""
    flat = neutral.reshape(-1)
    scratch = np.empty(min(DISPLACED_CHUNK, flat.size))
    for row in range(start, stop):
        displacement = displacements[row - 1].reshape(-1)
        for at in range(0, flat.size, DISPLACED_CHUNK):
            part = slice(at, at + DISPLACED_CHUNK)
            made = scratch[: flat[part].size]
            np.add(flat[part], displacement[part], out=made)
            np.subtract(made, flat[part], out=basis[row, part], casting="same_kind")


def _fill_rows(target_vertices: Targets, basis: np.ndarray, start: int, stop: int) -> None:
    """Rows start:stop (start >= 1) of the basis: T_i - T_B rounded once to float32."""
    if isinstance(target_vertices, tuple):
        _fill_displaced(*target_vertices, basis, start, stop)
        return
    flat = target_vertices.reshape(len(target_vertices), -1)
    # Subtracted in float64 and rounded once into float32 (as (T_i - T_B).astype would),
    # in one ufunc call whose buffered cast goes through BASIS_BUFFER float64 at a time:
    # no float64 temporary of the difference. Measured on ICT, 4.4 ms against 5.7 for a
    # float64 row of scratch per example and 2.5 for the bare cast of the examples; a buffer
    # that stays in L1 (numpy's default, 8192 values, is 64 kB) took it from 3.5 ms to 2.7.
    # The buffer size is the calling thread's numpy setting (a context variable), restored.
    default_buffer = np.setbufsize(BASIS_BUFFER)
    try:
        np.subtract(flat[start:stop], flat[0], out=basis[start:stop], casting="same_kind")
    finally:
        np.setbufsize(default_buffer)


class BasisBuild:
    """A blend basis built by a worker thread and by the caller once it is free.

    The worker takes shares of rows from the top (``BASIS_CHUNK_BYTES`` each) from the
    moment it starts; the caller, done with its own work, calls ``help`` and takes shares
    from the bottom until they meet. Every row is computed by the same code whichever
    thread takes it, so the basis equals ``build_blend_basis``'s bit for bit. ``wait``
    never raises and stops the worker at its next share, so a ``finally`` can always join
    it; ``result`` then returns the basis or raises what building it raised. One thread per
    build, started and joined by its caller: concurrent builds share nothing.

    Parameters
    ----------
    target_vertices : (M, V, 3) float64, or (T_B, displacements) (``Targets``)
    thread : bool
        False: no worker; ``help`` builds the whole basis in the caller's thread.
    """

    def __init__(self, target_vertices: Targets, *, thread: bool) -> None:
        self._target_vertices = target_vertices
        self._basis = _new_basis(target_vertices)
        m = len(self._basis)
        rows = max(1, BASIS_CHUNK_BYTES // max(1, self._basis.shape[1] * 8))
        self._lock = threading.Lock()
        self._next = 1  # first row no thread has taken
        self._end = m  # one past the last row no thread has taken
        self._share = rows
        self._stopped = False
        self._errors: list[BaseException] = []
        self._seconds = [0.0, 0.0]  # the worker's, the caller's
        self._thread: threading.Thread | None = None
        if thread and m > 1:
            self._thread = threading.Thread(
                target=self._work, args=(0, True), name="facecast-fit-basis", daemon=True
            )
            self._thread.start()

    @property
    def seconds(self) -> float:
        """Seconds spent building the basis, summed over both threads.

        Each thread's own CPU clock: time a thread spends waiting for a core (the other
        thread's, on a loaded machine) or for the GIL is not basis work.
        """
        return self._seconds[0] + self._seconds[1]

    def _take(self, from_top: bool) -> tuple[int, int] | None:
        with self._lock:
            if self._stopped or self._errors or self._next >= self._end:
                return None
            if from_top:
                start = self._next
                self._next = min(start + self._share, self._end)
                return start, self._next
            stop = self._end
            self._end = max(stop - self._share, self._next)
            return self._end, stop

    def _work(self, slot: int, from_top: bool) -> None:
        try:
            while (rows := self._take(from_top)) is not None:
                started = time.thread_time()
                _fill_rows(self._target_vertices, self._basis, *rows)
                self._seconds[slot] += time.thread_time() - started
        except BaseException as error:  # handed to the caller by result()
            with self._lock:
                self._errors.append(error)

    def help(self) -> None:
        """Build, in the caller's thread, the rows the worker has not taken yet."""
        self._work(1, False)

    def wait(self) -> None:
        """Stop the worker at its next share and join it; never raises."""
        with self._lock:
            self._stopped = True
        if self._thread is not None:
            self._thread.join()

    def result(self) -> np.ndarray:
        """The basis, once ``help`` and ``wait`` have returned; or what building it raised."""
        if self._errors:
            raise self._errors[0]
        if self._next < self._end:
            raise RuntimeError("the blend basis was read before every row was built")
        return self._basis
