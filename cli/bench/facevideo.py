"""An ICT-FaceKit head as a webcam sees it: the webcam benchmark's camera videos.

Colours ICT's parts (skin, brows, lips, eyes with iris and pupil, teeth, the mouth's inside),
shades them with plain Lambert light, sways the head gently as a seated performer does, turns
the eyeballs by the eye-look weights when asked (ICT's own shapes move the lids only), and
draws each frame through ``facecast.cli.raster`` to a 640 x 480 Y4M file. Frames only: it
must not track, fit or score.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import scipy.sparse
from matplotlib.path import Path as Polygon
from tqdm import tqdm

from facecast.cli.raster import (
    PinholeCamera,
    lambert,
    normals_operator,
    rasterise,
    vertex_normals,
)
from facecast.cli.y4m import Y4MWriter, rgb_to_i420
from facecast.rig.evaluation.webcam import Performer

__all__ = ["CAMERA", "GAZE_NAMES", "HeadScene", "head_scene", "render_frames", "write_video"]

#: A webcam's view: 640 x 480, about 56 degrees across, 47 cm in front of the nose tip.
CAMERA = PinholeCamera(width=640, height=480, focal=600.0, position=(0.0, 1.0, 60.0))
BACKGROUND = (0.5, 0.5, 0.5)
#: Light from the upper left and the front (x to the subject's left, y up, z to the camera).
LIGHT = (0.3, 0.45, 1.0)
AMBIENT, DIFFUSE = 0.3, 0.7
#: Head sway: degrees of yaw, pitch and roll, and the frequencies (Hz) of each, chosen
#: incommensurate so that no pose repeats in a take; turned about the neck.
SWAY_HZ = (0.23, 0.31, 0.17)
PIVOT = (0.0, -8.0, 0.0)

_SKIN = (0.78, 0.58, 0.48)
_BROW = (0.30, 0.21, 0.16)
_LIP = (0.68, 0.38, 0.38)
_ALBEDO = {
    "face": _SKIN,
    "head_and_neck": _SKIN,
    "mouth_socket": (0.30, 0.10, 0.10),
    "eye_socket_left": (0.72, 0.46, 0.42),
    "eye_socket_right": (0.72, 0.46, 0.42),
    "gums_and_tongue": (0.62, 0.28, 0.30),
    "teeth": (0.93, 0.91, 0.86),
    "eyeball_left": (0.92, 0.90, 0.88),
    "eyeball_right": (0.92, 0.90, 0.88),
    "eyelashes_left": (0.12, 0.09, 0.08),
    "eyelashes_right": (0.12, 0.09, 0.08),
}
#: ICT's transparent overlays (tear film, eye blend and occlusion shells): not drawn.
_HIDDEN = (
    "lacrimal_fluid_left", "lacrimal_fluid_right", "eye_blend_left", "eye_blend_right",
    "eye_occlusion_left", "eye_occlusion_right",
)  # fmt: skip
#: Thin sheets seen from both sides; every other part is drawn where it faces the camera.
_TWO_SIDED = ("eyelashes_left", "eyelashes_right")
#: Per eyeball region: the ARKit eye-look names that turn it (out, in, up, down) and the
#: sign of x towards which "out" turns it (ICT's +x is the subject's left).
GAZE_NAMES = {
    "eyeball_left": (("eyeLookOutLeft", "eyeLookInLeft", "eyeLookUpLeft", "eyeLookDownLeft"), 1.0),
    "eyeball_right": (
        ("eyeLookOutRight", "eyeLookInRight", "eyeLookUpRight", "eyeLookDownRight"),
        -1.0,
    ),
}
#: How far an eyeball turns at an ARKit eye-look weight of 1, as ARKit reads a real face: on
#: a real iPhone take (MySlate_1_iPhone.csv of dwskillman/BlendFiles, 679 frames) its eye yaw
#: is 0.59 / 0.61 rad x (eyeLookOut - eyeLookIn), r 0.994, and its pitch 0.611 rad x
#: (eyeLookUp - eyeLookDown), r 0.9999996: 35 degrees a unit (README, issue 34's option (y)).
ARKIT_GAZE_DEGREES = 35.0
_IRIS = ((0.32, 0.21, 0.12), 0.95)  # colour, cosine of the angle from the eye's axis
_PUPIL = ((0.04, 0.04, 0.04), 0.985)
_BROW_HALF_WIDTH = 0.45  # cm either side of the brow landmarks' line
_LIP_RIM = 0.25  # cm: the lip colour fades out over this much beyond the outer lip line


@dataclass(frozen=True, eq=False)
class HeadScene:
    """What stays fixed from frame to frame: the drawn triangles, colours, camera, light.

    Attributes
    ----------
    faces : (F, 3) int64
        The triangles drawn (ICT's transparent overlays left out).
    albedo : (V, 3) float64
    cull : (F,) bool
        Triangles drawn only where they face the camera.
    operator : (V, F) sparse
        ``normals_operator`` of ``faces``.
    eyeballs : tuple of (start, stop, centre (3,), region name)
        Each eyeball's vertices [start, stop) and the centre it turns about (the sphere
        that fits them best), for a gaze (``render_frames``' ``gaze_degrees``).
    """

    faces: np.ndarray
    albedo: np.ndarray
    cull: np.ndarray
    operator: scipy.sparse.csr_matrix
    camera: PinholeCamera = CAMERA
    eyeballs: tuple[tuple[int, int, np.ndarray, str], ...] = ()


def _segment_distance(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """(N,) distance of each point to the polyline ``line`` (L, 3)."""
    best = np.full(len(points), np.inf)
    for a, b in itertools.pairwise(line):
        t = np.clip((points - a) @ (b - a) / max(float((b - a) @ (b - a)), 1e-12), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(points - (a + t[:, None] * (b - a)), axis=1))
    return best


def _albedo(
    neutral: np.ndarray, regions: dict[str, tuple[int, int]], landmarks68: np.ndarray
) -> np.ndarray:
    albedo = np.tile(np.asarray(_SKIN), (len(neutral), 1))
    for name, colour in _ALBEDO.items():
        start, stop = regions[name]
        albedo[start:stop] = colour
    face = slice(*regions["face"])
    skin = neutral[face]
    for brow in (landmarks68[17:22], landmarks68[22:27]):
        near = _segment_distance(skin, neutral[brow]) < _BROW_HALF_WIDTH
        albedo[face][near] = _BROW
    # Lips: the face vertices inside the outer lip line (Multi-PIE 48-59) seen from the front,
    # in front of the teeth, with a soft rim.
    outline = neutral[landmarks68[48:60]]
    polygon = Polygon(outline[:, :2])
    front = skin[:, 2] > outline[:, 2].min() - 1.0
    inside = polygon.contains_points(skin[:, :2]) & front
    rim = _segment_distance(skin, np.concatenate([outline, outline[:1]]))
    mix = np.where(inside, 1.0, np.clip(1.0 - rim / _LIP_RIM, 0.0, 1.0) * front)[:, None]
    albedo[face] = albedo[face] * (1.0 - mix) + np.asarray(_LIP) * mix
    for side in ("eyeball_left", "eyeball_right"):
        start, stop = regions[side]
        ball = neutral[start:stop]
        axis = ball - ball.mean(axis=0)
        cosine = axis[:, 2] / np.maximum(np.linalg.norm(axis, axis=1), 1e-12)
        for colour, limit in (_IRIS, _PUPIL):
            albedo[start:stop][cosine > limit] = colour
    return albedo


def _sphere_centre(points: np.ndarray) -> np.ndarray:
    """(3,) the centre of the sphere nearest ``points`` (N, 3), by linear least squares."""
    design = np.column_stack([2.0 * points, np.ones(len(points))])
    solution, *_ = np.linalg.lstsq(design, (points * points).sum(axis=1), rcond=None)
    centre: np.ndarray = solution[:3]
    return centre


def _eye_rotations(
    performer: Performer, act: np.ndarray, region: str, degrees: float
) -> np.ndarray:
    """(F, 3, 3) each frame's turn of one eyeball: yaw by out - in, pitch by up - down,
    ``degrees`` at a weight of 1 (a name the performer lacks counts as 0)."""
    names, out_sign = GAZE_NAMES[region]
    column = {name: i for i, name in enumerate(performer.names)}
    out, inward, up, down = (
        act[:, column[name]] if name in column else np.zeros(len(act)) for name in names
    )
    yaw = math.radians(degrees) * out_sign * (out - inward)  # about +y: +z turns to +x
    pitch = math.radians(degrees) * (up - down)  # +z turns to +y: about -x
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    zero, one = np.zeros(len(act)), np.ones(len(act))
    about_y = np.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], 1).reshape(-1, 3, 3)
    about_x = np.stack([one, zero, zero, zero, cp, sp, zero, -sp, cp], 1).reshape(-1, 3, 3)
    rotations: np.ndarray = about_x @ about_y
    return rotations


def head_scene(
    performer: Performer, regions: dict[str, tuple[int, int]], landmarks68: npt.ArrayLike
) -> HeadScene:
    """The scene for ``performer``'s head (``ict_regions`` gives regions and landmarks)."""
    marks = np.asarray(landmarks68, dtype=np.int64)
    hidden = np.zeros(len(performer.neutral), dtype=bool)
    for name in _HIDDEN:
        hidden[slice(*regions[name])] = True
    faces = performer.faces[~hidden[performer.faces].any(axis=1)]
    two_sided = np.zeros(len(performer.neutral), dtype=bool)
    for name in _TWO_SIDED:
        two_sided[slice(*regions[name])] = True
    return HeadScene(
        faces=faces,
        albedo=_albedo(performer.neutral, regions, marks),
        cull=~two_sided[faces].any(axis=1),
        operator=normals_operator(faces, len(performer.neutral)),
        eyeballs=tuple(
            (*regions[name], _sphere_centre(performer.neutral[slice(*regions[name])]), name)
            for name in GAZE_NAMES
        ),
    )


def _sway(count: int, fps: float, degrees: float) -> np.ndarray:
    """(count, 3, 3) head rotations: yaw, pitch and roll, each a slow sine of ``degrees``."""
    t = np.arange(count) / fps
    yaw, pitch, roll = (
        math.radians(degrees) * np.sin(2 * math.pi * hz * t + phase)
        for hz, phase in zip(SWAY_HZ, (0.0, 1.3, 2.1), strict=True)
    )
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    zero, one = np.zeros(count), np.ones(count)
    about_y = np.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], 1).reshape(-1, 3, 3)
    about_x = np.stack([one, zero, zero, zero, cp, -sp, zero, sp, cp], 1).reshape(-1, 3, 3)
    about_z = np.stack([cr, -sr, zero, sr, cr, zero, zero, zero, one], 1).reshape(-1, 3, 3)
    rotations: np.ndarray = about_z @ about_x @ about_y
    return rotations


def render_frames(
    scene: HeadScene,
    performer: Performer,
    activations: npt.ArrayLike,
    *,
    fps: float,
    sway_degrees: float = 1.5,
    rotations: npt.ArrayLike | None = None,
    gaze_degrees: float = 0.0,
) -> Iterator[np.ndarray]:
    """Each frame of ``performer`` making ``activations`` (F, M): (480, 640, 3) uint8 RGB.

    ``rotations``: (F, 3, 3) head rotations about the neck (``PIVOT``), applied to column
    vectors in ICT's frame, in place of the sway (the head-pose tests' known poses).
    ``gaze_degrees``: how far each eyeball turns at an ARKit eye-look weight of 1 (0: never,
    as ICT's own shapes, which move the lids only and leave the iris where it is).
    """
    act = np.asarray(activations, dtype=np.float64)
    if rotations is None:
        rotations = _sway(len(act), fps, sway_degrees)
    else:
        rotations = np.asarray(rotations, dtype=np.float64)
        if rotations.shape != (len(act), 3, 3):
            raise ValueError(f"rotations must be ({len(act)}, 3, 3), got {rotations.shape}")
    pivot = np.asarray(PIVOT)
    camera = scene.camera
    size = (camera.width, camera.height)
    eyes = [
        (start, stop, centre, _eye_rotations(performer, act, name, gaze_degrees))
        for start, stop, centre, name in scene.eyeballs
        if gaze_degrees
    ]
    # A frame that repeats the one before (a held key, a still head) is that image again:
    # the same inputs rasterise to the same pixels, so it is not drawn twice.
    previous: tuple[bytes, ...] | None = None
    image: np.ndarray | None = None
    for index in range(len(act)):
        inputs = (act[index].tobytes(), rotations[index].tobytes(),
                  *(turns[index].tobytes() for *_, turns in eyes))  # fmt: skip
        if inputs == previous and image is not None:
            yield image
            continue
        previous = inputs
        vertices = performer.vertices(act[index : index + 1])[0].astype(np.float64)
        for start, stop, centre, turns in eyes:
            vertices[start:stop] = (vertices[start:stop] - centre) @ turns[index].T + centre
        vertices = (vertices - pivot) @ rotations[index].T + pivot
        normals = vertex_normals(vertices, scene.faces, scene.operator)
        # Two-sided light: a normal turned away from the camera is flipped towards it.
        away = np.einsum("ij,ij->i", normals, np.asarray(camera.position) - vertices) < 0
        normals[away] *= -1.0
        shade = lambert(normals, LIGHT, ambient=AMBIENT, diffuse=DIFFUSE)
        image = rasterise(
            camera.project(vertices),
            scene.faces,
            size=size,
            background=BACKGROUND,
            vertex_colors=scene.albedo * shade[:, None],
            cull=scene.cull,
        )
        image = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        yield image


def write_video(
    path: str | Path,
    scene: HeadScene,
    performer: Performer,
    activations: npt.ArrayLike,
    *,
    fps: float,
    sway_degrees: float = 1.5,
    rotations: npt.ArrayLike | None = None,  # as for render_frames
    gaze_degrees: float = 0.0,  # as for render_frames
    progress: bool = True,
) -> Path:
    """Render ``activations`` (F, M) to a Y4M video at ``path``; returns the path."""

    act = np.asarray(activations, dtype=np.float64)
    camera = scene.camera
    frames = render_frames(
        scene,
        performer,
        act,
        fps=fps,
        sway_degrees=sway_degrees,
        rotations=rotations,
        gaze_degrees=gaze_degrees,
    )
    previous: np.ndarray | None = None
    planes = b""
    with Y4MWriter(path, camera.width, camera.height, fps) as writer:
        for image in tqdm(frames, total=len(act), unit="frame", desc=f"rendering {Path(path).name}",
                          disable=not progress, leave=False):  # fmt: skip
            # A repeated frame is the same image (render_frames): converted once (~9 ms).
            if image is not previous:
                previous, planes = image, rgb_to_i420(image)
            writer.write_i420(planes)
    return Path(path)
