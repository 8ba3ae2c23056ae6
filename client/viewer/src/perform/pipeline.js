// One image -> the layout's feature points exactly as /perform publishes them: the face
// model (tracker.js) and the face-frame normalisation (facemesh.js) joined in one place,
// shared by the live page (main.js) and the offline tracker (track.js, `facecast track`).
// No network, no drawing on the page (one off-screen canvas to hold a frame's pixels).

import layoutTable from "../../../../rig/sources/layouts/mediapipe_face_mesh.json";
import { checkLayout, FaceMeshError, imageToMesh, normaliseMesh } from "./facemesh.js";
import { headQuaternion } from "./headpose.js";
import { Tracker } from "./tracker.js";

/** The layout both the page and the offline tracker publish in. */
export const LAYOUT = checkLayout(layoutTable);

export class FacePipeline {
  /** `layout`: a checked layout table (default LAYOUT); `backend`, `base` as for Tracker. */
  constructor({ layout = LAYOUT, backend = "wasm", base } = {}) {
    this.layout = layout;
    this.tracker = new Tracker(base === undefined ? { backend } : { backend, base });
    this.points = new Float32Array(layout.features.length * 3);
    this.head = new Float32Array(4);
    this.canvas = document.createElement("canvas");
    this.context = this.canvas.getContext("2d");
  }

  /** Load the model and backend; returns the backend that really runs (Tracker.load). */
  async load() {
    return this.tracker.load();
  }

  get features() {
    return this.tracker.features;
  }

  /**
   * Track one VideoFrame (a camera's, or one made from a file's YUV planes): drawn into a
   * canvas of its display size, where Chromium converts it to RGB, then tracked. The
   * caller keeps and closes the frame. Returns what `track` does.
   */
  async trackFrame(frame) {
    const { displayWidth: width, displayHeight: height } = frame;
    if (this.canvas.width !== width || this.canvas.height !== height) {
      this.canvas.width = width;
      this.canvas.height = height;
    }
    this.context.drawImage(frame, 0, 0);
    return this.track(this.canvas);
  }

  /**
   * Track one image (a <video>, a canvas, anything the face model takes). Returns
   * {faces, face, mesh, points, head, frame, modelMs}: `points` (this.points, Float32Array
   * K*3) and `head` (this.head, the head pose's quaternion x, y, z, w in the protocol's
   * frame, headpose.js), both overwritten by the next call, and `mesh`/`frame` are null
   * when no face was found;
   * `face` is the tracker's (landmarks in image pixels, box, score); `modelMs` the model's
   * time.
   */
  async track(image) {
    const t0 = performance.now();
    const result = await this.tracker.track(image);
    const modelMs = performance.now() - t0;
    if (!result.face) return { faces: result.faces, face: null, mesh: null, points: null, head: null, frame: null, modelMs };
    const mesh = imageToMesh(result.face.landmarks);
    let frame;
    try {
      ({ frame } = normaliseMesh(mesh, this.layout, this.points));
    } catch (err) {
      // A degenerate mesh (eye centres coinciding) is no face, as in facecast.cli.facetrack.
      if (err instanceof FaceMeshError) return { faces: result.faces, face: null, mesh: null, points: null, head: null, frame: null, modelMs };
      throw err;
    }
    headQuaternion(frame, this.head);
    return { faces: result.faces, face: result.face, mesh, points: this.points, head: this.head, frame, modelMs };
  }
}
