// The face-landmark model: @vladmandic/human's BlazeFace + FaceMesh (468 points; the lids
// refined by its iris model, eyelids.js) on TensorFlow.js's WebAssembly backend, weights and
// .wasm files served by facecast itself (/perform/assets/, copied from the npm packages at
// build time). See docs/perform.md.

import { Human } from "@vladmandic/human";

import { EyelidModel } from "./eyelids.js";
import { largestFace } from "./facemesh.js";

/** Whether FaceMesh's eyelids are refined by the iris model (eyelids.js): FaceMesh's own
 * lids close a fifth of the way on a blink and move both eyes alike on a wink (README, "The
 * eyes clip"). The page, `facecast track` and `facecast perform`'s page all take it from here.
 * The same model gives the iris centres, the layout's last two features (the mesh then has
 * MediaPipe's 478 points): without it the mesh has 468, which the layout refuses. */
export const REFINE_EYELIDS = true;

/** Where build.mjs puts the models and the WebAssembly binaries, relative to the page. */
export const ASSETS = "perform/assets/";

function config(base, backend) {
  return {
    // WASM (SIMD) runs this model in ~30 ms a frame on a 2-core CPU; WebGL on SwiftShader
    // takes 0.7–1.5 s and the plain JS backend ~1.3 s (docs/perform.md, measured).
    backend,
    wasmPath: `${base}`,
    modelBasePath: `${base}`,
    debug: false,
    warmup: "none",
    cacheSensitivity: 0, // every camera frame is tracked anew, never served from a cache
    filter: { enabled: false }, // the raw image: the fake camera is drawn as it comes
    face: {
      enabled: true,
      detector: { modelPath: "blazeface.json", rotation: false, maxDetected: 2, minConfidence: 0.5, return: false },
      mesh: { enabled: true, modelPath: "facemesh.json" },
      iris: { enabled: false }, // the lids are refined by eyelids.js instead (see there)
      attention: { enabled: false },
      description: { enabled: false },
      emotion: { enabled: false },
      antispoof: { enabled: false },
      liveness: { enabled: false },
    },
    body: { enabled: false },
    hand: { enabled: false },
    object: { enabled: false },
    gesture: { enabled: false },
    segmentation: { enabled: false },
  };
}

export class Tracker {
  constructor({ base = ASSETS, backend = "wasm", eyelids = REFINE_EYELIDS } = {}) {
    this.human = new Human(config(base, backend));
    this.eyelids = eyelids ? new EyelidModel(this.human.tf, `${base}iris.json`) : null;
    this.backend = null;
    this.features = {};
  }

  /** Load the models and the backend; returns the backend that really runs ("wasm"), and
   * sets `features` ({simd, threads} for wasm). */
  async load() {
    await this.human.load();
    await this.human.tf.ready();
    // Human logs a model it could not fetch and goes on; a page without it would only
    // ever report "no face", so say what is missing instead.
    const loaded = this.human.models.loaded().join(" ");
    const missing = ["blazeface", "facemesh"].filter((name) => !loaded.includes(name));
    if (missing.length) throw new Error(`could not load ${missing.join(" and ")} from ${ASSETS} (is the server up?)`);
    if (this.eyelids) {
      try {
        await this.eyelids.load();
      } catch (err) {
        throw new Error(`could not load iris from ${ASSETS} (is the server up?): ${err.message}`);
      }
    }
    this.backend = this.human.tf.getBackend();
    const wasm = this.human.env.wasm || {};
    // What really runs: the backend TensorFlow.js settled on and, for wasm, which binary.
    this.features = this.backend === "wasm" ? { simd: wasm.simd === true, threads: wasm.multithread === true } : {};
    return this.backend;
  }

  /**
   * Track one video frame. Returns {faces, face} where faces is how many were found and
   * face (the largest, or null) is {landmarks: [[x, y, z]] in video pixels, box, score}.
   */
  async track(video) {
    const result = await this.human.detect(video);
    const faces = result.face.filter((f) => f.mesh && f.mesh.length >= 468);
    const best = largestFace(faces);
    if (best < 0) {
      if (this.eyelids) this.eyelids.reset();
      return { faces: 0, face: null };
    }
    const face = faces[best];
    if (this.eyelids) await this.eyelids.refine(video, face.mesh);
    return { faces: faces.length, face: { landmarks: face.mesh, box: face.box, score: face.faceScore ?? face.score } };
  }
}
