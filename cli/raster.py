"""A z-buffer triangle rasteriser and a pinhole camera: numpy only, the renderer's one core.

``render_mesh`` (pictures) and the webcam benchmark's camera video both draw through
``rasterise``; a frame of ICT-FaceKit at 640 x 480 takes a fraction of a second, so it is
for offline pictures and test videos, never for anything real-time.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse

from facecast.cli.errors import RenderError

__all__ = ["PinholeCamera", "lambert", "normals_operator", "rasterise", "vertex_normals"]

# Candidate (triangle, pixel) pairs drawn at once: bounds the scratch arrays (~100 bytes a
# candidate) whatever the triangles' sizes; an ICT frame at 640 x 480 (~240k candidates) is
# four batches. Small enough that glibc keeps the batches' arrays in its heap: at 1 << 19 a
# batch's arrays were mapped anew and faulted in each frame (the eyes rig's 74 frames: 0.9M
# page faults, 2.6 s of system time; 35k and 0.3 s at 1 << 16, measured 2026-12-05).
_BATCH_PIXELS = 1 << 16
# No candidate at a pixel (yet): above every candidate's index in a batch.
_NO_CANDIDATE = np.iinfo(np.int64).max


@dataclass(frozen=True)
class PinholeCamera:
    """A camera at ``position`` looking down -z, y up (the ICT-FaceKit convention).

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    focal : float
        Focal length in pixels (about 0.9 x the width for a webcam's 60 degree field).
    position : (3,) float
        Where the camera is, in the mesh's units.
    """

    width: int
    height: int
    focal: float
    position: tuple[float, float, float]

    def project(self, vertices: npt.ArrayLike) -> np.ndarray:
        """(V, 3) world points -> (V, 3) screen points: pixel x, pixel y (down), depth.

        Raises
        ------
        RenderError
            ``behind_camera`` when a vertex is not in front of the camera.
        """
        points = np.asarray(vertices, dtype=np.float64)
        relative = points - np.asarray(self.position, dtype=np.float64)
        depth = -relative[:, 2]
        if not (depth > 0).all():
            raise RenderError(
                f"{int((depth <= 0).sum())} vertices are not in front of the camera at "
                f"{self.position}: move it further out along +z",
                code="behind_camera",
            )
        screen = np.empty_like(points)
        screen[:, 0] = 0.5 * self.width + self.focal * relative[:, 0] / depth
        screen[:, 1] = 0.5 * self.height - self.focal * relative[:, 1] / depth
        screen[:, 2] = depth
        return screen


def normals_operator(faces: np.ndarray, num_vertices: int) -> scipy.sparse.csr_matrix:
    """(V, F) sparse: summing each vertex's triangles (``vertex_normals``'s fixed part)."""
    count = len(faces)
    return scipy.sparse.csr_matrix(
        (np.ones(3 * count), (faces.T.reshape(-1), np.tile(np.arange(count), 3))),
        shape=(num_vertices, count),
    )


def vertex_normals(
    vertices: np.ndarray, faces: np.ndarray, operator: scipy.sparse.csr_matrix | None = None
) -> np.ndarray:
    """(V, 3) unit normals: the area-weighted sum of each vertex's triangles' normals.

    ``operator`` is ``normals_operator(faces, V)``, made once for many frames of a mesh. A
    vertex no triangle uses gets (0, 0, 0).
    """
    corners = vertices[faces]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    if operator is None:
        operator = normals_operator(faces, len(vertices))
    normals: np.ndarray = np.asarray(operator @ face_normals, dtype=np.float64)
    lengths = np.linalg.norm(normals, axis=1, keepdims=True)
    np.divide(normals, lengths, out=normals, where=lengths > 0)
    return normals


def lambert(
    normals: np.ndarray, light: npt.ArrayLike, *, ambient: float, diffuse: float
) -> np.ndarray:
    """(N,) brightness ``ambient + diffuse * max(0, n . l)`` for unit normals (N, 3)."""
    direction = np.asarray(light, dtype=np.float64)
    direction = direction / np.linalg.norm(direction)
    shade: np.ndarray = ambient + diffuse * np.clip(normals @ direction, 0.0, None)
    return shade


def _corner_extremes(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) least and greatest of each row of ``values`` (N, 3)."""
    a, b, c = values[:, 0], values[:, 1], values[:, 2]
    return np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)


def _boxes(
    x: np.ndarray, y: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each triangle's first pixel column and row and its box's width and height (pixels
    whose centres, at i + 0.5, lie within the triangle's bounding box and the image)."""
    # The corners' least and greatest coordinates, pairwise: the same values as
    # x.min(axis=1), which reduces each row of 3 on its own (~4x slower on ICT's 51k).
    low_x, high_x = _corner_extremes(x)
    low_y, high_y = _corner_extremes(y)
    x0 = np.maximum(np.ceil(low_x - 0.5), 0)
    x1 = np.minimum(np.floor(high_x - 0.5), width - 1)
    y0 = np.maximum(np.ceil(low_y - 0.5), 0)
    y1 = np.minimum(np.floor(high_y - 0.5), height - 1)
    box_w = np.maximum(x1 - x0 + 1, 0).astype(np.int64)
    box_h = np.maximum(y1 - y0 + 1, 0).astype(np.int64)
    return x0.astype(np.int64), y0.astype(np.int64), box_w, box_h


def rasterise(
    screen: npt.ArrayLike,
    faces: npt.ArrayLike,
    *,
    size: tuple[int, int],
    background: npt.ArrayLike,
    vertex_colors: npt.ArrayLike | None = None,
    face_colors: npt.ArrayLike | None = None,
    cull: npt.ArrayLike | None = None,
) -> np.ndarray:
    """Draw triangles with a z-buffer: the nearest triangle at each pixel centre wins.

    Parameters
    ----------
    screen : (V, 3) float
        Pixel x, pixel y (down) and depth (smaller is nearer) of each vertex.
    faces : (F, 3) int
    size : (width, height)
    background : (3,) float
    vertex_colors : (V, 3) float, optional
        Colours interpolated across each triangle (Gouraud).
    face_colors : (F, 3) float, optional
        One colour per triangle (flat); exactly one of the two colour arguments.
    cull : (F,) bool, optional
        Triangles drawn only where they face the camera (counter-clockwise as seen, y up:
        the outward side of a mesh whose normals point out); the others are two-sided.

    Returns
    -------
    (height, width, 3) float64
        Colours at each pixel centre; ``background`` where no triangle is.
    """
    if (vertex_colors is None) == (face_colors is None):
        raise RenderError("give exactly one of vertex_colors and face_colors")
    width, height = size
    points = np.asarray(screen, dtype=np.float64)
    tris = np.asarray(faces, dtype=np.int64)
    image = np.empty((height * width, 3))
    image[:] = np.asarray(background, dtype=np.float64)
    if tris.size == 0:
        return image.reshape(height, width, 3)
    corners = points[tris]
    x, y = corners[..., 0], corners[..., 1]
    # Twice the signed area in pixel space (y down): negative when counter-clockwise in y up.
    area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    x0, y0, box_w, box_h = _boxes(x, y, width, height)
    drawn = (box_w > 0) & (box_h > 0) & (area != 0)
    if cull is not None:
        drawn &= ~(np.asarray(cull, dtype=bool) & (area > 0))
    which = np.nonzero(drawn)[0]
    # Each box as strips of at most _BATCH_PIXELS pixels (a big triangle's box is cut into
    # rows), the strips drawn in batches of about _BATCH_PIXELS candidates: bounded memory
    # whatever the triangles' sizes.
    strip_rows = np.maximum(1, _BATCH_PIXELS // box_w[which])
    strips = -(-box_h[which] // strip_rows)
    tri = np.repeat(which, strips)
    first_strip = np.repeat(np.cumsum(strips) - strips, strips)
    rows = np.repeat(strip_rows, strips)
    strip_y0 = y0[tri] + (np.arange(tri.size) - first_strip) * rows
    strip_h = np.minimum(rows, y0[tri] + box_h[tri] - strip_y0)
    counts = box_w[tri] * strip_h
    batch = np.cumsum(counts) // _BATCH_PIXELS
    bounds = np.searchsorted(batch, np.arange(int(batch[-1]) + 2)) if tri.size else [0]
    nearest = np.full(width * height, np.inf)
    # The batches' z-buffer scratch, each batch leaving it as it found it (all inf, all
    # _NO_CANDIDATE): allocated once, not once a batch (a 4096 x 4096 picture has dozens).
    scratch = (np.full(width * height, np.inf), np.full(width * height, _NO_CANDIDATE))
    colors = np.asarray(face_colors if vertex_colors is None else vertex_colors, dtype=np.float64)
    for lo, hi in itertools.pairwise(bounds):
        if hi > lo:
            _draw_batch(
                corners, area, tri[lo:hi], x0, box_w, strip_y0[lo:hi], counts[lo:hi],
                tris if vertex_colors is not None else None, colors, width, nearest, image,
                scratch,
            )  # fmt: skip
    return image.reshape(height, width, 3)


def _draw_batch(
    corners: np.ndarray,
    area: np.ndarray,
    tri: np.ndarray,
    x0: np.ndarray,
    box_w: np.ndarray,
    y0: np.ndarray,
    counts: np.ndarray,
    vertex_faces: np.ndarray | None,
    colors: np.ndarray,
    width: int,
    nearest: np.ndarray,
    image: np.ndarray,
    scratch: tuple[np.ndarray, np.ndarray],
) -> None:
    """Draw one batch of strips (triangle ``tri``, first row ``y0``, ``counts`` pixels) into
    ``image`` where nearer than ``nearest``, updating it (``scratch``: rasterise's). Ties go
    to the earlier candidate (within a batch the first index at the least depth, across
    batches by a strict test): the image is a function of the input alone."""
    # Every (triangle, pixel of its strip) pair, enumerated without a loop.
    cand = np.repeat(tri, counts)
    offset = np.arange(cand.size) - np.repeat(np.cumsum(counts) - counts, counts)
    row, column = np.divmod(offset, box_w[cand])
    px, py = x0[cand] + column, np.repeat(y0, counts) + row
    # Each corner's offset from the pixel centre, one contiguous row per corner (3, N).
    dx = corners[:, :, 0].T[:, cand] - (px + 0.5)
    dy = corners[:, :, 1].T[:, cand] - (py + 0.5)
    inverse = 1.0 / area[cand]
    b0 = (dx[1] * dy[2] - dx[2] * dy[1]) * inverse
    b1 = (dx[2] * dy[0] - dx[0] * dy[2]) * inverse
    b2 = 1.0 - b0 - b1
    inside = np.nonzero((b0 >= 0.0) & (b1 >= 0.0) & (b2 >= 0.0))[0]
    cand = cand[inside]
    bary = np.stack([b0[inside], b1[inside], b2[inside]], axis=1)
    pixel = py[inside] * width + px[inside]
    depth = np.einsum("ij,ij->i", bary, corners[cand, :, 2])
    # The batch's z-buffer without a sort: each pixel's least depth, then of the candidates
    # at it the first (a sort by pixel and depth did the same at ~3x the cost: a
    # 640 x 480 frame of ICT-FaceKit, ~240k candidates, 88 -> 63 ms, the same pixels).
    least, first = scratch
    np.minimum.at(least, pixel, depth)
    at_least = np.nonzero(depth == least[pixel])[0]
    least[pixel] = np.inf
    at_pixel = pixel[at_least]
    np.minimum.at(first, at_pixel, at_least)
    won = at_least[first[at_pixel] == at_least]
    first[at_pixel] = _NO_CANDIDATE
    won = won[depth[won] < nearest[pixel[won]]]
    won_pixel = pixel[won]
    if vertex_faces is not None:
        shaded = np.einsum("ij,ijk->ik", bary[won], colors[vertex_faces[cand[won]]])
    else:
        shaded = colors[cand[won]]
    nearest[won_pixel] = depth[won]
    image[won_pixel] = shaded
