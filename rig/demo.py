"""The procedural demo: a human-ish source head, a cartoon target head and a performance.

Everything is generated from seeded formulas in milliseconds, so the demo runs on a fresh
machine with no downloads; it must not read files or touch the network.

Public names
------------
- ``demo_example_set()`` -> ExampleSet: source head (warped UV sphere) and cartoon target
  (icosphere), neutral + 6 emotions + 5 visemes + a blink (``DEMO_NAMES``).
- ``demo_animation(seconds, fps)`` -> SourceAnimation: the source performance.
- ``demo_activations(seconds, fps)`` -> (F, M): per-example activation curves that
  drive the performance (column 0, the neutral, is zero).
- ``demo_target_frames(activations)`` -> (F, V, 3): the ideal clone, the target's own
  expressions driven by the same activations (ground truth for evaluation).
- ``demo_landmarks(character)``: named semantic landmark positions on either neutral.

Each expression is a set of facial "controls" (jaw, smile, brows, lids, ...); the source
and the target give the same expression different control values, so the target's
examples are characteristic of the cartoon and not a resampled copy of the source's.
Controls act on neutral geometry in a face-local frame (y up, +z out of the face, cm),
mostly as linear displacement fields, with a rotating jaw and sliding eyelids that make
frames nonlinear in the activations.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from .animation import SourceAnimation
from .errors import InputError
from .examples import ExampleSet

__all__ = [
    "DEMO_EMOTIONS",
    "DEMO_FEATURE_NAMES",
    "DEMO_NAMES",
    "DEMO_VISEMES",
    "demo_activations",
    "demo_animation",
    "demo_example_set",
    "demo_landmarks",
    "demo_target_frames",
]

DEMO_EMOTIONS = ("happy", "sad", "surprise", "fear", "anger", "disgust")
DEMO_VISEMES = ("aa", "oo", "ee", "mbp", "fv")
DEMO_NAMES = ("neutral", *DEMO_EMOTIONS, *DEMO_VISEMES, "blink")

# The face controls; each expression is a point in this space.
_CONTROLS = (
    "jaw", "smile", "frown", "stretch", "pucker", "press", "bite", "lip_raise",
    "wrinkle", "brow_in_up", "brow_out_up", "brow_down", "lid", "squint", "cheek", "ears",
)  # fmt: skip
_C = {name: i for i, name in enumerate(_CONTROLS)}

_SOURCE_POSES: dict[str, dict[str, float]] = {
    "happy": {"smile": 1.0, "cheek": 0.8, "squint": 0.45, "jaw": 0.12, "lid": -0.15},
    "sad": {"frown": 1.0, "brow_in_up": 1.0, "lid": -0.35, "press": 0.2},
    "surprise": {"brow_in_up": 1.0, "brow_out_up": 1.0, "lid": 1.0, "jaw": 0.75, "pucker": 0.2},
    "fear": {"brow_in_up": 1.0, "brow_out_up": 0.35, "lid": 0.8, "stretch": 0.9, "jaw": 0.3},
    "anger": {"brow_down": 1.0, "squint": 0.6, "lid": 0.25, "press": 0.55, "frown": 0.25},
    "disgust": {"wrinkle": 1.0, "lip_raise": 0.9, "brow_down": 0.45, "squint": 0.5, "frown": 0.3},
    "aa": {"jaw": 1.0, "stretch": 0.1},
    "oo": {"pucker": 1.0, "jaw": 0.3},
    "ee": {"stretch": 0.8, "jaw": 0.3, "smile": 0.2, "lip_raise": 0.2},
    "mbp": {"press": 1.0, "jaw": -0.05},
    "fv": {"bite": 1.0, "lip_raise": 0.25, "jaw": 0.1},
    "blink": {"lid": -1.0},
}
# The cartoon's own acting: a bigger grin, a wider-eyed surprise, harder furrows, ears
# that droop when sad and perk up when surprised; its sad mouth moves comparatively less.
_TARGET_POSES: dict[str, dict[str, float]] = {
    "happy": {"smile": 1.9, "cheek": 1.0, "squint": 0.5, "jaw": 0.4, "ears": 0.4},
    "sad": {"frown": 0.8, "brow_in_up": 1.6, "lid": -0.45, "ears": -1.0},
    "surprise": {"brow_in_up": 1.5, "brow_out_up": 1.7, "lid": 1.8, "jaw": 1.15, "ears": 1.0},
    "fear": {"brow_in_up": 1.6, "brow_out_up": 0.5, "lid": 1.5, "stretch": 1.3, "jaw": 0.45,
             "ears": -0.6},
    "anger": {"brow_down": 1.8, "squint": 0.7, "lip_raise": 0.7, "frown": 0.5, "jaw": 0.15,
              "ears": -0.4},
    "disgust": {"wrinkle": 1.6, "lip_raise": 1.3, "brow_down": 0.6, "squint": 0.6, "frown": 0.6,
                "ears": -0.3},
    "aa": {"jaw": 1.3, "stretch": 0.2},
    "oo": {"pucker": 1.35, "jaw": 0.35},
    "ee": {"stretch": 1.2, "jaw": 0.35, "smile": 0.35, "lip_raise": 0.25},
    "mbp": {"press": 1.2, "pucker": 0.15},
    "fv": {"bite": 1.3, "lip_raise": 0.35, "jaw": 0.1},
    "blink": {"lid": -1.0},
}  # fmt: skip

# Semantic feature points on the source, by landmark name (about 20).
DEMO_FEATURE_NAMES = (
    "mouth_corner_l", "mouth_corner_r", "upper_lip", "lower_lip",
    "upper_lid_l", "upper_lid_r", "lower_lid_l", "lower_lid_r",
    "brow_inner_l", "brow_inner_r", "brow_outer_l", "brow_outer_r",
    "forehead_l", "forehead_r", "chin", "jaw_l",
    "cheek_l", "cheek_r", "nose_tip", "nose_wing_l", "nose_wing_r",
)  # fmt: skip

_MAX_FRAMES = 36_000  # 10 min at 60 fps of points
_MAX_VERTEX_FRAMES = 4_000  # bounds the (F, Vs, 3) float32 meshes to about 220 MB


@dataclass(frozen=True)
class _Head:
    """Proportions of one character, cm; +x is the character's left."""

    radii: tuple[float, float, float]
    narrow: float  # how much the lower head narrows towards the chin
    eye: tuple[float, float, float]  # x, y, eyeball radius
    eye_bulge: float
    socket: float
    brow: tuple[float, float, float]  # y, height, thickness
    nose: tuple[float, float]  # tip y, tip height
    mouth: tuple[float, float, float]  # y, half-width, lip thickness
    lips: float  # lip fullness
    muzzle: tuple[float, float, float, float]  # y, sx, sy, height
    cheek: tuple[float, float, float]  # x, y, height
    chin: tuple[float, float]  # y, height
    ears: float  # 0: none
    jaw_angle: float  # radians at jaw = 1
    gain: float  # overall size of control displacements
    lid_travel: float = 0.4
    groove: float = 0.16  # half-width of the mouth line; wider on coarser meshes


_HUMAN = _Head(
    radii=(7.3, 10.2, 8.6), narrow=0.3, eye=(3.1, 1.4, 1.15), eye_bulge=0.9, socket=1.5,
    brow=(3.15, 0.7, 0.65), nose=(-1.9, 2.1), mouth=(-4.6, 2.5, 0.5), lips=0.6,
    muzzle=(-4.0, 2.6, 2.4, 0.9), cheek=(3.4, -1.8, 0.55), chin=(-7.6, 0.7), ears=0.0,
    jaw_angle=0.24, gain=1.0,
)  # fmt: skip
_CARTOON = _Head(
    radii=(8.2, 8.8, 8.0), narrow=0.12, eye=(2.9, 1.9, 1.9), eye_bulge=1.2, socket=1.0,
    brow=(4.35, 0.8, 0.5), nose=(-1.4, 0.9), mouth=(-4.0, 3.4, 0.4), lips=0.3,
    muzzle=(-3.4, 3.4, 2.6, 2.3), cheek=(4.3, -1.2, 0.5), chin=(-6.9, 0.4), ears=2.6,
    jaw_angle=0.22, gain=1.25, lid_travel=0.45, groove=0.3,
)  # fmt: skip


# -- meshes ------------------------------------------------------------------------------
def _warped_angles(count: int, lo: float, hi: float, peak: float, width: float, boost: float):
    """``count`` angles in [lo, hi], denser (by 1 + boost) around ``peak``."""
    fine = np.linspace(lo, hi, 4096)
    density = 1.0 + boost * np.exp(-(((fine - peak) / width) ** 2))
    cumulative = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2)])
    return np.interp(np.linspace(0.0, cumulative[-1], count), cumulative, fine)


def _uv_sphere(n_lon: int, n_lat: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (V, 3) and faces of a UV sphere, poles on y, denser on the face."""
    lon = _warped_angles(n_lon + 1, -math.pi, math.pi, 0.0, 0.8, 3.0)[:-1]
    elev = _warped_angles(n_lat + 1, -math.pi / 2, math.pi / 2, -0.15, 0.55, 3.5)[1:-1]
    el, lo = np.meshgrid(elev, lon, indexing="ij")  # rows bottom to top
    ring = np.stack([np.cos(el) * np.sin(lo), np.sin(el), np.cos(el) * np.cos(lo)], axis=-1)
    dirs = np.concatenate([[[0.0, -1.0, 0.0]], ring.reshape(-1, 3), [[0.0, 1.0, 0.0]]])
    rows, cols = len(elev), n_lon
    grid = 1 + np.arange(rows * cols).reshape(rows, cols)
    nxt = np.roll(grid, -1, axis=1)
    a, b, c, d = grid[:-1], nxt[:-1], nxt[1:], grid[1:]
    quads = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    top = len(dirs) - 1
    bottom_fan = np.stack([np.zeros(cols, int), nxt[0], grid[0]], -1)
    top_fan = np.stack([grid[-1], nxt[-1], np.full(cols, top)], -1)
    return dirs, np.concatenate([bottom_fan, quads, top_fan]).astype(np.int64)


def _icosphere(levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (V, 3) and faces of a subdivided icosahedron."""
    t = (1.0 + 5.0**0.5) / 2.0
    verts = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float
    )  # fmt: skip
    faces = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    )  # fmt: skip
    for _ in range(levels):
        edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mids = len(verts) + inverse.reshape(-1, 3)
        verts = np.concatenate([verts, (verts[unique[:, 0]] + verts[unique[:, 1]]) / 2])
        a, b, c = faces.T
        ab, bc, ca = mids.T
        faces = np.concatenate(
            [np.stack(f, -1) for f in ([a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca])]
        )
    return verts / np.linalg.norm(verts, axis=1, keepdims=True), faces.astype(np.int64)


# -- geometry of a head ----------------------------------------------------------------------
def _g(x, y, cx, cy, sx, sy):
    return np.exp(-(((x - cx) / sx) ** 2) - ((y - cy) / sy) ** 2)


def _smooth(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _narrowing(head: _Head, y):
    return 1.0 - head.narrow * _smooth(-y / head.radii[1])


def _lip_envelope(head: _Head, x, extra=1.0):
    hw = head.mouth[1] * extra
    return np.clip(1.0 - (x / hw) ** 2, 0.0, 1.0) ** 0.6


def _lips(head: _Head, x, y):
    """Height of the lips and the mouth line (a groove) around the mouth."""
    my, _, lt = head.mouth
    env = _lip_envelope(head, x)
    upper = np.exp(-(((y - my - 1.1 * lt) / (0.95 * lt)) ** 2))
    lower = np.exp(-(((y - my + 1.2 * lt) / (1.05 * lt)) ** 2))
    groove = np.exp(-(((y - my) / head.groove) ** 2)) * _lip_envelope(head, x, 1.06)
    return head.lips * env * (upper + 1.1 * lower) - 0.35 * groove


def _eye_curve(head: _Head, x):
    """(…) factor in [0, 1] shaping lid margins into an almond: 1 mid-eye, 0 at the corners."""
    ex, _, er = head.eye
    xr = (np.abs(x) - ex) / (1.2 * er)
    return np.clip(1.0 - xr**2, 0.0, 1.0)


def _eye_height(head: _Head, x, y, upper, lower):
    """Eyeball with sliding lids; ``upper``/``lower`` are the lid margins in eye radii."""
    ex, ey, er = head.eye
    r2 = ((np.abs(x) - ex) ** 2 + (y - ey) ** 2) / er**2
    ball = head.eye_bulge * np.exp(-r2 / 1.1)
    yr = (y - ey) / er
    curve = _eye_curve(head, x)
    cover = np.maximum(
        _smooth((yr - upper * curve) / 0.4 + 0.5), _smooth((lower * curve - yr) / 0.4 + 0.5)
    )
    lid = 0.28 * er * cover * _smooth((1.9 - np.sqrt(r2)) / 0.8)
    crease = -0.1 * er * np.exp(-(((yr - 1.0 - 0.3 * upper) / 0.15) ** 2)) * np.exp(-r2 / 1.5)
    return ball + lid + crease - head.socket * np.exp(-r2 / 1.8)


def _front_height(head: _Head, x, y, upper=0.55, lower=-0.55):
    """Height of the facial features above the ellipsoid, along +z, at (x, y)."""
    ex, ey, _ = head.eye
    by, bh, bt = head.brow
    ny, nh = head.nose
    muy, msx, msy, mh = head.muzzle
    cx, cy, ch = head.cheek
    chy, chh = head.chin
    h = mh * _g(x, y, 0, muy, msx, msy) + chh * _g(x, y, 0, chy, 1.6, 1.0)
    h = h + ch * (_g(x, y, cx, cy, 1.6, 1.4) + _g(x, y, -cx, cy, 1.6, 1.4))
    h = h + bh * (_g(x, y, ex, by, 1.9, bt) + _g(x, y, -ex, by, 1.9, bt))
    h = h + 0.5 * bh * _g(x, y, 0, by - 0.3, 1.0, 0.8)
    # Nose: bridge from between the eyes to the tip, tip ball, wings, nostrils.
    bridge_len = max(ey - ny, 0.5)
    h = h + 0.45 * nh * _g(x, y, 0, (ey + ny) / 2, 0.55, bridge_len * 0.6)
    h = h + 0.75 * nh * _g(x, y, 0, ny, 0.75, 0.65)
    h = h + 0.4 * nh * (_g(x, y, 0.9, ny - 0.3, 0.5, 0.45) + _g(x, y, -0.9, ny - 0.3, 0.5, 0.45))
    h = h - 0.12 * nh * (_g(x, y, 0.45, ny - 0.7, 0.25, 0.2) + _g(x, y, -0.45, ny - 0.7, 0.25, 0.2))
    return h + _lips(head, x, y) + _eye_height(head, x, y, upper, lower)


def _ellipsoid_z(head: _Head, x, y):
    rx, ry, rz = head.radii
    x0 = x / _narrowing(head, y)
    return rz * np.sqrt(np.clip(1.0 - (x0 / rx) ** 2 - (y / ry) ** 2, 0.0, None))


def _front_mask(head: _Head, base_z):
    return _smooth((base_z / head.radii[2] - 0.15) / 0.35)


def _surface_point(head: _Head, x: float, y: float) -> np.ndarray:
    z = _ellipsoid_z(head, x, y)
    return np.array([x, y, z + _front_mask(head, z) * _front_height(head, x, y)])


def _landmarks(head: _Head) -> dict[str, np.ndarray]:
    ex, ey, er = head.eye
    by = head.brow[0]
    my, hw, lt = head.mouth
    marks = {
        "mouth_corner_l": (hw, my),
        "mouth_corner_r": (-hw, my),
        "upper_lip": (0.0, my + 1.1 * lt),
        "lower_lip": (0.0, my - 1.2 * lt),
        "upper_lid_l": (ex, ey + 0.55 * er),
        "upper_lid_r": (-ex, ey + 0.55 * er),
        "lower_lid_l": (ex, ey - 0.6 * er),
        "lower_lid_r": (-ex, ey - 0.6 * er),
        "brow_inner_l": (0.4 * ex, by),
        "brow_inner_r": (-0.4 * ex, by),
        "brow_outer_l": (1.3 * ex, by - 0.2),
        "brow_outer_r": (-1.3 * ex, by - 0.2),
        "forehead_l": (0.6 * ex, by + 2.2),
        "forehead_r": (-0.6 * ex, by + 2.2),
        "chin": (0.0, head.chin[0]),
        "jaw_l": (hw + 1.3, (my + head.chin[0]) / 2 - 0.6),
        "cheek_l": (head.cheek[0], head.cheek[1]),
        "cheek_r": (-head.cheek[0], head.cheek[1]),
        "nose_tip": (0.0, head.nose[0]),
        "nose_wing_l": (0.9, head.nose[0] - 0.3),
        "nose_wing_r": (-0.9, head.nose[0] - 0.3),
    }
    return {name: _surface_point(head, x, y) for name, (x, y) in marks.items()}


@dataclass(frozen=True, eq=False)
class _Model:
    """A character's neutral mesh plus everything its controls need, computed once."""

    head: _Head
    neutral: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    fields: np.ndarray  # (C, V*3) linear displacement per unit control
    jaw_weight: np.ndarray  # (V,)
    cavity: np.ndarray  # (V,) depth of the mouth opening per unit jaw
    eye_index: np.ndarray  # (E,) vertices near the eyes, moved by the lids
    landmarks: dict


def _neutral_mesh(head: _Head, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) neutral vertices and (V,) how much of each vertex is ear (0 to 1)."""
    rx, ry, rz = head.radii
    base = dirs * np.array([rx, ry, rz])
    base[:, 0] *= _narrowing(head, base[:, 1])
    x, y, z = base.T
    base[:, 2] += _front_mask(head, z) * _front_height(head, x, y)
    if head.ears:
        # Round ears on the sides, slightly behind the middle of the head.
        ear = _g(y, z, 0.9, -0.8, 0.45 * head.ears, 0.5 * head.ears) ** 2
        side = _smooth((np.abs(x) / rx - 0.55) / 0.3)
        base[:, 0] += np.sign(x) * head.ears * 1.1 * ear * side
        return base, ear * side
    return base, np.zeros(len(base))


def _control_fields(head: _Head, neutral: np.ndarray, ear: np.ndarray) -> np.ndarray:
    """(C, V, 3) displacement of each linear control at strength 1."""
    x, y, _ = neutral.T
    ex, ey, er = head.eye
    by = head.brow[0]
    my, hw, lt = head.mouth
    front = _front_mask(head, _ellipsoid_z(head, x, y))
    fields = np.zeros((len(_CONTROLS), len(x), 3))

    def add(control: str, weight, vector) -> None:
        fields[_C[control]] += (weight * front)[:, None] * np.asarray(vector, float)

    sc = 0.5 * hw + 0.2  # reach of a mouth corner's pull
    for s in (-1.0, 1.0):
        corner = _g(x, y, s * hw, my, sc, sc * 0.9)
        add("smile", corner, [s * 0.45, 0.95, -0.3])
        add("smile", _g(x, y, s * (hw + 0.6), my + 1.6, 1.5, 1.3), [s * 0.1, 0.4, 0.3])
        add("frown", corner, [s * 0.1, -0.75, -0.05])
        add("stretch", corner, [s * 0.8, -0.2, -0.3])
        add("pucker", corner, [-s * 0.75, 0.0, 0.3])
        add("lip_raise", _g(x, y, s * 0.45 * hw, my + lt, 0.7, 0.6), [0.0, 0.4, 0.15])
        add("lip_raise", _g(x, y, s * (hw * 0.6 + 0.5), my + 2.0, 0.9, 1.0), [0.0, 0.25, 0.2])
        add("wrinkle", _g(x, y, s * 0.9, head.nose[0] - 0.2, 0.7, 0.8), [0.0, 0.35, 0.1])
        add("wrinkle", _g(x, y, s * 1.2, ey - 0.3 * er, 0.6, 0.6), [s * -0.05, 0.1, 0.15])
        add("brow_in_up", _g(x, y, s * 0.45 * ex, by, 1.1, 0.9), [s * -0.05, 0.75, 0.05])
        add("brow_out_up", _g(x, y, s * 1.25 * ex, by - 0.2, 1.4, 1.0), [0.0, 0.7, 0.0])
        add("brow_down", _g(x, y, s * 0.45 * ex, by, 1.1, 0.9), [-s * 0.3, -0.6, 0.2])
        add("brow_down", _g(x, y, s * 1.25 * ex, by - 0.2, 1.2, 0.9), [0.0, -0.2, 0.0])
        add("squint", _g(x, y, s * ex, ey - 1.1 * er, 0.9 * er, 0.5 * er), [0.0, 0.25, 0.15])
        add("cheek", _g(x, y, s * head.cheek[0], head.cheek[1], 1.4, 1.3), [s * 0.05, 0.35, 0.35])
    lips_region = _g(x, y, 0.0, my, hw * 0.8, 1.2 * lt + 0.6)
    upper_lip = _g(x, y, 0.0, my + lt, hw * 0.75, 0.55)
    lower_lip = _g(x, y, 0.0, my - 1.1 * lt, hw * 0.75, 0.55)
    chin = _g(x, y, 0.0, head.chin[0] + 0.6, 1.6, 1.2)
    add("frown", lower_lip, [0.0, 0.15, 0.3])
    add("frown", chin, [0.0, 0.25, 0.15])
    add("pucker", lips_region, [0.0, 0.0, 0.75])
    add("pucker", upper_lip, [0.0, 0.12, 0.0])
    add("pucker", lower_lip, [0.0, -0.12, 0.0])
    add("stretch", lips_region, [0.0, 0.0, -0.15])
    add("press", upper_lip, [0.0, -0.18, -0.2])
    add("press", lower_lip, [0.0, 0.2, -0.2])
    fields[_C["press"], :, 2] -= 0.8 * front * np.clip(_lips(head, x, y), 0.0, None)
    add("press", chin, [0.0, 0.2, 0.12])
    add("bite", lower_lip, [0.0, 0.45, -0.55])
    add("bite", upper_lip, [0.0, 0.1, 0.1])
    add("brow_down", _g(x, y, 0.0, by - 0.1, 0.35, 0.9), [0.0, 0.0, -0.25])
    add("brow_in_up", _g(x, y, 0.0, by + 2.5, 3.0, 1.8), [0.0, 0.25, 0.0])
    add("brow_out_up", _g(x, y, 0.0, by + 2.5, 3.5, 1.8), [0.0, 0.25, 0.0])
    fields[_C["ears"]] += ear[:, None] * np.array([0.0, 1.3, 0.9])
    return fields * head.gain


def _jaw_weight(head: _Head, neutral: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V,) share of the jaw's rotation, and (V,) depth of the mouth opening per unit jaw."""
    x, y, z = neutral.T
    my, hw, _ = head.mouth
    # A sharp split along the mouth line between the corners, a soft one beyond them.
    beyond = _smooth((np.abs(x) - 0.85 * hw) / (0.4 * hw + 2.0))
    width = 0.75 * head.groove + 2.5 * beyond
    below = _smooth((my - y) / (2.0 * width) + 0.5)
    behind = _smooth((z / head.radii[2] + 0.1) / 0.5)
    cavity = np.exp(-(((y - my) / (2.0 * head.groove)) ** 2)) * _lip_envelope(head, x, 0.95)
    return below * behind, cavity * 3.0 * head.gain


def _eye_region(head: _Head, neutral: np.ndarray) -> np.ndarray:
    ex, ey, er = head.eye
    x, y, z = neutral.T
    near = (np.abs(np.abs(x) - ex) < 1.5 * er) & (np.abs(y - ey) < 1.55 * er)
    return np.flatnonzero(near & (z > 0))


@functools.cache
def _model(character: str) -> _Model:
    if character == "source":
        head, (dirs, faces) = _HUMAN, _uv_sphere(96, 72)
    else:
        head, (dirs, faces) = _CARTOON, _icosphere(5)
    neutral, ear = _neutral_mesh(head, dirs)
    marks = _landmarks(head)
    fields = _control_fields(head, neutral, ear)
    jaw_weight, cavity = _jaw_weight(head, neutral)
    for array in (neutral, faces, fields, jaw_weight, cavity):
        array.flags.writeable = False
    return _Model(
        head=head,
        neutral=neutral,
        faces=faces,
        fields=fields.reshape(len(_CONTROLS), -1),
        jaw_weight=jaw_weight,
        cavity=cavity,
        eye_index=_eye_region(head, neutral),
        landmarks=marks,
    )


def _lid_margins(head: _Head, lid, squint):
    """Upper and lower lid margins, in eye radii from the eye centre, per frame."""
    lid = np.asarray(lid, float)
    upper = 0.55 + head.lid_travel * np.clip(lid, 0.0, 1.6) + 1.1 * np.clip(lid, -1.2, 0.0)
    lower = -0.55 + 0.3 * np.clip(squint, 0.0, 1.2)
    # Closed lids meet, they do not cross; a smooth maximum keeps the lid's motion C1.
    upper = (upper + lower + np.sqrt((upper - lower) ** 2 + 0.15**2)) / 2.0
    return upper, lower


def _pose(model: _Model, controls: np.ndarray) -> np.ndarray:
    """(T, V, 3) float64 vertices for (T, C) control values."""
    head, neutral = model.head, model.neutral
    t_count, v_count = controls.shape[0], neutral.shape[0]
    out = (controls @ model.fields).reshape(t_count, v_count, 3)
    out += neutral
    # The jaw turns about a hinge in front of the ears; the lips part into a cavity.
    jaw = np.clip(controls[:, _C["jaw"]], -0.2, 1.6)
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
    upper, lower = _lid_margins(head, controls[:, _C["lid"]], controls[:, _C["squint"]])
    upper, lower = upper[:, None], lower[:, None]
    yr = (y - ey) / er
    curve = np.maximum(_eye_curve(head, x), 0.05)
    upper0, lower0, upper, lower = upper0 * curve, lower0 * curve, upper * curve, lower * curve
    top = 1.5
    above = yr >= upper0
    mapped_above = top - (top - yr) * (top - upper) / (top - upper0)
    mapped_between = lower + (yr - lower0) * (upper - lower) / (upper0 - lower0)
    mapped_below = -top + (yr + top) * (lower + top) / (lower0 + top)
    mapped = np.where(above, mapped_above, np.where(yr >= lower0, mapped_between, mapped_below))
    mapped = np.where(np.abs(yr) <= top, mapped, yr)
    reach = _smooth((1.45 - np.abs(np.abs(x) - ex) / er) / 0.35)
    new_y = y + reach * (mapped - yr) * er
    z_old = _front_height(head, x, y, upper0 / curve, lower0 / curve)
    z_new = _front_height(head, x, new_y, upper / curve, lower / curve)
    base = _ellipsoid_z(head, x, new_y) - _ellipsoid_z(head, x, y)
    front = _front_mask(head, _ellipsoid_z(head, x, y))
    out[:, idx, 1] += new_y - y
    out[:, idx, 2] += base + front * (z_new - z_old)
    return out


def _controls_of(poses: dict[str, dict[str, float]]) -> np.ndarray:
    """(M, C) control values of each example, row 0 the neutral."""
    table = np.zeros((len(DEMO_NAMES), len(_CONTROLS)))
    for m, name in enumerate(DEMO_NAMES[1:], start=1):
        for control, value in poses[name].items():
            table[m, _C[control]] = value
    return table


# -- public API -------------------------------------------------------------------------
def demo_landmarks(character: str = "source") -> dict[str, np.ndarray]:
    """Named semantic landmarks (3,) float64 on the neutral of "source" or "target"."""
    if character not in ("source", "target"):
        raise InputError(
            f"character must be 'source' or 'target', got {character!r}", code="bad_demo_argument"
        )
    return {k: v.copy() for k, v in _model(character).landmarks.items()}


@functools.cache
def _feature_indices() -> np.ndarray:
    model = _model("source")
    marks = model.landmarks
    wanted = np.stack([marks[name] for name in DEMO_FEATURE_NAMES])
    distance = np.linalg.norm(model.neutral[None, :, :] - wanted[:, None, :], axis=2)
    indices = distance.argmin(axis=1)
    indices.flags.writeable = False
    return indices


def demo_example_set() -> ExampleSet:
    """The demo's paired examples: neutral + 6 emotions + 5 visemes + blink (13).

    Returns
    -------
    ExampleSet
        ``source_points`` (13, 21, 3), ``source_vertices`` (13, Vs, 3) with ``source_faces``,
        ``feature_indices`` (21,), ``target_vertices`` (13, V, 3) and ``target_faces``;
        the source and target meshes differ in vertex count and topology.
    """
    source, target = _model("source"), _model("target")
    source_vertices = _pose(source, _controls_of(_SOURCE_POSES))
    target_vertices = _pose(target, _controls_of(_TARGET_POSES))
    return ExampleSet.from_source_meshes(
        DEMO_NAMES,
        source_vertices,
        _feature_indices().copy(),
        target_vertices,
        target.faces.copy(),
        source_faces=source.faces.copy(),
    )


def _frame_count(seconds: float, fps: float, limit: int) -> int:
    try:
        seconds, fps = float(seconds), float(fps)
    except (TypeError, ValueError):
        raise InputError(
            f"seconds and fps must be numbers, got {seconds!r}, {fps!r}", code="bad_demo_argument"
        ) from None
    if not (math.isfinite(seconds) and seconds > 0 and math.isfinite(fps) and fps > 0):
        raise InputError(
            f"seconds and fps must be finite and positive, got {seconds}, {fps}",
            code="bad_demo_argument",
        )
    frames = round(seconds * fps)
    if not 1 <= frames <= limit:
        raise InputError(
            f"{seconds} s at {fps} fps is {frames} frames; allowed 1 to {limit}",
            code="too_many_frames",
        )
    return frames


def _bump(t: np.ndarray, start: float, end: float, attack: float, release: float) -> np.ndarray:
    """0 -> 1 -> 0 with raised-cosine ramps (C1 smooth), 1 on [start, end]."""
    rise = np.clip((t - (start - attack)) / attack, 0.0, 1.0)
    fall = np.clip(((end + release) - t) / release, 0.0, 1.0)
    return (0.5 - 0.5 * np.cos(np.pi * rise)) * (0.5 - 0.5 * np.cos(np.pi * fall))


def demo_activations(seconds: float = 12.0, fps: float = 60.0, *, seed: int = 7) -> np.ndarray:
    """Activation curves of the demo performance, one column per example.

    Emotions come and go over ~2 s with cross-fades and occasional blends, peaks up to
    1.15; speech-like bursts of visemes (one every ~0.17 s, overlapping) run over them;
    blinks every few seconds; everything is scaled by a slow seeded wobble.

    Returns
    -------
    (F, M) float64
        ``F = round(seconds * fps)`` frames; columns follow ``DEMO_NAMES`` (column 0, the
        neutral, is zero); frame ``i`` is at ``i / fps`` seconds.
    """
    frames = _frame_count(seconds, fps, _MAX_FRAMES)
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / float(fps)
    total = frames / float(fps)
    col = {name: i for i, name in enumerate(DEMO_NAMES)}
    act = np.zeros((frames, len(DEMO_NAMES)))

    order = ["happy", "surprise", "sad", "anger", "fear", "disgust"]
    start = 0.5
    k = 0
    while start < total:
        name = order[k % len(order)]
        hold = rng.uniform(0.9, 1.7)
        peak = rng.uniform(0.6, 1.15)
        act[:, col[name]] += peak * _bump(t, start, start + hold, 0.5, 0.6)
        if rng.random() < 0.4:  # blend in a second emotion for part of the segment
            other = order[(k + rng.integers(1, len(order))) % len(order)]
            act[:, col[other]] += rng.uniform(0.25, 0.5) * _bump(
                t, start + 0.3 * hold, start + 0.8 * hold, 0.4, 0.4
            )
        start += hold + rng.uniform(0.7, 1.2)
        k += 1

    visemes = list(DEMO_VISEMES)
    start = 0.8
    while start < total:
        length = rng.uniform(1.2, 2.6)
        s = start
        while s < min(start + length, total):
            step = rng.uniform(0.13, 0.22)
            name = visemes[rng.integers(len(visemes))]
            act[:, col[name]] += rng.uniform(0.35, 0.9) * _bump(t, s, s + 0.02, step, step)
            s += step
        start += length + rng.uniform(0.4, 1.0)

    start = rng.uniform(0.8, 1.8)
    while start < total:
        act[:, col["blink"]] += rng.choice([1.0, 1.0, 0.85]) * _bump(t, start, start, 0.09, 0.13)
        start += rng.uniform(2.2, 4.2)

    wobble = np.zeros_like(act)
    for _ in range(3):
        freq = rng.uniform(0.1, 0.6, size=len(DEMO_NAMES))
        phase = rng.uniform(0.0, 2 * np.pi, size=len(DEMO_NAMES))
        wobble += np.sin(2 * np.pi * freq * t[:, None] + phase)
    act *= 1.0 + 0.03 * wobble
    # Overlapping bumps may stack up: saturate softly (C1) above 1, at most 1.25.
    over = np.clip(act - 1.0, 0.0, None)
    act = np.minimum(act, 1.0) + 0.25 * np.tanh(over / 0.25)
    act[:, 0] = 0.0
    return act


def _sanitize_activations(activations) -> np.ndarray:
    try:
        act = np.asarray(activations, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(
            f"activations: not a numeric array ({exc})", code="bad_activations"
        ) from None
    if act.ndim == 1:
        act = act[None, :]
    if act.ndim != 2 or act.shape[1] != len(DEMO_NAMES):
        raise InputError(
            f"activations: expected shape (F, {len(DEMO_NAMES)}), got {act.shape}",
            code="bad_activations",
        )
    if act.shape[0] > _MAX_VERTEX_FRAMES:
        raise InputError(
            f"activations: at most {_MAX_VERTEX_FRAMES} frames at once, got {act.shape[0]}",
            code="too_many_frames",
        )
    if not np.isfinite(act).all():
        raise InputError("activations: NaN or Inf values", code="non_finite")
    return act


def _source_frames(activations: np.ndarray) -> np.ndarray:
    return _pose(_model("source"), activations @ _controls_of(_SOURCE_POSES))


def demo_target_frames(activations) -> np.ndarray:
    """The ideal clone: the target's own expressions driven by ``activations``.

    Parameters
    ----------
    activations : (F, M) float
        As returned by ``demo_activations`` (columns follow ``DEMO_NAMES``).

    Returns
    -------
    (F, V, 3) float32
        Target vertices per frame (the same frames as the source animation).
    """
    act = _sanitize_activations(activations)
    return _pose(_model("target"), act @ _controls_of(_TARGET_POSES)).astype(np.float32)


def demo_animation(
    seconds: float = 12.0, fps: float = 60.0, *, with_vertices: bool = True, seed: int = 7
) -> SourceAnimation:
    """The demo performance on the source face, at the demo's feature points.

    Parameters
    ----------
    seconds, fps : float
        Length and frame rate; frames are at ``i / fps``.
    with_vertices : bool
        Also return the full source meshes per frame (at most 4000 frames).
    seed : int
        Seed of the performance (the same seed gives the same frames).

    Returns
    -------
    SourceAnimation
        ``points`` (F, 21, 3) float64 and, with ``with_vertices``, ``source_vertices``
        (F, Vs, 3) float32; driven by ``demo_activations(seconds, fps, seed=seed)``.
    """
    _frame_count(seconds, fps, _MAX_VERTEX_FRAMES if with_vertices else _MAX_FRAMES)
    act = demo_activations(seconds, fps, seed=seed)
    controls = act @ _controls_of(_SOURCE_POSES)
    model = _model("source")
    indices = _feature_indices()
    if with_vertices:
        vertices = _pose(model, controls)
        return SourceAnimation(
            points=vertices[:, indices, :],
            fps=float(fps),
            source_vertices=vertices.astype(np.float32),
        )
    # Points only: pose just the feature vertices' neighbourhood, in chunks.
    points = np.empty((act.shape[0], len(indices), 3))
    for lo in range(0, act.shape[0], 1000):
        points[lo : lo + 1000] = _pose(model, controls[lo : lo + 1000])[:, indices, :]
    return SourceAnimation(points=points, fps=float(fps))
