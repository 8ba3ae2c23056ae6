"""The software mesh renderer: framing, shading, occlusion, grids, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from facecast.cli.render import RenderError, render_mesh, save_side_by_side

ICT = Path(__file__).resolve().parents[3] / "shared" / "data" / "ict-facekit" / "ict_facekit.npz"
WHITE = np.array([255, 255, 255])


def _sphere(n: int = 48) -> tuple[np.ndarray, np.ndarray]:
    theta, phi = np.meshgrid(np.linspace(0.01, np.pi - 0.01, n), np.linspace(0, 2 * np.pi, 2 * n))
    vertices = np.stack(
        [np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], axis=-1
    ).reshape(-1, 3)
    grid = np.arange(2 * n * n).reshape(2 * n, n)
    a, b, c, d = grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]
    faces = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    return vertices, faces


def _quad(z: float, half: float) -> np.ndarray:
    return np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])


def _foreground(image: np.ndarray) -> np.ndarray:
    return (image != WHITE).any(axis=2)


def test_image_has_the_requested_size():
    vertices, faces = _sphere(12)
    image = render_mesh(vertices, faces, size=(200, 120))
    assert image.shape == (120, 200, 3)
    assert image.dtype == np.uint8


def test_mesh_fills_the_middle_and_leaves_the_corners_empty():
    vertices, faces = _sphere(24)
    image = render_mesh(vertices, faces, size=(100, 100))
    foreground = _foreground(image)
    assert 0.5 < foreground.mean() < 0.9  # a disc fills pi/4 of its square
    assert foreground[50, 50]
    assert not foreground[[0, 0, 99, 99], [0, 99, 0, 99]].any()


def test_mesh_without_triangles_renders_background_only():
    image = render_mesh(np.zeros((3, 3)), np.zeros((0, 3), int), size=(40, 30))
    assert not _foreground(image).any()


def test_front_lit_sphere_is_brighter_in_the_middle_than_at_the_lower_right_rim():
    vertices, faces = _sphere(48)
    image = render_mesh(vertices, faces, size=(200, 200), color=(1.0, 1.0, 1.0)).astype(int)
    centre = image[100, 100].sum()
    rim = image[150, 150].sum()  # normal points down-right, away from the light
    assert centre > rim + 150


def test_nearer_triangles_hide_farther_ones_whatever_their_order():
    near = _quad(1.0, 1.0)  # faces the viewer: brightly lit
    far = _quad(-1.0, 2.0)
    far[:, 2] += 0.8 * far[:, 1]  # tilted to face downwards: darker
    vertices = np.concatenate([near, far])
    quads = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    shades = []
    for faces in (quads, quads[::-1]):
        image = render_mesh(vertices, faces, size=(80, 80), color=(1.0, 1.0, 1.0),
                            background=(0, 0, 0)).astype(int)  # fmt: skip
        centre, corner = image[40, 40].sum(), image[4, 4].sum()
        assert corner > 0  # the far quad shows around the near one
        assert centre > corner + 100
        shades.append(centre)
    assert shades[0] == shades[1]


def test_three_quarter_view_turns_the_front_to_the_right():
    box = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    nose = np.array([[-0.1, -0.1, 1.0], [0.1, -0.1, 1.0], [0.0, 0.1, 1.0]])
    vertices = np.concatenate([box, nose])
    faces = np.array([[8, 9, 10]])
    columns = {}
    for view in ("front", "three_quarter"):
        image = render_mesh(vertices, faces, size=(100, 100), view=view, frame_vertices=box)
        columns[view] = np.nonzero(_foreground(image))[1].mean()
    assert abs(columns["front"] - 50) < 3
    assert columns["three_quarter"] > columns["front"] + 10


def test_side_by_side_writes_a_png_grid_of_the_expected_size(tmp_path):
    vertices, faces = _sphere(10)
    panels = [(f"p{i}", vertices * (1 + i / 10), faces) for i in range(5)]
    out = save_side_by_side(tmp_path / "grid.png", panels, columns=3, panel_size=(100, 80))
    image = imread(out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert image.shape[:2] == (2 * (80 + 28), 3 * 100)
    # The sixth cell has no panel, so it stays white.
    assert (image[-40:, -50:, :3] == 1.0).all()


def test_side_by_side_accepts_rows_of_panels(tmp_path):
    vertices, faces = _sphere(10)
    rows = [[("a", vertices, faces), ("b", vertices, faces)], [("c", vertices, faces)]]
    image = imread(save_side_by_side(tmp_path / "rows.png", rows, panel_size=(60, 60),
                                     title="frames"))  # fmt: skip
    assert image.shape[:2] == (36 + 2 * (60 + 28), 2 * 60)


@pytest.mark.parametrize(
    ("vertices", "faces", "kwargs", "code"),
    [
        (np.zeros((3, 3)), np.array([[0, 1, 3]]), {}, "index_out_of_range"),
        (np.full((3, 3), np.nan), np.array([[0, 1, 2]]), {}, "non_finite"),
        (np.zeros((3, 2)), np.array([[0, 1, 2]]), {}, "bad_render_input"),
        (np.zeros((3, 3)), np.array([[0.0, 1.0, 2.0]]), {}, "bad_render_input"),
        (np.eye(3), np.array([[0, 1, 2]]), {"view": "top"}, "bad_view"),
        (np.eye(3), np.array([[0, 1, 2]]), {"size": (0, 10)}, "bad_size"),
        (np.eye(3), np.array([[0, 1, 2]]), {"size": (10**6, 10)}, "bad_size"),
        (np.eye(3), np.array([[0, 1, 2]]), {"color": "red"}, "bad_color"),
    ],
)
def test_bad_input_is_refused_with_a_code(vertices, faces, kwargs, code):
    with pytest.raises(RenderError) as info:
        render_mesh(vertices, faces, **kwargs)
    assert info.value.code == code


def test_empty_grid_is_refused(tmp_path):
    with pytest.raises(RenderError) as info:
        save_side_by_side(tmp_path / "x.png", [])
    assert info.value.code == "empty_grid"


@pytest.mark.ict
@pytest.mark.skipif(not ICT.exists(), reason="needs shared/data/ict-facekit")
def test_renders_the_ict_face_with_a_nose_in_the_middle():
    data = np.load(ICT)
    image = render_mesh(data["neutral"], data["faces"], size=(200, 200))
    foreground = _foreground(image)
    assert 0.3 < foreground.mean() < 0.9
    assert foreground[100, 100]  # a head, centred
