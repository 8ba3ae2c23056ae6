"""``facecast perform``'s eye crops and iris points are the /perform page's.

``cli/eyelids.py`` ports the page's ``eyelids.js`` (where each eye is cropped, frame after
frame; the crop TensorFlow.js cuts; how the iris model's points land back on the mesh) so
that the CLI's irises are the page's, which the shipped generic source set's are (README,
option (z)). Each part is run in Node on the same numbers and compared.
"""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest

from facecast.cli.eyelids import (
    EYE_BOX_ANCHOR,
    EYE_BOX_FRAMES,
    EyeBoxes,
    crop_and_resize,
    replace_lids,
)
from facecast.server.pages.viewer import viewer_dir

_SCRIPT = """
import { readFileSync } from "node:fs";
import * as tf from "@tensorflow/tfjs-core";
import "@tensorflow/tfjs-backend-cpu";
import { EyeBoxes, replaceLids } from "./src/perform/eyelids.js";
await tf.setBackend("cpu");
const { image, crops, frames, outputs, input } = JSON.parse(readFileSync(0, "utf8"));
const [h, w] = [image.length, image[0].length];
const pixels = tf.tensor3d(image, [h, w, 3], "float32");
const cut = crops.map((b) => Array.from(tf.image.cropAndResize(tf.expandDims(pixels, 0),
  [[b[1] / h, b[0] / w, (b[1] + b[2]) / h, (b[0] + b[2]) / w]], [0], [input, input]).dataSync()));
const boxes = new EyeBoxes();
const placed = frames.map((landmarks) => {
  const got = boxes.place(landmarks);
  return ["right", "left"].map((side) => [got[side].x, got[side].y, got[side].size]);
});
const last = frames[frames.length - 1].map((p) => [...p]);
const lastBoxes = placed[placed.length - 1];
replaceLids(last, "right", Float32Array.from(outputs[0]), { x: lastBoxes[0][0], y: lastBoxes[0][1], size: lastBoxes[0][2] }, input, false);
replaceLids(last, "left", Float32Array.from(outputs[1]), { x: lastBoxes[1][0], y: lastBoxes[1][1], size: lastBoxes[1][2] }, input, true);
process.stdout.write(JSON.stringify({ cut, placed, last }));
"""

#: The iris model's input side.
INPUT = 64


def _face(rng: np.random.Generator, nose, drop: float, roll: float, zoom: float) -> np.ndarray:
    """FaceMesh's 468 points in image pixels (y down): noise, with the nose tip at ``nose``
    and each eye's corners ``drop`` px low, the head rolled and zoomed about the nose."""
    c, s = np.cos(roll), np.sin(roll)

    def at(dx: float, dy: float) -> list[float]:
        return [nose[0] + zoom * (c * dx - s * dy), nose[1] + zoom * (s * dx + c * dy), 0.0]

    landmarks = np.concatenate([rng.uniform(100, 400, (468, 2)), rng.normal(size=(468, 1))], 1)
    landmarks[EYE_BOX_ANCHOR] = at(0, 0)
    for index, dx in ((33, -55), (133, -22), (263, 55), (362, 22)):
        landmarks[index] = at(dx, -40 + drop)
    return landmarks


@pytest.fixture(scope="module")
def both():
    """The same inputs through Node (eyelids.js, TensorFlow.js's CPU backend) and Python."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    rng = np.random.default_rng(7)
    image = rng.integers(0, 256, (48, 64, 3)).astype(np.float64)
    # Inside the image, over each edge, and a sub-pixel box.
    crops = [[8.0, 6.0, 30.0], [-10.0, -4.0, 40.0], [40.0, 30.0, 35.0], [3.3, 7.7, 11.1]]
    # A still head, a quick blink's drop of the corners, then a head moving, rolling, zooming.
    motion = [((320, 250), 0, 0, 1)] * EYE_BOX_FRAMES + [((320, 250), 5, 0, 1)] * 4
    motion += [((320 + 3 * i, 250 - i), 0, 0.05 * i, 1 + 0.04 * i) for i in range(8)]
    frames = np.stack([_face(rng, *m) for m in motion])
    outputs = rng.uniform(0, INPUT, (2, 76 * 3))
    data = {"image": image.tolist(), "crops": crops, "frames": frames.tolist(),
            "outputs": outputs.tolist(), "input": INPUT}  # fmt: skip
    run = subprocess.run([node, "--input-type=module", "-e", _SCRIPT], cwd=viewer_dir(),
                         input=json.dumps(data), capture_output=True, text=True, timeout=60)  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    return data, json.loads(run.stdout)


def test_the_crop_is_tensorflows_crop_and_resize(both):
    data, js = both
    image = np.asarray(data["image"], dtype=np.uint8)
    for box, cut in zip(data["crops"], js["cut"], strict=True):
        ours = crop_and_resize(image, np.array(box), INPUT)
        assert ours.shape == (INPUT, INPUT, 3)
        # The page divides TensorFlow's crop by 255 before the model sees it.
        np.testing.assert_allclose(ours, np.reshape(cut, ours.shape) / 255.0, atol=1e-5)
    # Some of each edge crop lies outside the image, which reads as black.
    assert (crop_and_resize(image, np.array(data["crops"][1]), INPUT)[:4, :4] == 0).all()


def test_the_eyes_are_cropped_where_the_page_crops_them(both):
    data, js = both
    boxes = EyeBoxes()
    for landmarks, placed in zip(data["frames"], js["placed"], strict=True):
        got = boxes.place(np.asarray(landmarks))
        np.testing.assert_allclose([got["right"], got["left"]], placed, atol=1e-9)


def test_the_model_output_lands_on_the_mesh_as_the_page_puts_it(both):
    data, js = both
    boxes = EyeBoxes()
    for landmarks in data["frames"]:
        placed = boxes.place(np.asarray(landmarks))
    mesh = np.concatenate([np.asarray(data["frames"][-1]), np.zeros((10, 3))])
    before = mesh.copy()
    for side, values, mirrored in (("right", data["outputs"][0], False),
                                   ("left", data["outputs"][1], True)):  # fmt: skip
        values = np.asarray(values, dtype=np.float32).astype(np.float64).reshape(76, 3)
        replace_lids(mesh, side, values[:71], values[71:], placed[side], INPUT, mirrored)
    np.testing.assert_allclose(mesh, np.asarray(js["last"]), atol=1e-6)
    # Irises only: the lids stay FaceMesh's (``facecast perform`` takes them elsewhere).
    irises = before.copy()
    values = np.asarray(data["outputs"][0], dtype=np.float32).astype(np.float64).reshape(76, 3)
    replace_lids(irises, "right", values[:71], values[71:], placed["right"], INPUT, False, False)
    assert (irises[:468] == before[:468]).all()
    np.testing.assert_allclose(irises[468:473, :2], mesh[468:473, :2], atol=1e-9)
