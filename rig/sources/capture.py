"""A held expression's frames -> one source example and its spread (the landmark noise).

The robust average the calibration walk-through takes of about a second of tracked
frames, and ``WinkCapture``, the winks a performance without a walk-through captures after
its neutral; pure array code, no tracking, fitting or I/O.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ..closure import CLOSURE_NAMES
from ..errors import InputError

__all__ = ["MAD_TO_SIGMA", "WinkCapture", "robust_example"]

#: Median absolute deviation -> standard deviation for normally distributed noise.
MAD_TO_SIGMA = 1.4826
#: A frame whose RMS distance to the median frame exceeds this many times the median such
#: distance is an outlier (a blink, a tracking slip) and is left out.
OUTLIER_FACTOR = 3.0


def robust_example(frames: npt.ArrayLike) -> tuple[np.ndarray, float, np.ndarray]:
    """The median frame of a held expression, outliers out, and the points' spread.

    Parameters
    ----------
    frames : (F, K, 3) float, F >= 3
        Normalised feature points of the frames captured while the expression was held.

    Returns
    -------
    points : (K, 3) float64
        Per-coordinate median of the frames kept.
    spread : float
        The landmark noise those frames show: the root mean square over coordinates of
        their robust standard deviation (1.4826 x median absolute deviation), in the
        points' units. This is the ``noise`` a fit on such captures should use.
    kept : (F,) bool
        Which frames were kept.

    Raises
    ------
    InputError
        ``wrong_point_count`` for another shape or fewer than 3 frames, ``non_finite``.
    """
    x = np.asarray(frames, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] != 3 or x.shape[0] < 3:
        raise InputError(
            f"expected frames of shape (F, K, 3) with F >= 3, got {x.shape}",
            code="wrong_point_count",
        )
    if not np.isfinite(x).all():
        raise InputError("the frames hold NaN or Inf", code="non_finite")
    median = np.median(x, axis=0)
    distance = np.sqrt(((x - median) ** 2).mean(axis=(1, 2)))
    typical = float(np.median(distance))
    kept = distance <= OUTLIER_FACTOR * typical if typical > 0 else np.ones(len(x), bool)
    held = x[kept]
    points = np.median(held, axis=0)
    mad = np.median(np.abs(held - points), axis=0)
    spread = float(np.sqrt(np.mean((MAD_TO_SIGMA * mad) ** 2)))
    return points, spread, kept


class WinkCapture:
    """A wink of each eye, captured from a performance after its neutral (the subject's
    left eye first): the closed eyes a re-based rig reads as closed (``calibrate.blinks``,
    PROTOCOL.md §5.1.3), for a performer with no walk-through (``facecast perform
    --winks``).

    A frame counts for the wink of one eye when that eye's lid gap (its upper lid point to
    its lower) is at most ``shut`` of the neutral's and the other eye's at least ``opened``
    (a blink, both shut, counts for neither); ``frames`` such frames make the wink, their
    ``robust_example``. Measured on ICT's rendered winks tracked by ``facecast perform``:
    the closed eye 0.25-0.27 of its gap at rest, the other 1.00-1.05 (tests/perform/
    test_eyelids.py).

    Parameters
    ----------
    neutral : (K, 3) float
        The performer's captured neutral.
    lids : {"left" | "right": (upper, lower)}
        Each eye's lid points among the K (the subject's sides).
    """

    def __init__(
        self,
        neutral: npt.ArrayLike,
        lids: dict[str, tuple[int, int]],
        *,
        frames: int = 8,
        shut: float = 0.6,
        opened: float = 0.8,
    ) -> None:
        if frames < 3:
            raise InputError(f"a wink needs at least 3 frames, got {frames}")
        self.lids = dict(lids)
        self.rest = {side: self._gap(np.asarray(neutral, dtype=np.float64), side) for side in lids}
        if not all(gap > 0 for gap in self.rest.values()):
            raise InputError("the neutral's eyes are shut: no wink can be told from it")
        self.frames, self.shut, self.opened = frames, shut, opened
        self.pending = list(CLOSURE_NAMES)  # the ARKit blinks, each the subject's own eye
        self.held: list[np.ndarray] = []
        self.closed: dict[str, np.ndarray] = {}

    def _gap(self, points: np.ndarray, side: str) -> float:
        upper, lower = self.lids[side]
        return float(np.linalg.norm(points[upper] - points[lower]))

    @property
    def wanted(self) -> str | None:
        """The wink captured next, or None when both are."""
        return self.pending[0] if self.pending else None

    def add(self, points: npt.ArrayLike) -> str | None:
        """One tracked frame (K, 3); the wink's name when this frame completes it."""
        name = self.wanted
        if name is None:
            return None
        frame = np.asarray(points, dtype=np.float64)
        side, other = ("left", "right") if name == "eyeBlinkLeft" else ("right", "left")
        if (
            self._gap(frame, side) <= self.shut * self.rest[side]
            and self._gap(frame, other) >= self.opened * self.rest[other]
        ):
            self.held.append(frame)
        if len(self.held) < self.frames:
            return None
        self.closed[name], _, _ = robust_example(np.stack(self.held))
        self.held = []
        self.pending.pop(0)
        return name
