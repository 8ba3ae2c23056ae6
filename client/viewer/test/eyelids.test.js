// The eyelid refinement's arithmetic (src/perform/eyelids.js): where an eye is cropped and
// how the iris model's contour, given in crop pixels, lands back on FaceMesh's lid points.
import assert from "node:assert/strict";
import { test } from "node:test";

import { eyeBox, replaceLids } from "../src/perform/eyelids.js";

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
