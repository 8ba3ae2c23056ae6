"""The page's face-frame normalisation (JavaScript) gives the numbers Python's gives.

Both read rig/sources/layouts/mediapipe_face_mesh.json; points published from /perform and from
a MediaPipe NDJSON file or ``facecast perform`` must agree for a performer's rig to work.
"""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest

from facecast.rig import estimate_noise
from facecast.rig.sources.facemesh import normalise_mesh
from facecast.rig.sources.layouts import load_layout
from facecast.server.pages.viewer import viewer_dir

_SCRIPT = """
import { readFileSync } from "node:fs";
import { checkLayout, normaliseMesh } from "./src/perform/facemesh.js";
const layout = checkLayout(JSON.parse(readFileSync("../../rig/sources/layouts/mediapipe_face_mesh.json")));
const meshes = JSON.parse(readFileSync(0, "utf8"));
const out = meshes.map((m) => Array.from(normaliseMesh(Float64Array.from(m.flat()), layout).points));
process.stdout.write(JSON.stringify(out));
"""


def _run_node(node: str, script: str, data: object) -> object:
    """``script`` (an ES module in the viewer's folder) on ``data`` as JSON; its JSON out."""
    run = subprocess.run(
        [node, "--input-type=module", "-e", script],
        cwd=viewer_dir(),
        input=json.dumps(data),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    return json.loads(run.stdout)


def test_javascript_and_python_normalise_a_mesh_alike():
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    layout = load_layout()
    rng = np.random.default_rng(4)
    # Face-sized meshes in isotropic y-up pixels, turned and scaled differently.
    meshes = rng.normal(scale=40.0, size=(3, layout.tracker_points, 3))
    meshes[:, layout.frame["right"]] += [-30.0, 0.0, 0.0]
    meshes[:, layout.frame["left"]] += [30.0, 0.0, 0.0]
    meshes[:, layout.frame["top"]] += [0.0, 60.0, 0.0]

    from_js = np.array(_run_node(node, _SCRIPT, meshes.tolist())).reshape(3, -1, 3)
    from_python = normalise_mesh(meshes, layout)
    np.testing.assert_allclose(from_js, from_python, rtol=1e-5, atol=1e-4)


_NOISE_SCRIPT = """
import { readFileSync } from "node:fs";
import { heldNoise } from "./src/perform/capture.js";
process.stdout.write(JSON.stringify(heldNoise(JSON.parse(readFileSync(0, "utf8")))));
"""


def test_the_pages_neutral_noise_is_estimate_noise():
    # What the page sends with its calibrate (heldNoise) and what the server measures from
    # held frames (rig.estimate_noise) are one rule: they must give the same sigma.
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    rng = np.random.default_rng(5)
    held = (
        rng.normal(scale=0.03, size=(24, load_layout().num_features, 3))
        + np.linspace(0.0, 0.2, 24)[:, None, None]
    )  # a slow drift, which steps barely count

    from_js = _run_node(node, _NOISE_SCRIPT, held.tolist())

    assert from_js == pytest.approx(estimate_noise(held), rel=1e-12)


_HEAD_SCRIPT = """
import { readFileSync } from "node:fs";
import { encodePerformFrame, headQuaternion, REST_PITCH_DEG } from "./src/perform/headpose.js";
const { axes, points } = JSON.parse(readFileSync(0, "utf8"));
const quaternions = axes.map((rotation) => Array.from(headQuaternion({ rotation })));
const head = Float32Array.from(quaternions[0]);
const frames = [head, null].map((h) =>
  Array.from(encodePerformFrame(3, 1.5, Float32Array.from(points), h)));
process.stdout.write(JSON.stringify({ quaternions, frames, rest: REST_PITCH_DEG }));
"""


def test_the_pages_head_pose_is_the_bridges_quaternion_and_a_valid_frame_head():
    # The face frame of a head turned by known angles (the frame's rest pitch, then the
    # turn: its axes are the columns of head_rotation(angles) @ Rx(rest)) gives the
    # quaternion the bridges send for those angles (§5.3), and its frame message decodes
    # with that head; without a head, the bytes of encodeFrame (protocol.js).
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    from facecast.cli.bridges.head_pose import unity_quaternion
    from facecast.protocol import Frame, decode_client, encode
    from facecast.rig.sources.source_rig import head_rotation

    rng = np.random.default_rng(6)
    # Every quadrant of Shepperd's method: small turns, and half-turns about each axis.
    angles = np.concatenate(
        [rng.uniform(-0.6, 0.6, size=(20, 3)), [[np.pi * 0.9, 0, 0], [0, np.pi * 0.9, 0],
                                                [0, 0, np.pi * 0.9], [0, 0, 0]]]
    )  # fmt: skip
    rest = head_rotation([0.0, np.radians(-11.4), 0.0])  # the page's REST_PITCH_DEG
    axes = np.swapaxes(head_rotation(angles) @ rest, 1, 2)  # rows: the frame's x, y, z
    points = rng.normal(size=(load_layout().num_features, 3)).astype(np.float32)

    out = _run_node(node, _HEAD_SCRIPT, {"axes": axes.tolist(), "points": points.ravel().tolist()})

    assert out["rest"] == -11.4
    got = np.array(out["quaternions"])
    want = np.array([unity_quaternion(a) for a in angles])
    want *= np.sign(want[:, 3:4] + (want[:, 3:4] == 0))  # w >= 0, as the page sends it
    np.testing.assert_allclose(got, want, atol=1e-6)
    with_head, without = (decode_client(bytes(frame)) for frame in out["frames"])
    assert isinstance(with_head, Frame) and with_head.head is not None
    np.testing.assert_array_equal(with_head.head.rotation, got[0].astype(np.float32))
    assert with_head.head.position is None and without.head is None
    np.testing.assert_array_equal(with_head.points, points)
    assert bytes(out["frames"][1]) == encode(Frame(seq=3, ts=1.5, points=points))
