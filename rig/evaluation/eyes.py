"""The webcam benchmark's eyes clip: quick blinks, winks, gaze holds and a jaw + smile, scored.

What an audience notices most is the eyes: this builds the weights of a clip of such events
(``eyes_clip``) and scores estimated weights per event against them (``eyes_scores``): a
blink's peak on both eyes, the other eye during a wink, the gaze's direction, each part of
a combination as a share of the truth. Pure computation, no rendering, tracking or I/O.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from ..retarget import fit_performer
from ..rig import Rig
from ..smoothing import smooth_take
from .webcam import generic_rig

__all__ = [
    "EYES_IDENTITY",
    "SHORT_TIMING",
    "EyesClip",
    "EyesEvent",
    "EyesTiming",
    "eyes_clip",
    "eyes_goals",
    "eyes_rows",
    "eyes_scores",
]

#: The face that performs the eyes clip: neither the take's performer (``webcam.
#: PERFORMER_IDENTITY``, person07), nor the character (person01), nor ICT's generic face.
EYES_IDENTITY = "person12"
#: A quick blink at 30 fps: 5 frames, fully closed in the middle one.
BLINK_PROFILE = (0.35, 0.85, 1.0, 0.85, 0.35)
REST_FRAMES = 8  # between events, at rest
LEAD_FRAMES = 10  # at rest before the first event
WINK = (3, 6)  # frames of ramp (each way) and hold
GAZE = (3, 12)
GAZE_AMOUNT = 0.7
COMBO = (4, 12)
#: With ``short``: every ramp, hold and rest, frames.
SHORT = 3
COMBO_WEIGHTS = {"jawOpen": 0.5, "mouthSmileLeft": 0.8, "mouthSmileRight": 0.8}
#: Frames after an event a peak is still looked for: a causal filter lags.
PEAK_LAG = 3
#: Gaze directions as the subject sees them, and the ARKit weights that make each
#: (ARKit: eyeLookOutLeft turns the left eye to the subject's left, eyeLookInRight the right).
GAZE_WEIGHTS = {
    "up": ("eyeLookUpLeft", "eyeLookUpRight"),
    "down": ("eyeLookDownLeft", "eyeLookDownRight"),
    "left": ("eyeLookOutLeft", "eyeLookInRight"),
    "right": ("eyeLookInLeft", "eyeLookOutRight"),
}
#: Issue 34's goals for the eyes clip.
GOAL_BLINK_MIN, GOAL_BLINK_MEAN = 0.6, 0.75
GOAL_WINK_EYE, GOAL_WINK_OTHER = 0.6, 0.3
GOAL_COMBO = 0.6


@dataclass(frozen=True)
class EyesEvent:
    """One scored event: ``kind`` blink, wink, gaze or combo; frames [start, stop) where it
    is at full strength (a blink's whole 5 frames); ``detail`` the wink's eye ("Left" or
    "Right") or the gaze's direction."""

    kind: str
    start: int
    stop: int
    detail: str = ""


@dataclass(frozen=True, eq=False)
class EyesClip:
    """The clip's true weights (F, M) in ``names`` order and its events, in time order."""

    names: tuple[str, ...]
    activations: np.ndarray
    events: tuple[EyesEvent, ...]


def _ramp(frames: int) -> np.ndarray:
    rise = np.arange(1, frames + 1) / (frames + 1.0)
    out: np.ndarray = rise * rise * (3.0 - 2.0 * rise)  # smoothstep
    return out


@dataclass(frozen=True)
class EyesTiming:
    """The clip's frames (30 fps): ``lead`` at rest first, ``blinks`` quick blinks, then
    each wink, gaze hold and the jaw + smile as (ramp each way, hold); ``rest`` at rest
    after every event. ``combo`` None leaves the jaw + smile out."""

    blinks: int = 3
    lead: int = LEAD_FRAMES
    rest: int = REST_FRAMES
    wink: tuple[int, int] = WINK
    gaze: tuple[int, int] = GAZE
    combo: tuple[int, int] | None = COMBO


#: One blink, and every ramp, hold and rest ``SHORT`` frames: each kind of event once, in
#: 102 frames instead of 221, to check the path end to end; its scores are not the
#: benchmark's (a hold of 3 frames is mostly a live filter's lag).
SHORT_TIMING = EyesTiming(
    blinks=1, rest=SHORT, wink=(SHORT, SHORT), gaze=(SHORT, SHORT), combo=(SHORT, SHORT)
)


def eyes_clip(
    names: Sequence[str], *, short: bool = False, timing: EyesTiming | None = None
) -> EyesClip:
    """Rest, quick blinks, a wink each side, gaze up, down, left, right, then jaw open +
    smile, each followed by frames at rest (30 fps frames; ``EyesTiming``'s defaults: three
    blinks, ``REST_FRAMES`` between events, 221 frames).

    Parameters
    ----------
    names : sequence of str
        The face's expressions, the neutral first; the ARKit eye names (and jaw and smile
        names, unless ``timing`` leaves the combination out) must be among them.
    short : bool
        ``SHORT_TIMING``.
    timing : EyesTiming, optional
        Other frame counts (``short`` then does not apply).
    """
    timing = timing or (SHORT_TIMING if short else EyesTiming())
    rest = timing.rest
    column = {name: i for i, name in enumerate(names)}
    needed = {"eyeBlinkLeft", "eyeBlinkRight", *(COMBO_WEIGHTS if timing.combo else ())}
    needed.update(n for pair in GAZE_WEIGHTS.values() for n in pair)
    missing = sorted(needed - set(column))
    if missing:
        raise InputError(f"the eyes clip needs ARKit {missing[0]!r}", code="unknown_expression")
    rows: list[np.ndarray] = [np.zeros((timing.lead, len(names)))]
    events: list[EyesEvent] = []
    frame = timing.lead

    def add(kind: str, weights: Mapping[str, float], profile: np.ndarray, full: tuple[int, int],
            detail: str = "") -> None:  # fmt: skip
        nonlocal frame
        block = np.zeros((len(profile) + rest, len(names)))
        for name, value in weights.items():
            block[: len(profile), column[name]] = value * profile
        rows.append(block)
        events.append(EyesEvent(kind, frame + full[0], frame + full[1], detail))
        frame += len(block)

    blink = np.array(BLINK_PROFILE)
    for _ in range(timing.blinks):
        add("blink", {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0}, blink, (0, len(blink)))

    def held(kind: str, weights: Mapping[str, float], timing: tuple[int, int],
             detail: str = "") -> None:  # fmt: skip
        ramp, hold = timing
        profile = np.concatenate([_ramp(ramp), np.ones(hold), _ramp(ramp)[::-1]])
        add(kind, weights, profile, (ramp, ramp + hold), detail)

    for side in ("Left", "Right"):
        held("wink", {f"eyeBlink{side}": 1.0}, timing.wink, side)
    for direction, pair in GAZE_WEIGHTS.items():
        held("gaze", dict.fromkeys(pair, GAZE_AMOUNT), timing.gaze, direction)
    if timing.combo is not None:
        held("combo", COMBO_WEIGHTS, timing.combo)
    return EyesClip(tuple(names), np.concatenate(rows), tuple(events))


def _gaze(series: Mapping[str, np.ndarray], frames: slice) -> dict[str, float]:
    """Each direction's mean weight over ``frames`` (the mean of its two names)."""
    return {
        direction: float(np.mean([series[a][frames].mean(), series[b][frames].mean()]))
        for direction, (a, b) in GAZE_WEIGHTS.items()
    }


def eyes_scores(weights: npt.ArrayLike, names: Sequence[str], clip: EyesClip) -> dict[str, Any]:
    """Estimated weights scored per event of ``clip`` against its truth.

    Parameters
    ----------
    weights : (F, M') float
        The estimate for the clip's frames, in ``names`` order (a name missing counts as 0).

    Returns
    -------
    dict (JSON-able)
        ``blinks``: per blink the peak (over its frames and ``PEAK_LAG`` after) of each eye
        as a share of the true peak; ``winks``: the winking eye's and the other eye's peak
        (truth 1 and 0); ``gaze``: per hold the direction whose weights are highest on
        average, whether it is the true one, the true direction's weights as a share of
        the truth, and ``shut``, the blinks' mean over the hold (truth 0); ``combo``:
        ``jawOpen`` and the smile (mean of both sides) as shares of the truth, averaged over
        the hold. And ``goals`` (``eyes_goals``).
    """
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 2 or w.shape != (len(clip.activations), len(names)):
        raise InputError(
            f"eyes weights: expected shape ({len(clip.activations)}, {len(names)}), got {w.shape}",
            code="bad_input",
        )
    column = {name: i for i, name in enumerate(names)}
    zero = np.zeros(len(w))
    series = {name: (w[:, column[name]] if name in column else zero) for name in clip.names}
    truth = {name: clip.activations[:, i] for i, name in enumerate(clip.names)}
    out: dict[str, Any] = {"blinks": [], "winks": [], "gaze": [], "combo": []}
    for event in clip.events:
        peak = slice(event.start, event.stop + PEAK_LAG)
        hold = slice(event.start, event.stop)
        if event.kind == "blink":
            out["blinks"].append({
                side.lower(): float(series[f"eyeBlink{side}"][peak].max()
                                    / truth[f"eyeBlink{side}"][hold].max())
                for side in ("Left", "Right")
            })  # fmt: skip
        elif event.kind == "wink":
            other = "Right" if event.detail == "Left" else "Left"
            out["winks"].append({
                "eye": event.detail.lower(),
                "peak": float(series[f"eyeBlink{event.detail}"][peak].max()),
                "other": float(series[f"eyeBlink{other}"][peak].max()),
            })  # fmt: skip
        elif event.kind == "gaze":
            got = _gaze(series, hold)
            # No direction at all (a rig without eye-look shapes, or one reading none): no
            # direction is seen, rather than the first of four zeros.
            seen = max(got, key=lambda d: got[d]) if max(got.values()) > 0 else None
            out["gaze"].append({
                "direction": event.detail,
                "seen": seen,
                "right": seen == event.detail,
                "share": got[event.detail] / _gaze(truth, hold)[event.detail],
                # How shut the eyes read over the hold (the truth: open): the mean of both
                # blinks, a gaze read as a closing (README, issue 34's option (ag)).
                "shut": float(np.mean([series[f"eyeBlink{side}"][hold].mean()
                                       for side in ("Left", "Right")])),
            })  # fmt: skip
        else:
            jaw = series["jawOpen"][hold].mean() / truth["jawOpen"][hold].mean()
            smile = (series["mouthSmileLeft"][hold] + series["mouthSmileRight"][hold]).mean()
            true_smile = (truth["mouthSmileLeft"][hold] + truth["mouthSmileRight"][hold]).mean()
            out["combo"].append({"jawOpen": float(jaw), "smile": float(smile / true_smile)})
    out["goals"] = eyes_goals(out)
    return out


def eyes_goals(scores: Mapping[str, Any]) -> dict[str, bool]:
    """Issue 34's eyes-clip goals on ``eyes_scores``'s figures: every blink >= 0.6 on both
    eyes and their mean >= 0.75; a wink >= 0.6 on its eye and <= 0.3 on the other; jaw and
    smile each >= 60 % of the truth; gaze direction right in every hold."""
    peaks = [v for blink in scores["blinks"] for v in (blink["left"], blink["right"])]
    return {
        "blinks": bool(peaks) and min(peaks) >= GOAL_BLINK_MIN
        and float(np.mean(peaks)) >= GOAL_BLINK_MEAN,
        "winks": all(
            w["peak"] >= GOAL_WINK_EYE and w["other"] <= GOAL_WINK_OTHER for w in scores["winks"]
        ),
        "gaze": all(g["right"] for g in scores["gaze"]),
        "combo": all(min(c.values()) >= GOAL_COMBO for c in scores["combo"]),
    }  # fmt: skip


def eyes_rows(
    character: Rig,
    clip: EyesClip,
    points: npt.ArrayLike,
    keys: Mapping[str, np.ndarray],
    *,
    noise: float,
    fps: float,
    filters: Mapping[str, tuple[str, float | None]],
    generic: Rig | None = None,
    contrast: tuple[float, float] | None = None,
) -> dict[str, dict[str, Any]]:
    """The eyes clip cloned by the personal and the generic path, each through ``filters``.

    Parameters
    ----------
    character : Rig
        The character's rig (as ``webcam.webcam_rows``'s).
    points : (F, K, 3) float
        The clip's feature points (tracked or exact; no NaN), frames at ``fps``.
    keys : {name: (K, 3)}
        The performer's captured keys (``webcam.captured_keys``), the neutral included.
    noise : float
        The landmark noise measured on the keys' held frames.
    filters : {label: (smoothing, acceleration)}
        ``smoothing.smooth_take``'s method ("none": each frame as it comes, as /perform
        publishes without a ``smoothing``; "kalman": the live filter at ``acceleration``
        (None: its default) and the measured noise; "rts": ``facecast clone``'s offline
        smoother) and its acceleration.
    generic : Rig, optional
        The generic path's rig before its re-base (default ``character``): the same
        targets on another source (``bench webcam``'s shipped generic set).
    contrast : (low, high), optional
        The generic path's blink curve, as the client's calibrate sends it
        (``webcam.generic_rig``; None: the server's).

    Returns
    -------
    {"<path> <label>": eyes_scores(...)}, path "personal" or "generic".
    """
    x = np.asarray(points, dtype=np.float64)
    times = np.arange(len(x)) / fps
    # Points after the character's (a later layout's: the iris centres) are the performer's:
    # the personal rig is fitted on them too, the generic one takes the first K, as the
    # page sends each rig its own count.
    source = character if generic is None else generic
    k = source.num_points
    rigs = {
        "personal": fit_performer(character, keys, noise=noise),
        "generic": generic_rig(source, keys["neutral"][:k], noise, keys, contrast),
    }
    rows: dict[str, dict[str, Any]] = {}
    for path, rig in rigs.items():
        for label, (method, acceleration) in filters.items():
            take = smooth_take(rig, x[:, : rig.num_points], times, smoothing=method,
                               noise=noise, acceleration=acceleration)  # fmt: skip
            weights = take.rig.weights(take.points)
            rows[f"{path} {label}"] = eyes_scores(weights, take.rig.names, clip)
    return rows
