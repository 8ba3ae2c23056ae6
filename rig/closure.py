"""Eye closures read as closed: each blink weight mapped by the performer's own closed eye.

A rig fitted for landmark noise shrinks its weights towards the neutral (the ridge M σ²),
and a blink's points move nearly as a look down's do, so the noise-aware fit splits the two:
a performer's own captured ``eyeBlinkLeft`` key reads about 0.74 on their own rig, and a
quick blink through a webcam less (README, issue 34's option (x)). The capture says what
closed is: the rig's reading of the performer's closed eye maps to 1 and their neutral's
to 0, linearly, clipped to [0, 1]. Applied to the blink weights only, after the rig's
bounds. Optionally the mapped weight then goes through a contrast curve (a smoothstep
from ``low`` to ``high``: open below, closed above), which a re-based rig takes (its
readings are another face's keys: a held gaze reads partly closed, README option (ag)).
The map travels in the rig's fit report (``"closure"``, ``"closure_contrast"``), so a
stored rig, a rig refitted for another noise and a rig re-based keep it. No I/O.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .errors import InputError

__all__ = [
    "CLOSURE_NAMES",
    "CLOSURE_REPORT_KEYS",
    "MIN_CLOSED",
    "ClosureMap",
    "check_contrast",
    "closure_ranges",
    "contrast_from_report",
]

#: The weights mapped: the two blinks (ARKit names).
CLOSURE_NAMES = ("eyeBlinkLeft", "eyeBlinkRight")
#: The fit report's entries that describe the map.
CLOSURE_REPORT_KEYS = ("closure", "closure_contrast")
#: A closed eye the rig reads below this (above the neutral's reading) is not mapped: the
#: map would multiply that weight's noise by more than 1 / MIN_CLOSED.
MIN_CLOSED = 0.2


def closure_ranges(
    weights_of_keys: Mapping[str, np.ndarray], names: Sequence[str]
) -> dict[str, list[float]]:
    """{name: [open, closed]} for each blink a capture holds: the rig's reading of that
    blink's weight on the captured neutral and on the captured blink itself.

    ``weights_of_keys`` : {key name: (M,) the rig's weights of that key's points}, the
    neutral's under ``"neutral"``; ``names`` the rig's names (column order). A blink whose
    closed reading is less than ``MIN_CLOSED`` above the open one is left out.
    """
    ranges: dict[str, list[float]] = {}
    if "neutral" not in weights_of_keys:
        return ranges
    for name in CLOSURE_NAMES:
        if name not in names or name not in weights_of_keys:
            continue
        column = list(names).index(name)
        opened = max(0.0, float(weights_of_keys["neutral"][column]))
        closed = float(weights_of_keys[name][column])
        if np.isfinite(opened) and np.isfinite(closed) and closed - opened >= MIN_CLOSED:
            ranges[name] = [opened, closed]
    return ranges


def check_contrast(contrast: Any) -> tuple[float, float]:
    """``contrast`` as a curve's (low, high): two finite numbers, 0 <= low < high <= 1.

    Raises
    ------
    InputError
        ``bad_input`` for anything else (the curve would be a step, reversed or off [0, 1]).
    """
    try:
        low, high = (float(v) for v in contrast)
    except (TypeError, ValueError):
        raise InputError(
            "blink contrast: expected two numbers [low, high]", code="bad_input"
        ) from None
    if not (0.0 <= low < high <= 1.0):  # NaN fails every comparison
        raise InputError(
            f"blink contrast: expected 0 <= low < high <= 1, got [{low:g}, {high:g}]",
            code="bad_input",
        )
    return low, high


def contrast_from_report(report: Mapping[str, Any] | None) -> tuple[float, float] | None:
    """A fit report's ``"closure_contrast"`` [low, high] (0 <= low < high <= 1), or None
    (no entry, or one that is not such a pair: the map is then linear)."""
    entry = (report or {}).get("closure_contrast")
    if not isinstance(entry, (list, tuple)):
        return None
    try:
        return check_contrast(entry)
    except InputError:
        return None


class ClosureMap:
    """The map of a rig's blink weights: (w − open) / (closed − open), clipped to [0, 1],
    then, with a ``contrast`` (low, high), a smoothstep from low (0) to high (1).

    Column 0 (the neutral) takes up the change, so the weights still sum to 1.
    """

    def __init__(
        self,
        columns: np.ndarray,
        opened: np.ndarray,
        closed: np.ndarray,
        contrast: tuple[float, float] | None = None,
    ) -> None:
        self.columns = columns
        self.opened = opened
        self.scale = 1.0 / (closed - opened)
        self.contrast = contrast
        # The curve as (low, 1 / (high - low)) for the single frame's inline arithmetic.
        self._curve = None if contrast is None else (contrast[0], 1.0 / (contrast[1] - contrast[0]))
        # A single frame (the live path) maps its two weights as Python floats: numpy's
        # fancy indexing would cost more than the rest of the frame's map.
        self._single = [
            (int(j), float(low), float(gain))
            for j, low, gain in zip(columns, opened, self.scale, strict=True)
        ]

    @classmethod
    def from_report(
        cls, report: Mapping[str, Any] | None, names: Sequence[str]
    ) -> ClosureMap | None:
        """The map a fit report's ``"closure"`` entry describes (with its
        ``"closure_contrast"``, when a usable one is there), or None (no entry, or none of its
        names among ``names``, or a range that is not one)."""
        ranges = (report or {}).get("closure")
        if not isinstance(ranges, Mapping):
            return None
        columns, opened, closed = [], [], []
        for name, pair in ranges.items():
            if name not in names:
                continue
            try:
                low, high = (float(v) for v in pair)
            except (TypeError, ValueError):
                return None
            if not (np.isfinite(low) and np.isfinite(high) and high - low >= MIN_CLOSED):
                return None
            columns.append(list(names).index(name))
            opened.append(low)
            closed.append(high)
        if not columns:
            return None
        contrast = contrast_from_report(report)
        return cls(np.asarray(columns), np.asarray(opened), np.asarray(closed), contrast)

    def apply(self, weights: np.ndarray) -> np.ndarray:
        """(M,) or (B, M) weights mapped in place (and returned); the neutral's weight takes
        up the change, so the weights still sum to what they did."""
        curve = self._curve
        if weights.ndim == 1:
            for j, low, gain in self._single:
                old = float(weights[j])
                new = min(1.0, max(0.0, (old - low) * gain))
                if curve is not None:  # the smoothstep, inline: this runs every frame
                    x = min(1.0, max(0.0, (new - curve[0]) * curve[1]))
                    new = x * x * (3.0 - 2.0 * x)
                weights[j] = new
                weights[0] += old - new
            return weights
        before = weights[:, self.columns]
        after = np.clip((before - self.opened) * self.scale, 0.0, 1.0)
        if curve is not None:
            after = np.clip((after - curve[0]) * curve[1], 0.0, 1.0)
            after = after * after * (3.0 - 2.0 * after)
        weights[:, self.columns] = after
        weights[:, 0] += (before - after).sum(axis=1)
        return weights
