"""Neutral geometry of the demo's two heads: proportions, sphere meshes, surface formulas.

Pure seeded formulas in a face-local frame (y up, +z out of the face, cm); it knows
nothing of expressions or controls (see ``controls``) and must not read files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "CARTOON",
    "HUMAN",
    "Head",
    "ellipsoid_z",
    "eye_curve",
    "front_height",
    "front_mask",
    "gauss",
    "head_landmarks",
    "icosphere",
    "lip_envelope",
    "lip_height",
    "neutral_mesh",
    "smoothstep",
    "uv_sphere",
]


@dataclass(frozen=True)
class Head:
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


# The source (a human-ish face) and the target (a cartoon with big eyes and ears).
HUMAN = Head(
    radii=(7.3, 10.2, 8.6), narrow=0.3, eye=(3.1, 1.4, 1.15), eye_bulge=0.9, socket=1.5,
    brow=(3.15, 0.7, 0.65), nose=(-1.9, 2.1), mouth=(-4.6, 2.5, 0.5), lips=0.6,
    muzzle=(-4.0, 2.6, 2.4, 0.9), cheek=(3.4, -1.8, 0.55), chin=(-7.6, 0.7), ears=0.0,
    jaw_angle=0.24, gain=1.0,
)  # fmt: skip
CARTOON = Head(
    radii=(8.2, 8.8, 8.0), narrow=0.12, eye=(2.9, 1.9, 1.9), eye_bulge=1.2, socket=1.0,
    brow=(4.35, 0.8, 0.5), nose=(-1.4, 0.9), mouth=(-4.0, 3.4, 0.4), lips=0.3,
    muzzle=(-3.4, 3.4, 2.6, 2.3), cheek=(4.3, -1.2, 0.5), chin=(-6.9, 0.4), ears=2.6,
    jaw_angle=0.22, gain=1.25, lid_travel=0.45, groove=0.3,
)  # fmt: skip


# -- meshes ------------------------------------------------------------------------------
def _warped_angles(
    count: int, lo: float, hi: float, peak: float, width: float, boost: float
) -> np.ndarray:
    """``count`` angles in [lo, hi], denser (by 1 + boost) around ``peak``."""
    fine = np.linspace(lo, hi, 4096)
    density = 1.0 + boost * np.exp(-(((fine - peak) / width) ** 2))
    cumulative = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2)])
    return np.interp(np.linspace(0.0, cumulative[-1], count), cumulative, fine)


def uv_sphere(n_lon: int, n_lat: int) -> tuple[np.ndarray, np.ndarray]:
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


def icosphere(levels: int) -> tuple[np.ndarray, np.ndarray]:
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
#: float64 coordinates and fields over them.
F64 = npt.NDArray[np.float64]
#: A lid margin in eye radii: one for every vertex, or per frame and vertex (T, E).
Margin = F64 | float


def gauss(x: F64, y: F64, cx: float, cy: float, sx: float, sy: float) -> F64:
    """Axis-aligned Gaussian bump at (cx, cy) with widths (sx, sy); 1 at its centre."""
    return np.exp(-(((x - cx) / sx) ** 2) - ((y - cy) / sy) ** 2)


def smoothstep(t: F64) -> F64:
    """0 below 0, 1 above 1, and the C1 cubic ``3t² - 2t³`` in between."""
    c: F64 = np.clip(t, 0.0, 1.0)
    return c * c * (3.0 - 2.0 * c)


def _narrowing(head: Head, y: F64) -> F64:
    return 1.0 - head.narrow * smoothstep(-y / head.radii[1])


def lip_envelope(head: Head, x: F64, extra: float = 1.0) -> F64:
    """Across the mouth: 1 at the middle, 0 beyond ``extra`` mouth half-widths."""
    hw = head.mouth[1] * extra
    return np.clip(1.0 - (x / hw) ** 2, 0.0, 1.0) ** 0.6


def lip_height(head: Head, x: F64, y: F64) -> F64:
    """Height of the lips and the mouth line (a groove) around the mouth."""
    my, _, lt = head.mouth
    env = lip_envelope(head, x)
    upper = np.exp(-(((y - my - 1.1 * lt) / (0.95 * lt)) ** 2))
    lower = np.exp(-(((y - my + 1.2 * lt) / (1.05 * lt)) ** 2))
    groove = np.exp(-(((y - my) / head.groove) ** 2)) * lip_envelope(head, x, 1.06)
    return head.lips * env * (upper + 1.1 * lower) - 0.35 * groove


def eye_curve(head: Head, x: F64) -> F64:
    """(…) factor in [0, 1] shaping lid margins into an almond: 1 mid-eye, 0 at the corners."""
    ex, _, er = head.eye
    xr = (np.abs(x) - ex) / (1.2 * er)
    curve: F64 = np.clip(1.0 - xr**2, 0.0, 1.0)
    return curve


def _eye_height(head: Head, x: F64, y: F64, upper: Margin, lower: Margin) -> F64:
    """Eyeball with sliding lids; ``upper``/``lower`` are the lid margins in eye radii."""
    ex, ey, er = head.eye
    r2 = ((np.abs(x) - ex) ** 2 + (y - ey) ** 2) / er**2
    ball = head.eye_bulge * np.exp(-r2 / 1.1)
    yr = (y - ey) / er
    curve = eye_curve(head, x)
    cover = np.maximum(
        smoothstep((yr - upper * curve) / 0.4 + 0.5), smoothstep((lower * curve - yr) / 0.4 + 0.5)
    )
    lid = 0.28 * er * cover * smoothstep((1.9 - np.sqrt(r2)) / 0.8)
    crease = -0.1 * er * np.exp(-(((yr - 1.0 - 0.3 * upper) / 0.15) ** 2)) * np.exp(-r2 / 1.5)
    return ball + lid + crease - head.socket * np.exp(-r2 / 1.8)


def front_height(head: Head, x: F64, y: F64, upper: Margin = 0.55, lower: Margin = -0.55) -> F64:
    """Height of the facial features above the ellipsoid, along +z, at (x, y)."""
    ex, ey, _ = head.eye
    by, bh, bt = head.brow
    ny, nh = head.nose
    muy, msx, msy, mh = head.muzzle
    cx, cy, ch = head.cheek
    chy, chh = head.chin
    h = mh * gauss(x, y, 0, muy, msx, msy) + chh * gauss(x, y, 0, chy, 1.6, 1.0)
    h = h + ch * (gauss(x, y, cx, cy, 1.6, 1.4) + gauss(x, y, -cx, cy, 1.6, 1.4))
    h = h + bh * (gauss(x, y, ex, by, 1.9, bt) + gauss(x, y, -ex, by, 1.9, bt))
    h = h + 0.5 * bh * gauss(x, y, 0, by - 0.3, 1.0, 0.8)
    # Nose: bridge from between the eyes to the tip, tip ball, wings, nostrils.
    bridge_len = max(ey - ny, 0.5)
    h = h + 0.45 * nh * gauss(x, y, 0, (ey + ny) / 2, 0.55, bridge_len * 0.6)
    h = h + 0.75 * nh * gauss(x, y, 0, ny, 0.75, 0.65)
    h = h + 0.4 * nh * (
        gauss(x, y, 0.9, ny - 0.3, 0.5, 0.45) + gauss(x, y, -0.9, ny - 0.3, 0.5, 0.45)
    )
    h = h - 0.12 * nh * (
        gauss(x, y, 0.45, ny - 0.7, 0.25, 0.2) + gauss(x, y, -0.45, ny - 0.7, 0.25, 0.2)
    )
    return h + lip_height(head, x, y) + _eye_height(head, x, y, upper, lower)


def ellipsoid_z(head: Head, x: F64, y: F64) -> F64:
    """Depth (+z) of the head's narrowed ellipsoid at (x, y), before any features."""
    rx, ry, rz = head.radii
    x0 = x / _narrowing(head, y)
    inside: F64 = np.clip(1.0 - (x0 / rx) ** 2 - (y / ry) ** 2, 0.0, None)
    return rz * np.sqrt(inside)


def front_mask(head: Head, base_z: F64) -> F64:
    """How much of the face (0 to 1) a point of ellipsoid depth ``base_z`` belongs to."""
    return smoothstep((base_z / head.radii[2] - 0.15) / 0.35)


def _surface_point(head: Head, x: float, y: float) -> np.ndarray:
    # 0-d arrays: the surface functions take arrays of points.
    xs, ys = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    z = ellipsoid_z(head, xs, ys)
    return np.array([x, y, z + front_mask(head, z) * front_height(head, xs, ys)])


def head_landmarks(head: Head) -> dict[str, np.ndarray]:
    """Named semantic points (3,) float64 on the neutral surface of ``head``."""
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


def neutral_mesh(head: Head, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) neutral vertices and (V,) how much of each vertex is ear (0 to 1)."""
    rx, ry, rz = head.radii
    base = dirs * np.array([rx, ry, rz])
    base[:, 0] *= _narrowing(head, base[:, 1])
    x, y, z = base.T
    base[:, 2] += front_mask(head, z) * front_height(head, x, y)
    if head.ears:
        # Round ears on the sides, slightly behind the middle of the head.
        ear = gauss(y, z, 0.9, -0.8, 0.45 * head.ears, 0.5 * head.ears) ** 2
        side = smoothstep((np.abs(x) / rx - 0.55) / 0.3)
        base[:, 0] += np.sign(x) * head.ears * 1.1 * ear * side
        return base, ear * side
    return base, np.zeros(len(base))
