// Posing a character file through the server's bindings, and the head pose's frame
// (character.js; server/SERVER.md "Characters", PROTOCOL.md §5.3).
import assert from "node:assert/strict";
import { test } from "node:test";

import {
  applyWeights,
  bindMorphs,
  headQuaternion,
  metaText,
  primitiveTargetNames,
  springsMoving,
} from "../src/character.js";

function mesh(id, morphs) {
  return { id, morphTargetInfluences: new Array(morphs).fill(0.5) };
}

test("a weight drives every morph its bindings name, on every primitive of every mesh", () => {
  const face = [mesh(1, 3), mesh(2, 3)]; // one glTF mesh, two primitives
  const teeth = [mesh(3, 1)];
  const meshes = new Map([[0, face], [1, teeth]]);
  // weights: neutral, jawOpen (face morph 0 and the teeth's morph 0), a VRM "aa" at 0.5
  const bound = bindMorphs(meshes, [[], [{ mesh: 0, morph: 0, weight: 1 }, { mesh: 1, morph: 0, weight: 1 }], [{ mesh: 0, morph: 0, weight: 0.5 }, { mesh: 0, morph: 2, weight: 1 }]]);

  applyWeights(bound, [1, 0.4, 0.2]);

  for (const primitive of face) assert.deepEqual(primitive.morphTargetInfluences, [0.4 + 0.1, 0.5, 0.2]);
  assert.deepEqual(teeth[0].morphTargetInfluences, [0.4]);
  // Unbound morphs keep what they had (0.5); bound ones are rewritten, not accumulated.
  applyWeights(bound, [1, 0, 0]);
  assert.deepEqual(face[0].morphTargetInfluences, [0, 0.5, 0]);
});

test("bindings naming a missing mesh or morph are skipped, not thrown on", () => {
  const bound = bindMorphs(new Map([[0, [mesh(1, 1)]]]), [[{ mesh: 5, morph: 0, weight: 1 }, { mesh: 0, morph: 9, weight: 1 }]]);
  assert.equal(bound.slots.length, 0);
  applyWeights(bound, [1]);
});

test("the VMC head rotation is mirrored in x: a turn about y or z changes sign, about x not", () => {
  const s = Math.sin(0.3);
  const c = Math.cos(0.3);
  const yaw = headQuaternion([0, s, 0, c]);
  const pitch = headQuaternion([s, 0, 0, c]);
  assert.deepEqual([yaw.x, yaw.y, yaw.z, yaw.w].map((v) => +v.toFixed(6)), [0, -s, 0, c].map((v) => +v.toFixed(6)));
  assert.deepEqual([pitch.x, pitch.y, pitch.z, pitch.w].map((v) => +v.toFixed(6)), [s, 0, 0, c].map((v) => +v.toFixed(6)));
});

test("the VRM meta reads as name, authors, licence and the redistribution rule", () => {
  const text = metaText({ name: "Ava", authors: ["A", "B"], licence: "CC_BY", redistribution: false }, "vrm0");
  assert.equal(text, "VRM 0.x · Ava · by A, B · licence CC_BY · no redistribution");
  assert.equal(metaText({}, "gltf"), "");
});

test("spring bones count as moving until no joint turns by more than the tolerance", () => {
  const joint = (x, w) => ({ bone: { quaternion: { x, y: 0, z: 0, w } } });
  const joints = new Set([joint(0, 1), joint(0.1, 0.995)]);
  const last = new Float32Array(8);
  assert.equal(springsMoving(joints, last), true); // from the zeros: everything moved
  assert.equal(springsMoving(joints, last), false); // the same pose again: settled
  [...joints][1].bone.quaternion.x = 0.1 + 1e-4;
  assert.equal(springsMoving(joints, last), true);
  [...joints][1].bone.quaternion.x += 1e-6; // below the tolerance
  assert.equal(springsMoving(joints, last), false);
});

test("morph names only on a primitive's extras name that primitive's morphs", () => {
  const json = {
    meshes: [
      { primitives: [{ extras: { targetNames: ["jawOpen", "eyeBlinkLeft"] } }, {}] },
      { extras: { targetNames: ["jawOpen"] }, primitives: [{}] },
      { primitives: [{ extras: { targetNames: [3] } }] },
    ],
  };

  assert.deepEqual(primitiveTargetNames(json, { meshes: 0, primitives: 0 }), ["jawOpen", "eyeBlinkLeft"]);
  // A primitive without names of its own takes the first primitive's, as the server does.
  assert.deepEqual(primitiveTargetNames(json, { meshes: 0, primitives: 1 }), ["jawOpen", "eyeBlinkLeft"]);
  assert.equal(primitiveTargetNames(json, { meshes: 1, primitives: 0 }), null); // three.js named them
  assert.equal(primitiveTargetNames(json, { meshes: 2, primitives: 0 }), null); // not names
});
