"""The demo's face controls: per-character displacement fields, a jaw and sliding lids.

Turns (T, C) control values into (T, V, 3) vertices of either demo head; it knows no
expression names or performances (see ``demo``) and must not read files.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .geometry import (
    CARTOON,
    HUMAN,
    Head,
    ellipsoid_z,
    eye_curve,
    front_height,
    front_mask,
    gauss,
    head_landmarks,
    icosphere,
    lip_envelope,
    lip_height,
    neutral_mesh,
    smoothstep,
    uv_sphere,
)

__all__ = ["CONTROLS", "CONTROL_INDEX", "CharacterModel", "character_model", "pose_vertices"]

# The face controls; each expression is a point in this space.
CONTROLS = (
    "jaw", "smile", "frown", "stretch", "pucker", "press", "bite", "lip_raise",
    "wrinkle", "brow_in_up", "brow_out_up", "brow_down", "lid", "squint", "cheek", "ears",
)  # fmt: skip
CONTROL_INDEX = {name: i for i, name in enumerate(CONTROLS)}


@dataclass(frozen=True, eq=False)
class CharacterModel:
    """A character's neutral mesh plus everything its controls need, computed once."""

    head: Head
    neutral: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    fields: np.ndarray  # (C, V*3) linear displacement per unit control
    jaw_weight: np.ndarray  # (V,)
    cavity: np.ndarray  # (V,) depth of the mouth opening per unit jaw
    eye_index: np.ndarray  # (E,) vertices near the eyes, moved by the lids
    landmarks: dict[str, np.ndarray]


def _control_fields(head: Head, neutral: np.ndarray, ear: np.ndarray) -> np.ndarray:
    """(C, V, 3) displacement of each linear control at strength 1."""
    x, y, _ = neutral.T
    ex, ey, er = head.eye
    by = head.brow[0]
    my, hw, lt = head.mouth
    cx, cy, _ = head.cheek
    front = front_mask(head, ellipsoid_z(head, x, y))
    fields = np.zeros((len(CONTROLS), len(x), 3))

    def add(control: str, weight: np.ndarray, vector: list[float]) -> None:
        fields[CONTROL_INDEX[control]] += (weight * front)[:, None] * np.asarray(vector, float)

    sc = 0.5 * hw + 0.2  # reach of a mouth corner's pull
    for s in (-1.0, 1.0):
        corner = gauss(x, y, s * hw, my, sc, sc * 0.9)
        add("smile", corner, [s * 0.45, 0.95, -0.3])
        add("smile", gauss(x, y, s * (hw + 0.6), my + 1.6, 1.5, 1.3), [s * 0.1, 0.4, 0.3])
        add("frown", corner, [s * 0.1, -0.75, -0.05])
        add("stretch", corner, [s * 0.8, -0.2, -0.3])
        add("pucker", corner, [-s * 0.75, 0.0, 0.3])
        add("lip_raise", gauss(x, y, s * 0.45 * hw, my + lt, 0.7, 0.6), [0.0, 0.4, 0.15])
        add("lip_raise", gauss(x, y, s * (hw * 0.6 + 0.5), my + 2.0, 0.9, 1.0), [0.0, 0.25, 0.2])
        add("wrinkle", gauss(x, y, s * 0.9, head.nose[0] - 0.2, 0.7, 0.8), [0.0, 0.35, 0.1])
        add("wrinkle", gauss(x, y, s * 1.2, ey - 0.3 * er, 0.6, 0.6), [s * -0.05, 0.1, 0.15])
        add("brow_in_up", gauss(x, y, s * 0.45 * ex, by, 1.1, 0.9), [s * -0.05, 0.75, 0.05])
        add("brow_out_up", gauss(x, y, s * 1.25 * ex, by - 0.2, 1.4, 1.0), [0.0, 0.7, 0.0])
        add("brow_down", gauss(x, y, s * 0.45 * ex, by, 1.1, 0.9), [-s * 0.3, -0.6, 0.2])
        add("brow_down", gauss(x, y, s * 1.25 * ex, by - 0.2, 1.2, 0.9), [0.0, -0.2, 0.0])
        add("squint", gauss(x, y, s * ex, ey - 1.1 * er, 0.9 * er, 0.5 * er), [0.0, 0.25, 0.15])
        add("cheek", gauss(x, y, s * cx, cy, 1.4, 1.3), [s * 0.05, 0.35, 0.35])
    lips_region = gauss(x, y, 0.0, my, hw * 0.8, 1.2 * lt + 0.6)
    upper_lip = gauss(x, y, 0.0, my + lt, hw * 0.75, 0.55)
    lower_lip = gauss(x, y, 0.0, my - 1.1 * lt, hw * 0.75, 0.55)
    chin = gauss(x, y, 0.0, head.chin[0] + 0.6, 1.6, 1.2)
    add("frown", lower_lip, [0.0, 0.15, 0.3])
    add("frown", chin, [0.0, 0.25, 0.15])
    add("pucker", lips_region, [0.0, 0.0, 0.75])
    add("pucker", upper_lip, [0.0, 0.12, 0.0])
    add("pucker", lower_lip, [0.0, -0.12, 0.0])
    add("stretch", lips_region, [0.0, 0.0, -0.15])
    add("press", upper_lip, [0.0, -0.18, -0.2])
    add("press", lower_lip, [0.0, 0.2, -0.2])
    lip_bulge = np.clip(lip_height(head, x, y), 0.0, None)
    fields[CONTROL_INDEX["press"], :, 2] -= 0.8 * front * lip_bulge
    add("press", chin, [0.0, 0.2, 0.12])
    add("bite", lower_lip, [0.0, 0.45, -0.55])
    add("bite", upper_lip, [0.0, 0.1, 0.1])
    add("brow_down", gauss(x, y, 0.0, by - 0.1, 0.35, 0.9), [0.0, 0.0, -0.25])
    add("brow_in_up", gauss(x, y, 0.0, by + 2.5, 3.0, 1.8), [0.0, 0.25, 0.0])
    add("brow_out_up", gauss(x, y, 0.0, by + 2.5, 3.5, 1.8), [0.0, 0.25, 0.0])
    fields[CONTROL_INDEX["ears"]] += ear[:, None] * np.array([0.0, 1.3, 0.9])
    return fields * head.gain


def _jaw_weight(head: Head, neutral: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V,) share of the jaw's rotation, and (V,) depth of the mouth opening per unit jaw."""
    x, y, z = neutral.T
    my, hw, _ = head.mouth
    # A sharp split along the mouth line between the corners, a soft one beyond them.
    beyond = smoothstep((np.abs(x) - 0.85 * hw) / (0.4 * hw + 2.0))
    width = 0.75 * head.groove + 2.5 * beyond
    below = smoothstep((my - y) / (2.0 * width) + 0.5)
    behind = smoothstep((z / head.radii[2] + 0.1) / 0.5)
    cavity = np.exp(-(((y - my) / (2.0 * head.groove)) ** 2)) * lip_envelope(head, x, 0.95)
    return below * behind, cavity * 3.0 * head.gain


def _eye_region(head: Head, neutral: np.ndarray) -> np.ndarray:
    """(E,) indices of the front vertices around either eye, the ones the lids move."""
    ex, ey, er = head.eye
    x, y, z = neutral.T
    near = (np.abs(np.abs(x) - ex) < 1.5 * er) & (np.abs(y - ey) < 1.55 * er)
    return np.flatnonzero(near & (z > 0))


@functools.cache
def character_model(character: str) -> CharacterModel:
    """The "source" head (a UV sphere) or the cartoon target (an icosphere), built once.

    Parameters
    ----------
    character : str
        ``"source"`` for the human-ish head; anything else gives the cartoon.

    Returns
    -------
    CharacterModel
        Read-only arrays, shared by every caller (the result is cached).
    """
    if character == "source":
        head, (dirs, faces) = HUMAN, uv_sphere(96, 72)
    else:
        head, (dirs, faces) = CARTOON, icosphere(5)
    neutral, ear = neutral_mesh(head, dirs)
    marks = head_landmarks(head)
    fields = _control_fields(head, neutral, ear)
    jaw_weight, cavity = _jaw_weight(head, neutral)
    for array in (neutral, faces, fields, jaw_weight, cavity):
        array.flags.writeable = False
    return CharacterModel(
        head=head,
        neutral=neutral,
        faces=faces,
        fields=fields.reshape(len(CONTROLS), -1),
        jaw_weight=jaw_weight,
        cavity=cavity,
        eye_index=_eye_region(head, neutral),
        landmarks=marks,
    )


def _lid_margins(
    head: Head, lid: npt.ArrayLike, squint: npt.ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """Upper and lower lid margins, in eye radii from the eye centre, per frame."""
    lids = np.asarray(lid, float)
    upper = 0.55 + head.lid_travel * np.clip(lids, 0.0, 1.6) + 1.1 * np.clip(lids, -1.2, 0.0)
    lower = -0.55 + 0.3 * np.clip(np.asarray(squint, float), 0.0, 1.2)
    # Closed lids meet, they do not cross; a smooth maximum keeps the lid's motion C1.
    upper = (upper + lower + np.sqrt((upper - lower) ** 2 + 0.15**2)) / 2.0
    return upper, lower


def pose_vertices(model: CharacterModel, controls: np.ndarray) -> np.ndarray:
    """Pose a character: linear control fields, then the jaw's turn and the lids' slide.

    Parameters
    ----------
    model : CharacterModel
    controls : (T, C) float64
        Control values per frame, columns in ``CONTROLS`` order.

    Returns
    -------
    (T, V, 3) float64
        Vertices per frame.
    """
    head, neutral = model.head, model.neutral
    t_count, v_count = controls.shape[0], neutral.shape[0]
    out: np.ndarray = (controls @ model.fields).reshape(t_count, v_count, 3)
    out += neutral
    # The jaw turns about a hinge in front of the ears; the lips part into a cavity.
    jaw = np.clip(controls[:, CONTROL_INDEX["jaw"]], -0.2, 1.6)
    angle = head.jaw_angle * jaw[:, None]
    pivot_y, pivot_z = head.eye[1] - 1.2, -0.5
    dy, dz = neutral[:, 1] - pivot_y, neutral[:, 2] - pivot_z
    cos, sin = np.cos(angle), np.sin(angle)
    w = model.jaw_weight
    out[:, :, 1] += w * ((cos - 1.0) * dy - sin * dz)
    out[:, :, 2] += w * (sin * dy + (cos - 1.0) * dz)
    # Deeper towards the lower lip, so the inside faces down, away from the light.
    out[:, :, 2] -= np.clip(jaw, 0.0, None)[:, None] ** 0.8 * model.cavity * (0.2 + 1.6 * w)
    # Lids slide over the eyeball: the band between the brow and the lower lid is
    # remapped so that the upper margin lands where the lid control puts it.
    idx = model.eye_index
    ex, ey, er = head.eye
    x, y = neutral[idx, 0], neutral[idx, 1]
    upper0, lower0 = _lid_margins(head, 0.0, 0.0)
    upper, lower = _lid_margins(
        head, controls[:, CONTROL_INDEX["lid"]], controls[:, CONTROL_INDEX["squint"]]
    )
    upper, lower = upper[:, None], lower[:, None]
    yr = (y - ey) / er
    curve = np.maximum(eye_curve(head, x), 0.05)
    upper0, lower0, upper, lower = upper0 * curve, lower0 * curve, upper * curve, lower * curve
    top = 1.5
    above = yr >= upper0
    mapped_above = top - (top - yr) * (top - upper) / (top - upper0)
    mapped_between = lower + (yr - lower0) * (upper - lower) / (upper0 - lower0)
    mapped_below = -top + (yr + top) * (lower + top) / (lower0 + top)
    mapped = np.where(above, mapped_above, np.where(yr >= lower0, mapped_between, mapped_below))
    mapped = np.where(np.abs(yr) <= top, mapped, yr)
    reach = smoothstep((1.45 - np.abs(np.abs(x) - ex) / er) / 0.35)
    new_y = y + reach * (mapped - yr) * er
    z_old = front_height(head, x, y, upper0 / curve, lower0 / curve)
    z_new = front_height(head, x, new_y, upper / curve, lower / curve)
    base = ellipsoid_z(head, x, new_y) - ellipsoid_z(head, x, y)
    front = front_mask(head, ellipsoid_z(head, x, y))
    out[:, idx, 1] += new_y - y
    out[:, idx, 2] += base + front * (z_new - z_old)
    return out
