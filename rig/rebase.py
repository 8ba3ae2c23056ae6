"""A rig re-based on another face's neutral, noise-aware and bounded: the generic-rig re-base.

``Rig.calibrated`` keeps a rig exact on another performer's neutral, so the performer's
landmark noise, and every way their face differs from the rig's source face, reach the
weights amplified. ``rebase`` refits the weight model for that: no fitting of targets, no
I/O; it must not change the rig it is given.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt

from .characters.generic import is_gaze
from .closure import CLOSURE_NAMES, check_contrast
from .errors import InputError
from .fit import fit_weight_model
from .pose import similarity_transform
from .rig import Rig
from .weight_model import Floats, WeightModel

__all__ = [
    "DEPTH_NOISE_FACTOR",
    "IDENTITY_NOISE_FACTOR",
    "MAX_NOISE_RELATIVE",
    "REBASE_BLINK_CONTRAST",
    "REBASE_BLINK_CONTRAST_GAZELESS",
    "REBASE_CLAMP",
    "calibrate",
    "default_contrast",
    "identity_noise",
    "rebase",
]

#: How much noisier the depth (z) of the performer's points is taken to be than x and y.
#: A webcam tracker measures a face in the image plane and guesses its depth from a learned
#: prior: a mouth opening in the image comes back with almost no depth motion, where the
#: source face's jawOpen moves the chin back as much as down (ICT-FaceKit: 2.9 cm both
#: ways). Rotated into the source face's pitch (the tests' photo leans back ~25 degrees
#: against ICT's face), the missing depth reads as the jaw thrust forward. Measured
#: (docs/perform.md): on the page's tracked photo, ICT's jawOpen over jawForward on
#: mouth-open frames is 0.20 / 0.13 at 1, 0.24 / 0.09 at 3, 0.25 / 0.08 at 10; on the demo
#: face with no depth motion at all (tests/rig/test_rebase.py) 1 and 3 read the jaw opening
#: as another expression, 10 reads it right. At 30 the fit keeps one principal axis fewer
#: on ICT (50 of 51) and the neutral is no longer exact (weights up to 0.03).
DEPTH_NOISE_FACTOR = 10.0
#: The share of the identity residual (``identity_noise``) taken as noise the refit must not
#: pass on. The expressions of two faces differ by less than their shapes do; how much less
#: was measured (docs/perform.md) on a real face and on rendered ones with a known truth.
#: First (20 points): the tests' photo, mouth opening, jawOpen / jawForward medians 0.25 /
#: 0.08 at 1, 0.35 / 0.16 at 0.5, 0.37 / 0.31 at 0.25; `facecast bench webcam` 3.99 at 1,
#: 2.92 at 0.5, 2.59 at 0.25 (NNLS 3.04): half was taken. Re-measured on the 24-point layout
#: (2026-12-04, README option (m)): the take's generic error 2.783 at 0.5, 2.623 at 0.4,
#: 2.561 at 0.35, 2.515 at 0.3, 2.486 at 0.25, 2.485 at 0.2 (NNLS 2.690); the photo's
#: jawOpen leads its runner-up (jawForward) by 0.184 at 0.5, 0.135 at 0.35, 0.097 at 0.3,
#: 0.044 at 0.25 and trails it at 0.2; the synthetic depthless jaw opening of
#: tests/rig/test_rebase.py reads `aa` by 0.12 at 0.5, 0.05 at 0.35, 0.01 at 0.3, is misread
#: at 0.278 (`oo`). 0.35 is the least share that keeps both margins clear (over 40 % of
#: half's); the eyes clip's generic blinks rise 0.24 -> 0.29, its jaw and smile 70 -> 74 %
#: and 36 -> 46 %, and on exact landmarks its winks and jaw + smile reach the issue's goals.
IDENTITY_NOISE_FACTOR = 0.35
#: A ``noise`` above this many times the neutral's radius (RMS distance of its points from
#: their centre) is refused: it cannot be landmark noise in the points' units.
MAX_NOISE_RELATIVE = 10.0
#: The bounds of a re-based rig's weights: each non-neutral weight in [0, 1], so a face
#: that no example explains shows the nearest mix of them, never an extrapolated one.
REBASE_CLAMP = "unit"
#: The contrast curve of a re-based rig's closed-read blinks (``closure.ClosureMap``): a
#: mapped blink below 0.4 reads open, above 0.8 closed, a smoothstep between. The re-based
#: rig reads the performer through another face's keys, and reads a held gaze partly
#: closed: on `bench webcam`'s eyes clip with the eyeballs turned at ARKit's 35°, up, down,
#: left and right held read as closed by 0.43 / 0.59 / 0.44 / 0.34 (the Kalman filter's
#: rows), 0.08 / 0.43 / 0.12 / 0.13 through the curve; its quick blinks 0.84 / 0.94 (min /
#: mean) -> 1.00 / 1.00 and a wink's other eye 0.19 -> 0.00 on the default videos; the real
#: take's error 2.413 -> 2.399, the calmer one's 1.547 -> 1.597 (its eyes never close; the
#: curve opens their small closing). 0.3-0.7 leaves a held gaze at 0.28-0.69, 0.5-0.9 takes
#: a quick blink's least peak to 0.94 (README, issue 34's option (ag)). The performer's own
#: rig (``fit_performer``) keeps the linear map: there the curve took the take's error
#: above NNLS's. This is the curve of a rig that reads gaze (it has eye-look examples).
REBASE_BLINK_CONTRAST = (0.4, 0.8)
#: The curve of a rig with no eye-look examples, as a character uploaded as a file is
#: paired (its look-at turns its eyes): nothing but the blinks explains the lids' motion, so
#: a blink reads less whole and a look less closed. Its high end lower: on `bench webcam
#: --as-uploaded` (live Kalman rows, 2026-12-05 19:35 UTC) the page's quick blinks 0.87 /
#: 0.97 -> 1.00 / 1.00, `facecast perform`'s 0.79 / 0.94 -> 0.99 / 1.00, and the real
#: take's slower right-eye closure on `facecast perform`'s tracks 0.65 -> 0.93 of the truth
#: (0.41 -> 0.64 with the eyes still); a held look down reads 0.20 -> 0.31 shut (page),
#: 0.34 -> 0.49 (`facecast perform`), the takes within 0.02 (README, issue 34's option
#: (ak)). On a rig with eye-look examples the same curve reads that look down 0.43 -> 0.55
#: shut with every blink already whole, so it keeps ``REBASE_BLINK_CONTRAST``.
REBASE_BLINK_CONTRAST_GAZELESS = (0.4, 0.7)


def default_contrast(names: Sequence[str]) -> tuple[float, float]:
    """The server's blink curve for a rig with these example ``names``: whether it reads
    gaze (an example ``characters.generic.is_gaze``: ARKit's eye-look shapes, VRM's look
    presets) decides (``REBASE_BLINK_CONTRAST`` / ``REBASE_BLINK_CONTRAST_GAZELESS``)."""
    reads_gaze = any(is_gaze(name) for name in names)
    return REBASE_BLINK_CONTRAST if reads_gaze else REBASE_BLINK_CONTRAST_GAZELESS


def identity_noise(rig: Rig, neutral: npt.ArrayLike) -> float:
    """How far ``neutral`` (K, 3) differs from the rig's source neutral, per coordinate.

    The root-mean-square residual of the best similarity (rotation, uniform scale,
    translation) of the source neutral onto ``neutral``, in ``neutral``'s units: the part of
    the two faces' shapes no re-base can remove. A re-based rig reads the performer's
    expression displacements as the source face's; they differ by about this much too.
    """
    x = np.asarray(neutral, dtype=np.float64)
    source = rig.source_neutral
    rotation, scales, translation = similarity_transform(source[None], x, scale=True)
    residual = x - (scales[0] * source @ rotation[0].T + translation[0])
    return float(np.sqrt(np.mean(residual * residual)))


def rebase(
    rig: Rig,
    neutral: npt.ArrayLike,
    *,
    noise: float,
    depth_factor: float = DEPTH_NOISE_FACTOR,
) -> Rig:
    """``rig`` re-based on a performer's neutral, refitted for their noise and bounded.

    As ``rig.calibrated(neutral)``, frames are read as displacements from ``neutral``, the
    rig's source examples mapped into the performer's face frame by the same similarity;
    but the weight model is then refitted there (``fit_weight_model``) for landmark noise
    of standard deviation sigma on x and y and ``depth_factor`` * sigma on z, with sigma
    the largest of ``noise`` (the tracker's, measured), ``IDENTITY_NOISE_FACTOR`` times
    ``identity_noise`` (how far this face is from the source face) and the rig's own
    fitted noise, and its weights bounded
    to [0, 1] (``REBASE_CLAMP``). So landmark noise and identity mismatch are shrunk
    towards the neutral instead of amplified, and viewers never get extrapolated weights.
    The neutral's own points give the neutral exactly.

    Parameters
    ----------
    rig : Rig
        Any fitted rig (a region rig refits each region).
    neutral : (K, 3) float
        The performer's neutral, in their tracker's face frame (z the depth).
    noise : float
        The tracker's landmark noise in ``neutral``'s units, >= 0 (e.g. measured from the
        frames the neutral was held over, ``estimate_noise``).
    depth_factor : float
        >= 1: z's noise relative to x and y's.

    Returns
    -------
    Rig
        Its ``calibration`` is ``neutral``; ``fit_report["rebase"]`` says the sigma used
        and where from.

    Raises
    ------
    InputError
        As ``Rig.calibrated`` (``wrong_point_count``, ``non_finite``, ``out_of_range``),
        and ``bad_noise`` for a ``noise`` or ``depth_factor`` out of range (``noise`` above
        ``MAX_NOISE_RELATIVE`` times the neutral's radius included).
    """
    noise, depth_factor = _sanitize(noise, depth_factor)
    calibrated = rig.calibrated(neutral)  # checks the neutral; gives the similarity
    points = np.asarray(calibrated.calibration, dtype=np.float64)
    radius = float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))
    if noise > MAX_NOISE_RELATIVE * radius:
        # Noise beyond the face itself says nothing, and its square overflows the refit.
        raise InputError(
            f"noise {noise:g} is more than {MAX_NOISE_RELATIVE:g}x the neutral's radius "
            f"{radius:.3g}: give the landmark noise in the points' units",
            code="bad_noise",
        )
    k = points.shape[0]
    matrix = calibrated.model.input_matrix
    assert matrix is not None
    sr = matrix[:3, :3].T  # source = s R (performer - neutral) + source neutral
    scale = float(np.cbrt(abs(np.linalg.det(sr))))
    identity = IDENTITY_NOISE_FACTOR * identity_noise(rig, points)
    fitted = float(rig.fit_report.get("noise", 0.0) or 0.0) / scale
    sigma = max(noise, identity, fitted)
    # Performer frame -> weighted frame: z scaled by 1 / depth_factor, so isotropic noise
    # sigma there is (sigma, sigma, depth_factor * sigma) in the performer's frame.
    weight: Floats = np.diag([1.0, 1.0, 1.0 / depth_factor])
    back = np.linalg.inv(sr).T @ weight  # source displacement rows -> weighted rows
    offset = (points - points @ weight).reshape(-1)
    input_matrix: Floats = np.kron(np.eye(k), weight).astype(np.float64)
    names = [rig.names] if rig.regions is None else [
        (rig.names[0], *(rig.names[c] for c in columns)) for _, columns in rig.regions
    ]  # fmt: skip
    models = tuple(
        _refit(model, region_names, points, back, sigma).with_input_map(input_matrix, offset)
        for model, region_names in zip(rig.models, names, strict=True)
    )
    report = {
        **rig.fit_report,
        "rebase": {
            "noise": sigma,
            "tracker_noise": noise,
            "identity_noise": identity,
            "rig_noise": fitted,
            "depth_factor": depth_factor,
            "clamp": REBASE_CLAMP,
        },
    }
    return rig.with_models(models, calibration=points, report=report)


def _sanitize(noise: float, depth_factor: float) -> tuple[float, float]:
    try:
        noise, depth_factor = float(noise), float(depth_factor)
    except (TypeError, ValueError):
        raise InputError("noise and depth_factor must be numbers", code="bad_noise") from None
    if not (np.isfinite(noise) and noise >= 0):
        raise InputError(f"noise must be a finite number >= 0, got {noise}", code="bad_noise")
    if not (np.isfinite(depth_factor) and depth_factor >= 1):
        raise InputError(
            f"depth_factor must be a finite number >= 1, got {depth_factor}", code="bad_noise"
        )
    return noise, depth_factor


def _refit(
    model: WeightModel,
    names: tuple[str, ...],
    neutral: np.ndarray,
    back: np.ndarray,
    sigma: float,
) -> WeightModel:
    """``model``'s examples moved onto ``neutral`` in the weighted frame, fitted for sigma.

    The source examples are the model's own (eq. 3.7 inverted: mean + p_j F), so the
    rig's example files are not needed.
    """
    displacements = model.mean + model.params @ model.features  # (M, 3K), eq. 3.4, 3.7
    displacements -= displacements[0]  # the neutral's is 0 up to the PCA's rounding
    k = neutral.shape[0]
    examples = neutral + displacements.reshape(-1, k, 3) @ back
    refitted, _ = fit_weight_model(
        names, examples, noise=sigma, kernel=model.kernel, clamp=REBASE_CLAMP
    )
    return refitted


def calibrate(
    rig: Rig,
    neutral: npt.ArrayLike,
    noise: float | None = None,
    blinks: Mapping[str, npt.ArrayLike] | None = None,
    contrast: tuple[float, float] | None = None,
) -> Rig:
    """A session's re-base on a performer's neutral: exact without ``noise``, else ``rebase``.

    What a ``calibrate`` message asks for (PROTOCOL.md §5.1.3): without its ``noise`` the
    rig is ``rig.calibrated(neutral)``, exact as fitted; with it, noise-aware and bounded,
    and with ``blinks`` ({"eyeBlinkLeft" / "eyeBlinkRight": (K, 3)}, the performer's
    captured closed eyes, some or both) each blink weight is mapped so that the re-based
    rig reads the performer's own closed eye as 1 and their neutral as 0 (``closure``, as
    ``fit_performer`` does with a personal capture), then through the contrast curve
    ``contrast`` (low, high) (None: the server's for this rig, ``default_contrast``; the
    performer's own, as calibrate ``blink_contrast`` carries it: ``closure.check_contrast``).
    Names the rig lacks are ignored.
    """
    curve = default_contrast(rig.names) if contrast is None else check_contrast(contrast)
    if noise is None:
        return rig.calibrated(neutral)
    rebased = rebase(rig, neutral, noise=noise)
    if not blinks:
        return rebased
    unknown = sorted(set(blinks) - set(CLOSURE_NAMES))
    if unknown:
        raise InputError(
            f"blinks: {unknown[0]!r} is not one of {', '.join(CLOSURE_NAMES)}", code="bad_input"
        )
    return rebased.with_closed_eyes(neutral, blinks, curve)
