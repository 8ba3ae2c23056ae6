"""A small software renderer for pictures of meshes: flat Lambert shading, a z-buffer.

numpy (``facecast.cli.raster``, the one rasteriser) and matplotlib's Agg canvas for the
labelled grids (no OpenGL, no pyplot global state), for reports, thumbnails and
side-by-side comparisons; it must not be used for anything real-time.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from facecast.cli.errors import RenderError
from facecast.cli.raster import lambert, rasterise

__all__ = ["VIEWS", "RenderError", "render_mesh", "save_side_by_side"]

#: Names accepted by ``render_mesh(view=...)``.
VIEWS = ("front", "three_quarter", "side")

# Light from the upper left, in front of the face (+z towards the viewer); fixed so that
# pictures of different meshes compare.
_LIGHT = np.array([-0.35, 0.45, 1.0]) / np.linalg.norm([-0.35, 0.45, 1.0])
_AMBIENT = 0.22
_DIFFUSE = 0.78
_MAX_PIXELS = 8192

#: ``(label, vertices (V, 3), faces (F, 3)[, color])``, checked when drawn (``bad_panel``).
Panel = tuple[Any, ...]
_SUPERSAMPLE = 2
_DPI = 100.0


def _view_rotation(view: str) -> np.ndarray:
    """(3, 3) rotation taking model coordinates (y up, +z to the viewer) to camera ones."""
    if view not in VIEWS:
        raise RenderError(f"view must be one of {VIEWS}, got {view!r}", code="bad_view")
    yaw = {"front": 0.0, "three_quarter": 35.0, "side": 90.0}[view]
    pitch = 0.0 if view == "front" else 8.0
    a, b = math.radians(yaw), math.radians(pitch)
    about_y = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    about_x = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    rotation: np.ndarray = about_x @ about_y
    return rotation


def _sanitize_mesh(vertices: npt.ArrayLike, faces: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    try:
        verts = np.asarray(vertices, dtype=np.float64)
        tris = np.asarray(faces)
    except (TypeError, ValueError) as exc:
        raise RenderError(f"vertices/faces: not numeric arrays ({exc})") from None
    if verts.ndim != 2 or verts.shape[1] != 3 or verts.shape[0] == 0:
        raise RenderError(f"vertices: expected shape (V, 3) with V > 0, got {verts.shape}")
    if not np.isfinite(verts).all():
        raise RenderError("vertices: NaN or Inf coordinates", code="non_finite")
    if tris.ndim != 2 or tris.shape[1] != 3:
        raise RenderError(f"faces: expected shape (F, 3), got {tris.shape}")
    if tris.size and not np.issubdtype(tris.dtype, np.integer):
        raise RenderError(f"faces: expected integer indices, got dtype {tris.dtype}")
    tris = tris.astype(np.int64, copy=False)
    if tris.size and (tris.min() < 0 or tris.max() >= verts.shape[0]):
        raise RenderError(
            f"faces: indices must lie in [0, {verts.shape[0]}), got [{tris.min()}, {tris.max()}]",
            code="index_out_of_range",
        )
    return verts, tris


def _sanitize_color(name: str, value: npt.ArrayLike) -> np.ndarray:
    try:
        rgb = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise RenderError(
            f"{name}: expected 3 numbers (r, g, b), got {value!r}", code="bad_color"
        ) from None
    if rgb.shape != (3,) or not np.isfinite(rgb).all():
        raise RenderError(f"{name}: expected 3 numbers (r, g, b), got {value!r}", code="bad_color")
    if rgb.max() > 1.0:  # 0-255 colours are accepted too
        rgb = rgb / 255.0
    return np.clip(rgb, 0.0, 1.0)


def _sanitize_size(size: Sequence[int]) -> tuple[int, int]:
    try:
        width, height = (int(s) for s in size)
    except (TypeError, ValueError):
        raise RenderError(
            f"size: expected (width, height), got {size!r}", code="bad_size"
        ) from None
    if not (1 <= width <= _MAX_PIXELS and 1 <= height <= _MAX_PIXELS):
        raise RenderError(
            f"size: width and height must lie in [1, {_MAX_PIXELS}], got {size!r}", code="bad_size"
        )
    return width, height


def render_mesh(
    vertices: npt.ArrayLike,
    faces: npt.ArrayLike,
    *,
    size: tuple[int, int] = (480, 480),
    view: str = "front",
    color: npt.ArrayLike = (0.82, 0.72, 0.64),
    background: npt.ArrayLike = (1.0, 1.0, 1.0),
    frame_vertices: npt.ArrayLike | None = None,
    margin: float = 0.06,
) -> np.ndarray:
    """Render a triangle mesh to an RGB image.

    Orthographic camera on the +z axis looking down -z (y up), optionally turned by
    ``view``; triangles are shaded flat with a fixed light (two-sided, so the winding
    does not matter), the nearest one at each pixel drawn (a z-buffer, supersampled 2 x 2).

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
        0-based triangle indices.
    size : (width, height) int
    view : {"front", "three_quarter", "side"}
    color, background : (3,) float in [0, 1] (or 0-255)
    frame_vertices : (N, 3) float, optional
        Points whose bounding box sets the framing instead of ``vertices``; pass the
        neutral to keep the framing still across frames of an animation.
    margin : float
        Fraction of the image left empty around the framed box.

    Returns
    -------
    (height, width, 3) uint8
    """
    verts, tris = _sanitize_mesh(vertices, faces)
    width, height = _sanitize_size(size)
    rgb = _sanitize_color("color", color)
    bg = _sanitize_color("background", background)
    rotation = _view_rotation(view)
    camera = verts @ rotation.T
    if frame_vertices is None:
        # Frame what is drawn: vertices no triangle uses do not widen the picture.
        framed = camera[np.unique(tris)] if tris.size else camera
    else:
        framed_in, _ = _sanitize_mesh(frame_vertices, np.zeros((0, 3), np.int64))
        framed = framed_in @ rotation.T

    # Fit the framed box into the image keeping the aspect ratio.
    lo, hi = framed[:, :2].min(axis=0), framed[:, :2].max(axis=0)
    centre = (lo + hi) / 2.0
    extent = np.maximum(hi - lo, 1e-9) * (1.0 + 2.0 * margin)
    scale = min(width / extent[0], height / extent[1])
    half_w, half_h = width / (2.0 * scale), height / (2.0 * scale)

    # Supersampled, then averaged: the antialiasing of the picture's edges.
    big_w, big_h = width * _SUPERSAMPLE, height * _SUPERSAMPLE
    pixels = scale * _SUPERSAMPLE
    screen = np.empty_like(camera)
    screen[:, 0] = (camera[:, 0] - centre[0] + half_w) * pixels
    screen[:, 1] = (centre[1] + half_h - camera[:, 1]) * pixels
    screen[:, 2] = -camera[:, 2]  # nearer the viewer (+z) is smaller depth
    corners = camera[tris]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    keep = lengths > 0.0  # degenerate triangles have no area to draw
    normals = normals[keep] / lengths[keep, None]
    normals *= np.where(normals[:, 2] < 0.0, -1.0, 1.0)[:, None]  # two-sided
    brightness = lambert(normals, _LIGHT, ambient=_AMBIENT, diffuse=_DIFFUSE)
    shades = np.clip(brightness[:, None] * rgb, 0.0, 1.0)
    image = rasterise(screen, tris[keep], size=(big_w, big_h), background=bg, face_colors=shades)
    image = image.reshape(height, _SUPERSAMPLE, width, _SUPERSAMPLE, 3).mean(axis=(1, 3))
    out: np.ndarray = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return out


def _as_grid(rows: Sequence[Panel | Sequence[Panel]]) -> list[list[Panel]]:
    grid: list[list[Panel]] = []
    for row in rows:
        if isinstance(row, tuple) and row and isinstance(row[0], str):
            grid.append([row])
        else:
            grid.append(list(row))
    return grid


def save_side_by_side(
    path: str | os.PathLike[str],
    rows: Sequence[Panel] | Sequence[Sequence[Panel]],
    *,
    columns: int | None = None,
    panel_size: tuple[int, int] = (320, 320),
    view: str = "front",
    color: npt.ArrayLike = (0.82, 0.72, 0.64),
    title: str | None = None,
    frame_by_panel: bool = True,
) -> Path:
    """Write a PNG grid of rendered meshes with a label above each panel.

    Parameters
    ----------
    path : str or Path
        Where to write the PNG.
    rows : sequence
        Either panels ``(label, vertices (V, 3), faces (F, 3))`` — optionally with a
        fourth element, the panel's colour — laid out ``columns`` to a row (all in one
        row by default), or a sequence of rows, each a sequence of such panels.
    columns : int, optional
        Panels per row when ``rows`` is a flat list of panels.
    panel_size : (width, height) int
        Pixels of each rendered panel (the label adds 28 pixels above it).
    frame_by_panel : bool
        True frames each panel on its own mesh; False frames all panels of a column
        on the first row's mesh, so motion within a column shows.

    Returns
    -------
    Path
        The written file; the image is ``rows * (height + 28) (+ 36 with a title)``
        pixels high and ``columns * width`` pixels wide.
    """
    items: list[Panel | Sequence[Panel]] = list(rows)
    if not items:
        raise RenderError("rows: need at least one panel", code="empty_grid")
    flat = all(isinstance(item, tuple) and item and isinstance(item[0], str) for item in items)
    if flat:
        per_row = len(items) if columns is None else int(columns)
        if per_row < 1:
            raise RenderError(f"columns must be at least 1, got {columns!r}", code="bad_size")
        grid: list[list[Panel]] = [
            [cast(Panel, item) for item in items[i : i + per_row]]
            for i in range(0, len(items), per_row)
        ]
    else:
        grid = _as_grid(items)
    n_cols = max(len(row) for row in grid)
    width, height = _sanitize_size(panel_size)
    label_px, title_px = 28, (36 if title else 0)
    total_w, total_h = n_cols * width, len(grid) * (height + label_px) + title_px

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(total_w / _DPI, total_h / _DPI), dpi=_DPI, facecolor="white")
    canvas = FigureCanvasAgg(figure)
    if title:
        figure.text(
            0.5,
            1.0 - (title_px / 2) / total_h,
            title,
            ha="center",
            va="center",
            fontsize=14,
            weight="bold",
        )
    for r, row in enumerate(grid):
        for c, panel in enumerate(row):
            if not isinstance(panel, tuple) or len(panel) not in (3, 4):
                raise RenderError(
                    f"panel ({r}, {c}): expected (label, vertices, faces[, color])",
                    code="bad_panel",
                )
            label, vertices, faces = panel[:3]
            panel_color = panel[3] if len(panel) == 4 else color
            framing = None if frame_by_panel or r == 0 else grid[0][min(c, len(grid[0]) - 1)][1]
            image = render_mesh(
                vertices,
                faces,
                size=(width, height),
                view=view,
                color=panel_color,
                frame_vertices=framing,
            )
            top = title_px + r * (height + label_px)
            axes = figure.add_axes(
                (
                    c * width / total_w,
                    1.0 - (top + label_px + height) / total_h,
                    width / total_w,
                    height / total_h,
                )
            )
            axes.imshow(image, interpolation="nearest")
            axes.set_axis_off()
            figure.text(
                (c + 0.5) * width / total_w,
                1.0 - (top + label_px / 2) / total_h,
                str(label),
                ha="center",
                va="center",
                fontsize=11,
            )
    out = Path(path)
    canvas.print_png(str(out))  # type: ignore[no-untyped-call]  # matplotlib leaves it unannotated
    figure.clear()
    return out
