// The eyelid refinement's arithmetic (src/perform/eyelids.js): where an eye is cropped (one
// frame's corners, and the crops' median over the frames) and how the iris model's contour,
// given in crop pixels, lands back on FaceMesh's lid points.
import assert from "node:assert/strict";
import { test } from "node:test";

import { EYE_BOX_ANCHOR, EYE_BOX_FRAMES, EyeBoxes, IRIS_MESH, eyeBox, replaceLids } from "../src/perform/eyelids.js";

const INPUT = 64;

/** A mesh whose every point is [-1, -1, i] (i its index), so a replaced point shows. */
function mesh() {
  return Array.from({ length: 468 }, (_, i) => [-1, -1, i]);
}

/** Model output for one eye: contour point j at crop pixel (j, 32 + j), the iris after. */
function output() {
  const values = new Float32Array(76 * 3);
  for (let j = 0; j < 76; j++) values.set([j, 32 + j, 99], 3 * j);
  return values;
}

test("the crop is square, centred on the corners, 2.3 times their span", () => {
  const box = eyeBox([100, 50], [140, 54]);
  assert.deepEqual(box, { x: 120 - 46, y: 52 - 46, size: 92 });
});

test("the right eye's lids take the contour as it comes, the corners and depth stay", () => {
  const landmarks = mesh();
  const box = { x: 10, y: 20, size: 128 };
  replaceLids(landmarks, "right", output(), box, INPUT, false);
  // Upper lid 160 is the contour's 11th point; lower lid 144 its 3rd (Human's irisIndices).
  assert.deepEqual(landmarks[160], [10 + 2 * 11, 20 + 2 * (32 + 11), 160]);
  assert.deepEqual(landmarks[144], [10 + 2 * 3, 20 + 2 * (32 + 3), 144]);
  for (const corner of [33, 133]) assert.deepEqual(landmarks[corner], [-1, -1, corner]);
  // Nothing of the other eye moves.
  for (const index of [263, 362, 386, 374, 387, 373]) assert.deepEqual(landmarks[index], [-1, -1, index]);
});

test("the left eye went in mirrored and comes back un-mirrored in its box", () => {
  const landmarks = mesh();
  const box = { x: 300, y: 20, size: 64 };
  replaceLids(landmarks, "left", output(), box, INPUT, true);
  // 387 is the contour's 11th point: x = 11 in the mirrored crop is 64 - 11 in the image's.
  assert.deepEqual(landmarks[387], [300 + (INPUT - 11), 20 + 32 + 11, 387]);
  assert.deepEqual(landmarks[373], [300 + (INPUT - 3), 20 + 32 + 3, 373]);
  for (const corner of [263, 362]) assert.deepEqual(landmarks[corner], [-1, -1, corner]);
  for (const index of [33, 133, 159, 145, 160, 144]) assert.deepEqual(landmarks[index], [-1, -1, index]);
});

test("each eye's 5 iris points land after FaceMesh's 468, where MediaPipe's 478-point mesh has them", () => {
  const landmarks = mesh();
  replaceLids(landmarks, "right", output(), { x: 10, y: 20, size: 128 }, INPUT, false);
  replaceLids(landmarks, "left", output(), { x: 300, y: 20, size: 64 }, INPUT, true);
  assert.deepEqual(IRIS_MESH, { right: 468, left: 473 });
  assert.equal(landmarks.length, 478);
  // The iris points are the model's 72nd to 76th (after the 71 contour points); their depth
  // the mean of the eye's middle upper and lower lid points' (159 / 145, 386 / 374).
  for (let j = 0; j < 5; j++) {
    const c = 71 + j;
    assert.deepEqual(landmarks[468 + j], [10 + 2 * c, 20 + 2 * (32 + c), (159 + 145) / 2]);
    assert.deepEqual(landmarks[473 + j], [300 + (INPUT - c), 20 + 32 + c, (386 + 374) / 2]);
  }
});

/** FaceMesh's points for one frame: the nose tip at `nose`, each eye's corners `drop` px
 * below where they sit at rest (FaceMesh's upper face moving down on a blink), the head
 * rolled by `roll` radians about the nose tip and `zoom` times as large. */
function face(nose = [320, 250], drop = 0, roll = 0, zoom = 1) {
  const landmarks = Array.from({ length: 468 }, () => [0, 0, 0]);
  const [c, s] = [Math.cos(roll), Math.sin(roll)];
  const at = (dx, dy) => [nose[0] + zoom * (c * dx - s * dy), nose[1] + zoom * (s * dx + c * dy), 0];
  landmarks[EYE_BOX_ANCHOR] = at(0, 0);
  landmarks[33] = at(-55, -40 + drop); // the right eye's outer and inner corners
  landmarks[133] = at(-22, -40 + drop);
  landmarks[263] = at(55, -40 + drop); // the left eye's
  landmarks[362] = at(22, -40 + drop);
  return landmarks;
}

/** Boxes equal to a millionth of a pixel. */
function sameBox(got, want) {
  for (const key of ["x", "y", "size"]) assert.ok(Math.abs(got[key] - want[key]) < 1e-6, `${key}: ${got[key]} != ${want[key]}`);
}

test("a blink's corners, moved for fewer than half the frames, do not move the crops", () => {
  const boxes = new EyeBoxes();
  let rest;
  for (let i = 0; i < EYE_BOX_FRAMES; i++) rest = boxes.place(face());
  sameBox(rest.right, eyeBox([265, 210], [298, 210]));
  // FaceMesh moves the corners 5 px down for the 4 frames of a quick blink: the crops stay.
  for (let i = 0; i < 4; i++) {
    const blink = boxes.place(face([320, 250], 5));
    sameBox(blink.right, rest.right);
    sameBox(blink.left, rest.left);
  }
  sameBox(boxes.place(face()).right, rest.right);
});

test("the crops follow the head's shift, roll and zoom at once", () => {
  const boxes = new EyeBoxes();
  for (let i = 0; i < EYE_BOX_FRAMES; i++) boxes.place(face());
  // The head moves 30 px, rolls a quarter turn and comes twice as close: this very frame's
  // crops are where its own corners put them.
  const moved = face([350, 262], 0, Math.PI / 2, 2);
  const crops = boxes.place(moved);
  sameBox(crops.right, eyeBox(moved[33], moved[133]));
  sameBox(crops.left, eyeBox(moved[263], moved[362]));
});

test("a lasting change of the corners is followed once it is most of the frames", () => {
  const boxes = new EyeBoxes();
  for (let i = 0; i < EYE_BOX_FRAMES; i++) boxes.place(face());
  const rest = boxes.place(face()).left;
  // The corners lie 6 px lower from now on (the head pitches): the 5th frame of 9 follows.
  const ys = [];
  for (let i = 0; i < EYE_BOX_FRAMES; i++) ys.push(boxes.place(face([320, 250], 6)).left.y);
  const followed = ys.findIndex((y) => Math.abs(y - (rest.y + 6)) < 1e-6);
  assert.equal(followed, (EYE_BOX_FRAMES + 1) / 2 - 1);
  assert.ok(ys.slice(0, followed).every((y) => y < rest.y + 6 - 1e-6));
});

test("a face lost and found again is cropped from its own corners, not the last face's", () => {
  const boxes = new EyeBoxes();
  for (let i = 0; i < EYE_BOX_FRAMES; i++) boxes.place(face([320, 250], 20));
  boxes.reset();
  sameBox(boxes.place(face()).right, eyeBox([265, 210], [298, 210]));
});
