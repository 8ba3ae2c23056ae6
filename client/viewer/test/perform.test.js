// The performer page's arithmetic: the face-fixed frame (head pose and distance removed)
// and the calibration capture's robust average and refusals (src/perform/).
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { test } from "node:test";

import { CAPTURE_LIMITS, captureDone, expectsEyesShut, heldFrames, heldNoise, HELD_CAPTURES, noiseText, summariseCapture } from "../src/perform/capture.js";
import {
  checkLayout,
  eyeOpenness,
  FaceMeshError,
  faceFrame,
  headAngles,
  imageToMesh,
  largestFace,
  normaliseMesh,
} from "../src/perform/facemesh.js";

const layout = checkLayout(JSON.parse(readFileSync(new URL("../../../rig/sources/layouts/mediapipe_face_mesh.json", import.meta.url))));
const K = layout.features.length;

/** A deterministic pseudo-random face-sized point cloud (pixels, image coordinates). */
function cloud(seed = 1) {
  let s = seed;
  const rand = () => ((s = (s * 16807) % 2147483647) / 2147483647);
  const points = Array.from({ length: layout.tracker_points }, () => [200 + 80 * rand(), 150 + 100 * rand(), 40 * rand() - 20]);
  // The frame's points where a face has them: the subject's right eye on the image's left.
  const at = { right: [215, 160], left: [265, 160], top: [240, 110], bottom: [240, 200] };
  for (const [part, [x, y]] of Object.entries(at)) {
    for (const i of layout.frame[part]) points[i] = [x + 4 * rand(), y + 4 * rand(), 10 * rand() - 5];
  }
  return points;
}

/** Rotate (about z by roll, about y by yaw), scale and shift image landmarks. */
function move(landmarks, { roll = 0, yaw = 0, scale = 1, shift = [0, 0, 0] }) {
  const [cr, sr, cy, sy] = [Math.cos(roll), Math.sin(roll), Math.cos(yaw), Math.sin(yaw)];
  return landmarks.map(([x, y, z]) => {
    const [x1, y1] = [cr * x - sr * y, sr * x + cr * y];
    const [x2, z2] = [cy * x1 + sy * z, -sy * x1 + cy * z];
    return [scale * x2 + shift[0], scale * y1 + shift[1], scale * z2 + shift[2]];
  });
}

function maxAbsDiff(a, b) {
  return Math.max(...Array.from(a, (v, i) => Math.abs(v - b[i])));
}

test("a rigid head motion and a change of distance leave the normalised points unchanged", () => {
  const face = cloud();
  const { points: still } = normaliseMesh(imageToMesh(face), layout);
  const { points: moved } = normaliseMesh(imageToMesh(move(face, { roll: 0.3, yaw: -0.25, scale: 0.6, shift: [40, -25, 9] })), layout);
  assert.ok(maxAbsDiff(still, moved) < 1e-4, `moved by ${maxAbsDiff(still, moved)}`);
});

test("the unit makes the eye-centre distance the layout's span", () => {
  const mesh = imageToMesh(cloud(3));
  const { rotation, scale } = faceFrame(mesh, layout);
  const centre = (idx) => [0, 1, 2].map((c) => idx.reduce((a, i) => a + mesh[3 * i + c], 0) / idx.length);
  const [r, l] = [centre(layout.frame.right), centre(layout.frame.left)];
  assert.ok(Math.abs(scale * Math.hypot(l[0] - r[0], l[1] - r[1], l[2] - r[2]) - layout.frame.span) < 1e-9);
  const [ax, ay, az] = rotation;
  const dot = (u, v) => u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
  assert.ok(Math.abs(dot(ax, ay)) < 1e-12 && Math.abs(dot(ax, az)) < 1e-12 && Math.abs(dot(az, az) - 1) < 1e-12);
});

test("a feature point that moves (an expression) moves in the output, the frame does not", () => {
  const face = cloud(5);
  const open = face.map((p) => p.slice());
  const chin = layout.features[K - 1];
  open[chin][1] += 12; // image y down: the chin drops 12 px
  const a = normaliseMesh(imageToMesh(face), layout).points;
  const b = normaliseMesh(imageToMesh(open), layout).points;
  assert.ok(b[3 * (K - 1) + 1] < a[3 * (K - 1) + 1] - 0.1, "the chin went down");
  assert.ok(maxAbsDiff(a.subarray(0, 3 * (K - 1)), b.subarray(0, 3 * (K - 1))) < 1e-9);
});

test("head angles follow a yaw of the mesh", () => {
  const face = cloud(7);
  const base = headAngles(faceFrame(imageToMesh(face), layout));
  const turned = headAngles(faceFrame(imageToMesh(move(face, { yaw: 0.35 })), layout));
  const delta = Math.abs(turned.yaw - base.yaw);
  assert.ok(Math.abs(delta - 0.35 * (180 / Math.PI)) < 3, `yaw changed by ${delta}°`);
});

test("a mesh with too few points or coinciding eyes is an error, not a NaN", () => {
  assert.throws(() => normaliseMesh(new Float64Array(30), layout), FaceMeshError);
  const flat = imageToMesh(Array.from({ length: layout.tracker_points }, () => [1, 2, 3]));
  assert.throws(() => normaliseMesh(flat, layout), FaceMeshError);
});

test("a layout with an index out of range is refused", () => {
  const bad = structuredClone(layout);
  bad.features[0] = layout.tracker_points;
  assert.throws(() => checkLayout(bad), /indices must be integers/);
});

test("eye openness and the largest of two faces", () => {
  assert.ok(eyeOpenness(imageToMesh(cloud(2)), layout) > 0);
  assert.equal(largestFace([{ box: [0, 0, 10, 10] }, { box: [5, 5, 30, 20] }, { box: [0, 0, 20, 20] }]), 1);
  assert.equal(largestFace([]), -1);
});

// -- captures ---------------------------------------------------------------------------

const HEAD = { yaw: 0, pitch: -10, roll: 0 };

/** n frames of a K-point shape plus noise σ, eyes open at 0.3. */
function frames(n, { sigma = 0.02, eyes = 0.3, head = HEAD, seed = 11 } = {}) {
  let s = seed;
  const gauss = () => {
    s = (s * 16807) % 2147483647;
    const u = s / 2147483647;
    s = (s * 16807) % 2147483647;
    const v = s / 2147483647;
    return Math.sqrt(-2 * Math.log(u)) * Math.cos(2 * Math.PI * v);
  };
  return Array.from({ length: n }, () => ({
    points: Float32Array.from({ length: 3 * K }, (_, j) => j * 0.1 + sigma * gauss()),
    eyes,
    head: { ...head },
  }));
}

test("a held expression gives its median, its spread and its kept frames", () => {
  const samples = frames(40, { sigma: 0.02 });
  const summary = summariseCapture(samples, 40, "neutral");
  assert.ok(summary.ok, summary.reason);
  assert.equal(summary.points.length, K);
  assert.ok(Math.abs(summary.points[3][1] - 1.0) < 0.02);
  assert.ok(summary.spread > 0.012 && summary.spread < 0.03, `spread ${summary.spread}`);
  assert.equal(summary.held.length, summary.kept);
  assert.equal(summary.held[0].length, K);
  assert.equal(summary.held[0][3][1], samples[0].points[10]); // frame 0, point 3, y
  const still = summariseCapture(frames(20, { sigma: 0 }), 20, "neutral");
  assert.equal(still.spread, 0);
});

test("the fit sends the held frames of at most HELD_CAPTURES captures, rounded", () => {
  const summary = summariseCapture(frames(12, { sigma: 0.02 }), 12, "neutral");
  const accepted = Array.from({ length: HELD_CAPTURES + 3 }, (_, i) => ({ name: `e${i}`, result: summary }));
  const held = heldFrames(accepted);
  assert.deepEqual(Object.keys(held), accepted.slice(0, HELD_CAPTURES).map((c) => c.name));
  const value = held.e0[0][3][1];
  assert.equal(value, Math.round(summary.held[0][3][1] * 1e4) / 1e4);
  assert.deepEqual(heldFrames([{ name: "x", result: { ok: false } }]), {});
});

test("the neutral's noise is half the mean squared frame-to-frame step, square-rooted", () => {
  // rig.noise.estimate_noise's rule: steps of 0.3 on one coordinate of three frames of 2
  // points (12 coordinates a step): sqrt((2 * 0.09) / 12 / 2).
  const frame = (y) => [[0, y, 0], [1, 1, 1]];
  const noise = heldNoise([frame(0), frame(0.3), frame(0)]);
  assert.ok(Math.abs(noise - Math.sqrt((2 * 0.09) / 12 / 2)) < 1e-12, `noise ${noise}`);
  // A slow drift counts far less than its spread: the steps, not the distance from the mean.
  const drift = Array.from({ length: 21 }, (_, i) => frame(i * 0.01));
  assert.ok(heldNoise(drift) < 0.01);
  assert.equal(heldNoise([frame(0)]), 0);
  assert.equal(heldNoise(null), 0);
});

test("the page says the fit's noise and where it came from", () => {
  const text = noiseText({ noise: 0.0123, noise_source: "held_frames", held_frames: 60 });
  assert.equal(text, ", landmark noise σ = 0.12 mm measured from 60 held frames");
  assert.equal(noiseText({ noise: 0.02, noise_source: "capture" }), ", landmark noise σ = 0.20 mm");
  assert.equal(noiseText({ noise: null }), "");
});

test("blink frames and outlier frames are left out of the average", () => {
  const samples = frames(30);
  samples[4].eyes = 0.05; // a blink
  samples[9].points = samples[9].points.map((v) => v + 1.5); // a tracking glitch
  const summary = summariseCapture(samples, 30, "aa");
  assert.ok(summary.ok, summary.reason);
  assert.equal(summary.blinks, 1);
  assert.equal(summary.outliers, 1);
  assert.equal(summary.kept, 28);
  assert.ok(Math.abs(summary.points[3][1] - 1.0) < 0.02);
});

test("a capture with the head turned is refused, with the angle", () => {
  const summary = summariseCapture(frames(30, { head: { yaw: 28, pitch: -10, roll: 0 } }), 30, "neutral");
  assert.equal(summary.ok, false);
  assert.match(summary.reason, /head turned 28° to the side/);
  const away = summariseCapture(frames(30, { head: { yaw: 14, pitch: -10, roll: 0 } }), 30, "aa", { head: HEAD, eyes: 0.3 });
  assert.match(away.reason, /from where it was for the neutral/);
});

test("a capture with the eyes shut is refused unless the expression shuts them", () => {
  const shut = frames(30, { eyes: 0.04 });
  assert.match(summariseCapture(shut, 30, "neutral").reason, /eyes shut/);
  assert.ok(summariseCapture(shut, 30, "blink").ok);
  const neutral = { head: HEAD, eyes: 0.3 };
  assert.match(summariseCapture(frames(30, { eyes: 0.13 }), 30, "aa", neutral).reason, /eyes nearly shut/);
  assert.ok(summariseCapture(frames(30, { eyes: 0.25 }), 30, "aa", neutral).ok);
  assert.ok(expectsEyesShut("eyeBlink_L") && expectsEyesShut("eyes_closed") && !expectsEyesShut("aa"));
});

test("a capture where the head moves, the face is missing or the shape wobbles is refused", () => {
  const moving = frames(30);
  moving[3].head = { yaw: 9, pitch: -10, roll: 0 };
  assert.match(summariseCapture(moving, 30, "neutral").reason, /head moved/);
  assert.match(summariseCapture(frames(5), 30, "neutral").reason, /found in 5 of 30 frames/);
  assert.match(summariseCapture(frames(30, { sigma: 0.5 }), 30, "neutral").reason, /held loosely/);
});

test("a capture ends at its time with enough frames, or at its deadline for a slow tracker", () => {
  const frames = (n) => Array.from({ length: n }, () => ({}));
  const rec = (n) => ({ samples: frames(n), until: 1000, deadline: 4000 });
  const enough = CAPTURE_LIMITS.minFrames;
  assert.equal(captureDone(rec(enough), 999), false); // its time not yet up
  assert.equal(captureDone(rec(enough), 1000), true);
  assert.equal(captureDone(rec(enough - 1), 1000), false); // a slow tracker: held on
  assert.equal(captureDone(rec(enough - 1), 3999), false);
  assert.equal(captureDone(rec(enough - 1), 4000), true); // then summarised (and refused)
  assert.equal(captureDone(rec(0), 4000), true);
});

test("a capture left short of steady frames by an outlier is held on for more, to its deadline", () => {
  const n = CAPTURE_LIMITS.minFrames;
  const samples = frames(n + 1);
  samples[2].points = samples[2].points.map((v) => v + 1.5); // a tracking glitch
  const first = samples.slice(0, n); // a tracker at n frames a second, 1 s in
  const rec = { samples: first, until: 1000, deadline: 4000 };
  const short = summariseCapture(first, n, "aa");
  assert.equal(short.ok, false);
  assert.ok(short.short);
  assert.match(short.reason, new RegExp(`only ${n - 1} steady frames`));
  assert.equal(captureDone(rec, 1000, CAPTURE_LIMITS, short), false);
  assert.equal(captureDone(rec, 4000, CAPTURE_LIMITS, short), true); // then refused
  const more = summariseCapture(samples, n + 1, "aa"); // one frame more
  assert.ok(more.ok, more.reason);
  assert.equal(captureDone({ ...rec, samples }, 1100, CAPTURE_LIMITS, more), true);
  // A refusal more frames would not mend ends the capture at its time.
  const turned = summariseCapture(frames(n, { head: { yaw: 28, pitch: -10, roll: 0 } }), n, "neutral");
  assert.equal(turned.short, false);
  assert.equal(captureDone(rec, 1000, CAPTURE_LIMITS, turned), true);
  assert.equal(summariseCapture(frames(3), 3, "aa").short, true); // found too few: more may come
  assert.equal(summariseCapture(frames(10), 30, "aa").short, false); // the face was lost
});
