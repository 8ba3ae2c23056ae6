"""The z-buffer rasteriser and pinhole camera: coverage, occlusion, shading, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

import facecast.cli.raster as raster
from facecast.cli.errors import RenderError
from facecast.cli.raster import PinholeCamera, lambert, rasterise, vertex_normals

CAMERA = PinholeCamera(width=64, height=48, focal=60.0, position=(0.0, 0.0, 10.0))
GREY = (0.5, 0.5, 0.5)
QUAD = np.array([[0, 1, 2], [0, 2, 3]])


def _square(half: float, z: float = 0.0, tilt: float = 0.0) -> np.ndarray:
    """A square facing +z, turned by ``tilt`` radians about the x axis."""
    corners = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0],
                        [-half, half, 0.0]])  # fmt: skip
    c, s = math.cos(tilt), math.sin(tilt)
    turned = corners @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T
    return turned + np.array([0.0, 0.0, z])


def _draw(vertices, faces, colors, **kwargs) -> np.ndarray:
    return rasterise(CAMERA.project(vertices), faces, size=(64, 48), background=GREY,
                     vertex_colors=colors, **kwargs)  # fmt: skip


def test_covered_pixels_take_the_mesh_colour_and_the_rest_the_background():
    white = np.ones((4, 3))
    image = _draw(_square(1.0), QUAD, white)  # 1 unit at distance 10: 12 px across

    covered = (image != GREY).any(axis=2)
    assert covered.sum() == 12 * 12
    assert covered[24, 32] and not covered[0, 0] and not covered[24, 10]
    assert np.array_equal(image[covered], np.ones((144, 3)))


def test_vertex_colours_are_interpolated_across_a_triangle():
    vertices = np.array([[-2.0, -1.5, 0.0], [2.0, -1.5, 0.0], [0.0, 2.0, 0.0]])
    image = _draw(vertices, np.array([[0, 1, 2]]), np.eye(3))  # red, green, blue corners

    covered = image[(image != GREY).any(axis=2)]
    assert np.allclose(covered.sum(axis=1), 1.0)  # barycentric weights sum to one
    assert covered[:, 0].min() < 0.1 < 0.9 < covered[:, 0].max()  # red fades across


def test_the_nearer_triangle_wins_whatever_the_order():
    vertices = np.concatenate([_square(1.0, z=1.0), _square(2.0, z=-1.0)])
    colors = np.repeat([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], 4, axis=0)
    faces = np.concatenate([QUAD, QUAD + 4])

    images = [_draw(vertices, order, colors) for order in (faces, faces[::-1])]

    assert np.array_equal(images[0], images[1])
    assert np.array_equal(images[0][24, 32], [1.0, 0.0, 0.0])  # the near red square
    assert np.array_equal(images[0][24, 32 - 9], [0.0, 0.0, 1.0])  # the far blue one around it


def test_culled_triangles_are_drawn_only_facing_the_camera():
    facing = _square(1.0)
    away = facing[::-1].copy()  # the same square wound the other way: its back
    white = np.ones((4, 3))

    assert (_draw(facing, QUAD, white, cull=[True, True]) != GREY).any()
    assert not (_draw(away, QUAD, white, cull=[True, True]) != GREY).any()
    assert (_draw(away, QUAD, white) != GREY).any()  # two-sided by default


def test_lambert_brightness_rises_with_n_dot_l():
    light = (0.0, 0.0, 1.0)  # from the camera: n . l = cos(tilt)
    brightness = []
    cosines = []
    for tilt in np.radians([80, 60, 40, 20, 0]):
        vertices = _square(1.5, tilt=tilt)
        normals = vertex_normals(vertices, QUAD)
        shade = lambert(normals, light, ambient=0.2, diffuse=0.8)
        image = _draw(vertices, QUAD, np.ones((4, 3)) * shade[:, None])
        brightness.append(image[24, 32, 0])
        cosines.append(float(normals[0] @ light))

    assert np.all(np.diff(cosines) > 0)
    assert np.all(np.diff(brightness) > 0)
    assert brightness[-1] == pytest.approx(1.0) and brightness[0] == pytest.approx(
        0.2 + 0.8 * math.cos(math.radians(80))
    )


def test_rendering_is_deterministic():
    rng = np.random.default_rng(3)
    vertices = rng.uniform(-2, 2, (60, 3))
    faces = rng.integers(0, 60, (80, 3))
    colors = rng.uniform(0, 1, (60, 3))

    first = _draw(vertices, faces, colors)
    assert np.array_equal(first, _draw(vertices, faces, colors))


def test_batches_of_any_size_draw_the_same_image(monkeypatch):
    rng = np.random.default_rng(5)
    vertices = rng.uniform(-2, 2, (90, 3))
    faces = rng.integers(0, 90, (150, 3))
    colors = rng.uniform(0, 1, (90, 3))
    whole = _draw(vertices, faces, colors)

    monkeypatch.setattr(raster, "_BATCH_PIXELS", 7)  # strips of a few rows, many batches
    assert np.array_equal(_draw(vertices, faces, colors), whole)


def test_a_triangle_larger_than_a_batch_is_drawn_whole(monkeypatch):
    monkeypatch.setattr(raster, "_BATCH_PIXELS", 100)
    image = _draw(_square(1.0), QUAD, np.ones((4, 3)))  # 144 pixels, in strips
    assert (image != GREY).any(axis=2).sum() == 12 * 12


def test_camera_refuses_vertices_behind_it():
    with pytest.raises(RenderError) as info:
        CAMERA.project(_square(1.0, z=10.0))
    assert info.value.code == "behind_camera"


def test_exactly_one_kind_of_colour_is_required():
    with pytest.raises(RenderError):
        rasterise(CAMERA.project(_square(1.0)), QUAD, size=(64, 48), background=GREY)
