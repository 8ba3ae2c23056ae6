"""Which feature points a rig accepts: frames and calibration neutrals in its units.

A guard in front of the weights: points far outside the rig's neutral (other units, NaN,
an absurd scale) are refused with ``InputError`` code ``out_of_range`` or ``non_finite``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["CALIBRATION_RANGE", "POINT_RANGE", "PointRange", "check_calibration_range"]

#: A frame's feature points are refused (``InputError`` code ``out_of_range``) when their
#: root-mean-square distance from the reference neutral's centroid is more than this many
#: times that neutral's radius (its own RMS distance from its centroid). The reference is
#: the rig's source neutral, or the performer's neutral once calibrated. Far looser than
#: any real face (a head 2 m from the origin of a 10 cm rig is 20x), it catches points in
#: other units than the rig (mm for m is 1000x), whose weights mean nothing and overflow.
POINT_RANGE = 100.0
#: A calibration neutral is refused (``out_of_range``) when its RMS distance from the source
#: neutral's centroid is more than this many times the source neutral's radius, or when its
#: own radius is more than this factor larger or smaller: calibration absorbs a performer's
#: position and units, not an absurd scale (a 1e300 neutral makes every later frame NaN).
CALIBRATION_RANGE = 1e4


@dataclass(frozen=True)
class PointRange:
    """The frames within POINT_RANGE of a reference neutral (K, 3).

    Attributes
    ----------
    centre : (3,) float64
        The reference's centroid.
    radius : float
        The reference's RMS distance from its centroid (never 0).
    range2 : float
        Bound on a frame's sum of squared distances from ``centre``.
    fast2 : float
        A sum of squares of the points themselves up to this proves the bound without a
        subtraction (RMS |x - c| <= RMS |x| + |c|), with room for float32 rounding: one
        dot product for every ordinary frame instead of three calls. A float32 sum of 3K
        squares is within 3K units in the last place of the exact one (its rounding errors
        add up at most linearly); the room is four times that.
    """

    centre: np.ndarray
    radius: float
    range2: float
    fast2: float

    @classmethod
    def around(cls, reference: np.ndarray) -> PointRange:
        """The range of frames around a reference neutral (K, 3)."""
        centre, radius = centre_radius(np.asarray(reference, dtype=np.float64))
        k = reference.shape[0]
        slack = POINT_RANGE * radius - float(np.linalg.norm(centre))
        rounding = 4 * 3 * k * float(np.finfo(np.float32).eps)
        fast2 = k * max(slack, 0.0) ** 2 * (1.0 - max(rounding, 1e-5))
        return cls(centre, radius, k * (POINT_RANGE * radius) ** 2, fast2)

    def check(self, x: np.ndarray, *, single: bool) -> None:
        """Raise ``InputError`` for frames (B, K, 3) outside POINT_RANGE (or not finite)."""
        d = x - self.centre
        sums = np.einsum("bkc,bkc->b", d, d)
        bad = np.flatnonzero(~(sums <= self.range2))
        if not bad.size:
            return
        where = "" if single else f" (frame {int(bad[0])})"
        if not np.isfinite(x[bad[0]]).all():
            raise InputError(f"feature points hold NaN or Inf{where}", code="non_finite")
        rms = float(np.sqrt(sums[bad[0]] / x.shape[1]))
        raise InputError(
            f"feature points{where} lie {rms:.3g} (RMS) from the neutral's centre, more than "
            f"{POINT_RANGE:g}x its radius {self.radius:.3g}: are they in the rig's units?",
            code="out_of_range",
        )


def check_calibration_range(source_neutral: np.ndarray, neutral: np.ndarray) -> None:
    """Refuse a neutral too far from, or too much larger or smaller than, the source's."""
    source_centre, source_radius = centre_radius(source_neutral)
    _, radius = centre_radius(neutral)
    d = neutral - source_centre
    distance = float(np.sqrt(np.vdot(d, d) / neutral.shape[0]))
    limit = CALIBRATION_RANGE
    if not distance <= limit * source_radius:
        why = f"lies {distance:.3g} (RMS) from the source neutral's centre"
    elif not source_radius / limit <= radius <= source_radius * limit:
        why = f"has radius {radius:.3g}"
    else:
        return
    raise InputError(
        f"calibration neutral {why}; it must lie within {limit:g}x the source neutral's "
        f"radius {source_radius:.3g} of its centre, with a radius within a factor {limit:g}",
        code="out_of_range",
    )


def centre_radius(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centroid (3,) of points (K, 3) and their RMS distance from it (never 0)."""
    centre = points.mean(axis=0)
    d = points - centre
    radius = float(np.sqrt(np.vdot(d, d) / points.shape[0]))
    return centre, max(radius, float(np.finfo(np.float64).tiny))
