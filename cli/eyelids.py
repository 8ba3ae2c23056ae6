"""The eyelids and irises refined by MediaPipe's iris model, as the /perform page refines them.

The same model (``iris_landmark.tflite``, which mediapipe 0.10.21's wheel ships; the page
runs @vladmandic/human's conversion of it, ``iris.json``) on the same crops, written into
FaceMesh's 468-point mesh the same way: a port of the page's ``eyelids.js`` (its comments
say why each choice; ``tests/perform/test_eyelids_js.py`` runs both on the same numbers).
``facecast perform`` takes the irises from it (``refine(..., lids=False)``) and keeps the
attention mesh's lids: the shipped generic source set's irises are the page's tracker's
view of ICT's generic face (README, option (z)), and the attention mesh barely moved its
irises when both eyes closed (0.06-0.13 against the page's 0.31-0.45 on the eyelids clip),
so a character on that set read its quick blink at 0.46; with this model's lids too, a rig
on ICT's 24 landmarks read it at 0.13 (the attention mesh's: 0.83).

Runs the model with LiteRT (``ai-edge-litert``, the ``facecast[perform]`` extra).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = [
    "EYE_BOX_ANCHOR",
    "EYE_BOX_FRAMES",
    "EYE_CROP_SCALE",
    "EyeBoxes",
    "EyelidModel",
    "crop_and_resize",
    "eye_box",
    "replace_lids",
]

#: FaceMesh's lid contours, outer corner first, and which of the model's 71 contour points
#: each is (eyelids.js: UPPER, LOWER, UPPER_CONTOUR, LOWER_CONTOUR).
UPPER = {"right": (246, 161, 160, 159, 158, 157, 173), "left": (466, 388, 387, 386, 385, 384, 398)}
LOWER = {
    "right": (33, 7, 163, 144, 145, 153, 154, 155, 133),
    "left": (263, 249, 390, 373, 374, 380, 381, 382, 362),
}
UPPER_CONTOUR = (9, 10, 11, 12, 13, 14, 15)
LOWER_CONTOUR = (0, 1, 2, 3, 4, 5, 6, 7, 8)
#: Where each eye's 5 iris points go after FaceMesh's 468, centre first (MediaPipe's
#: 478-point mesh).
IRIS_MESH = {"right": 468, "left": 473}
#: The crop: the corners' box enlarged this much, made square.
EYE_CROP_SCALE = 2.3
#: Frames over which each crop's place and size are the median (a quick blink never
#: moves the crop).
EYE_BOX_FRAMES = 9
#: FaceMesh's nose tip, the point the crops are placed from.
EYE_BOX_ANCHOR = 4
#: Points of the 478-point mesh: FaceMesh's 468 and the 10 iris points.
MESH_POINTS = 478


def eye_box(a: np.ndarray, b: np.ndarray, scale: float = EYE_CROP_SCALE) -> np.ndarray:
    """The square crop around one eye from its corners ``a``, ``b`` (x, y): (x, y, size),
    its top-left corner and side in image pixels."""
    cx, cy = (a[0] + b[0]) / 2, (a[1] + b[1]) / 2
    size = scale * max(abs(a[0] - b[0]), abs(a[1] - b[1]))
    return np.array([cx - size / 2, cy - size / 2, size])


class EyeBoxes:
    """Where the eyes are cropped, frame after frame: each crop the median, over the last
    ``frames`` frames, of ``eye_box``'s place and size in the face's own axes (from the
    nose tip, along the outer eye corners' line, in units of their distance), put back at
    this frame's nose tip and axes (eyelids.js ``EyeBoxes``). ``reset`` when the face is
    lost."""

    def __init__(self, frames: int = EYE_BOX_FRAMES) -> None:
        self.frames = frames
        self.reset()

    def reset(self) -> None:
        self.history: dict[str, list[np.ndarray]] = {"right": [], "left": []}

    def place(self, landmarks: np.ndarray) -> dict[str, np.ndarray]:
        """This frame's crops {side: (x, y, size)} from FaceMesh's ``landmarks`` (image
        pixels, y down)."""
        origin = landmarks[EYE_BOX_ANCHOR, :2]
        a, b = landmarks[LOWER["right"][0], :2], landmarks[LOWER["left"][0], :2]
        span = float(np.hypot(*(b - a)))
        u = (b - a) / span
        v = np.array([-u[1], u[0]])
        boxes = {}
        for side in ("right", "left"):
            box = eye_box(landmarks[LOWER[side][0]], landmarks[LOWER[side][8]])
            d = box[:2] + box[2] / 2 - origin
            history = self.history[side]
            history.append(np.array([d @ u / span, d @ v / span, box[2] / span]))
            del history[: -self.frames]
            along, across, size = span * np.median(history, axis=0)
            centre = origin + along * u + across * v
            boxes[side] = np.array([centre[0] - size / 2, centre[1] - size / 2, size])
        return boxes


def crop_and_resize(image: np.ndarray, box: np.ndarray, side: int) -> np.ndarray:
    """The (side, side, 3) float32 crop of ``image`` (H, W, 3) in [0, 1] under ``box``
    (x, y, size in pixels), bilinear, zero outside the image: TensorFlow's
    ``image.cropAndResize`` as the page calls it (the box's edges mapped onto pixel
    centres 0 and H - 1 / W - 1 of the normalised box)."""
    height, width = image.shape[:2]
    x0, y0, size = box
    steps = np.arange(side) / (side - 1)
    ys = (y0 / height + steps * size / height) * (height - 1)
    xs = (x0 / width + steps * size / width) * (width - 1)
    rows_in = (ys >= 0) & (ys <= height - 1)
    columns_in = (xs >= 0) & (xs <= width - 1)
    top = np.clip(np.floor(ys), 0, height - 1).astype(np.intp)
    left = np.clip(np.floor(xs), 0, width - 1).astype(np.intp)
    bottom, right = np.minimum(top + 1, height - 1), np.minimum(left + 1, width - 1)
    fy, fx = (ys - np.floor(ys))[:, None, None], (xs - np.floor(xs))[None, :, None]
    # Only the window the samples fall in is converted; rows first, then columns.
    window = image[top[0] : bottom[-1] + 1, left[0] : right[-1] + 1].astype(np.float32)
    rows = window[top - top[0]] * (1 - fy) + window[bottom - top[0]] * fy
    crop = rows[:, left - left[0]] * (1 - fx) + rows[:, right - left[0]] * fx
    crop *= rows_in[:, None, None] & columns_in[None, :, None]
    out: np.ndarray = (crop / 255.0).astype(np.float32)
    return out


def replace_lids(
    landmarks: np.ndarray,
    side: str,
    contour: np.ndarray,
    iris: np.ndarray,
    box: np.ndarray,
    side_px: int,
    mirrored: bool,
    lids: bool = True,
) -> None:
    """One eye's model output written into ``landmarks`` (MESH_POINTS x 3, image pixels,
    changed in place): the lid points' x and y (the corners and z stay FaceMesh's) and the
    5 iris points, their z the lid centres' (eyelids.js ``replaceLids``).
    ``contour`` (71, 3) and ``iris`` (5, 3) are in crop pixels of a ``side_px`` crop;
    ``mirrored``: the crop was flipped left-right before the model saw it; ``lids``
    False: the irises only."""

    def image_xy(points: np.ndarray) -> np.ndarray:
        uv = points[:, :2] / side_px
        if mirrored:
            uv[:, 0] = 1 - uv[:, 0]
        placed: np.ndarray = box[:2] + uv * box[2]
        return placed

    if lids:
        upper, lower = list(UPPER[side]), list(LOWER[side][1:-1])
        landmarks[upper, :2] = image_xy(contour[list(UPPER_CONTOUR)])
        landmarks[lower, :2] = image_xy(contour[list(LOWER_CONTOUR[1:-1])])
    z = (landmarks[UPPER[side][3], 2] + landmarks[LOWER[side][4], 2]) / 2
    start = IRIS_MESH[side]
    landmarks[start : start + 5, :2] = image_xy(iris)
    landmarks[start : start + 5, 2] = z


def _model_path() -> Path:
    import mediapipe

    return Path(mediapipe.__file__).parent / "modules" / "iris_landmark" / "iris_landmark.tflite"


class EyelidModel:
    """The iris model on both eyes of one face, the frames of one face in order."""

    def __init__(self) -> None:
        from ai_edge_litert.interpreter import Interpreter

        self._interpreter = Interpreter(model_path=str(_model_path()), num_threads=1)
        self._interpreter.allocate_tensors()
        (entry,) = self._interpreter.get_input_details()
        self._input = entry["index"]
        self.side = int(entry["shape"][1])
        outputs = {o["name"]: o["index"] for o in self._interpreter.get_output_details()}
        self._contour = outputs["output_eyes_contours_and_brows"]
        self._iris = outputs["output_iris"]
        self.boxes = EyeBoxes()

    def reset(self) -> None:
        """The face was lost: the next face's crops start afresh."""
        self.boxes.reset()

    def refine(self, image: np.ndarray, landmarks: np.ndarray, *, lids: bool = True) -> np.ndarray:
        """FaceMesh's 468 ``landmarks`` (image pixels, y down, (468, 3)) with their lids
        refined (unless ``lids`` is False) and the 10 iris points appended: (478, 3).
        ``image``: the (H, W, 3) uint8 RGB frame they were tracked on."""
        mesh = np.concatenate([landmarks[:468], np.zeros((MESH_POINTS - 468, 3))])
        boxes = self.boxes.place(mesh)
        for side in ("right", "left"):
            crop = crop_and_resize(image, boxes[side], self.side)
            # The model takes right eyes (the image's left one): the left eye goes in mirrored.
            mirrored = side == "left"
            if mirrored:
                crop = crop[:, ::-1]
            self._interpreter.set_tensor(self._input, np.ascontiguousarray(crop[None]))
            self._interpreter.invoke()
            contour = self._interpreter.get_tensor(self._contour).reshape(71, 3)
            iris = self._interpreter.get_tensor(self._iris).reshape(5, 3)
            replace_lids(mesh, side, contour, iris, boxes[side], self.side, mirrored, lids)
        return mesh
