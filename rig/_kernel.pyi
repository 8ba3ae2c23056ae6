"""Types of the compiled extension built from _kernel.c and _boxqp.c (see its docstrings)."""

from typing import Final

import numpy as np

ISA: Final[str]
F16_ISA: Final[str]
BLEND_ISA: Final[str]

class BsplineKernel:
    num_inputs: int
    num_components: int
    num_examples: int
    def __init__(
        self,
        project: np.ndarray,
        param_offset: np.ndarray,
        linear: np.ndarray,
        linear_offset: np.ndarray,
        centres: np.ndarray,
        alpha: np.ndarray,
        radial: np.ndarray,
        *,
        generic: bool = False,
    ) -> None: ...
    def evaluate(self, x: np.ndarray, out: np.ndarray, /) -> float: ...
    def evaluate_rows(self, x: np.ndarray, out: np.ndarray, /) -> None: ...
    def weights(self, points: np.ndarray, limit: float = ..., /) -> np.ndarray | None: ...

def blend_rows(
    weights: np.ndarray,
    basis: np.ndarray,
    out: np.ndarray,
    runs: np.ndarray | None = None,
    generic: bool = False,
    tile: int = 0,
    /,
) -> None: ...
def place_columns(src: np.ndarray, out: np.ndarray, runs: np.ndarray, /) -> None: ...
def f32_to_f16(src: np.ndarray, dst: np.ndarray, generic: bool = False, /) -> None: ...
def project_box(
    metric: np.ndarray,
    weights: np.ndarray,
    shift: np.ndarray | None,
    half: float,
    out: np.ndarray,
    upper: float | None,
    max_iter: int,
    /,
) -> None: ...
