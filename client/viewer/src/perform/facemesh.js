// A tracker's face mesh -> the layout's feature points in the face-fixed frame: head pose
// and distance to the camera removed. Pure arithmetic, no DOM, no network.
//
// The same normalisation as facecast.rig.facemesh (Python), driven by the same layout
// table (rig/sources/layouts/*.json), so points published from this page and from
// `facecast perform` or a MediaPipe NDJSON file agree. The frame, per mesh:
//   x: right eye centre (mean of frame.right) -> left eye centre (frame.left), the
//      subject's own left;
//   y: mean(frame.top) - mean(frame.bottom), made orthogonal to x: up;
//   z: x × y, out of the face towards the camera;
//   origin: mean of the stable points; unit: eye-centre distance = frame.span (≈ cm).

export class FaceMeshError extends Error {}

/**
 * Whether a rig of `k` feature points takes this layout's points: `k` is its feature count or
 * an earlier version's (the layout only grows by appending, so such a rig takes the first k),
 * as facecast.rig.sources.layouts.Layout.drives.
 */
export function drives(layout, k) {
  return k === layout.features.length || (layout.earlier_counts ?? []).includes(k);
}

/** Check a layout table once (shape, index ranges); returns it frozen. */
export function checkLayout(layout) {
  const n = layout.tracker_points;
  const inRange = (i) => Number.isInteger(i) && i >= 0 && i < n;
  const lists = [layout.features, layout.stable, ...["right", "left", "top", "bottom"].map((p) => layout.frame?.[p])];
  if (!Number.isInteger(n) || lists.some((list) => !Array.isArray(list) || !list.length || !list.every(inRange))) {
    throw new FaceMeshError(`layout ${layout.name}: indices must be integers in [0, ${n})`);
  }
  for (const side of ["left", "right"]) {
    const eye = layout.eyes?.[side];
    if (!eye || !["upper", "lower", "outer", "inner"].every((p) => inRange(eye[p]))) {
      throw new FaceMeshError(`layout ${layout.name}: eyes.${side} needs upper, lower, outer, inner`);
    }
  }
  if (!(layout.frame.span > 0)) throw new FaceMeshError(`layout ${layout.name}: frame.span must be > 0`);
  const earlier = layout.earlier_counts ?? [];
  if (!earlier.every((c, i) => Number.isInteger(c) && c > 0 && c < layout.features.length && (i === 0 || c > earlier[i - 1]))) {
    throw new FaceMeshError(`layout ${layout.name}: earlier_counts must be increasing counts below ${layout.features.length}`);
  }
  return Object.freeze(layout);
}

/**
 * Image-space landmarks (pixels, y down, z into the screen in about pixel units: what the
 * face-mesh models give) -> isotropic y-up mesh coordinates, z towards the camera.
 * `landmarks`: array of [x, y, z]; returns a Float64Array of N*3.
 */
export function imageToMesh(landmarks) {
  const out = new Float64Array(landmarks.length * 3);
  for (let i = 0; i < landmarks.length; i++) {
    const p = landmarks[i];
    out[3 * i] = p[0];
    out[3 * i + 1] = -p[1];
    out[3 * i + 2] = -p[2];
  }
  return out;
}

function meanOf(mesh, indices, out) {
  out[0] = out[1] = out[2] = 0;
  for (const i of indices) {
    out[0] += mesh[3 * i];
    out[1] += mesh[3 * i + 1];
    out[2] += mesh[3 * i + 2];
  }
  out[0] /= indices.length;
  out[1] /= indices.length;
  out[2] /= indices.length;
  return out;
}

/**
 * The face-fixed frame of one mesh (Float64Array N*3 from imageToMesh).
 * Returns {rotation: [x, y, z] axes (each length 3), origin, scale (mesh -> layout units)}.
 */
export function faceFrame(mesh, layout) {
  if (mesh.length < layout.tracker_points * 3) {
    throw new FaceMeshError(`expected ${layout.tracker_points} mesh points, got ${mesh.length / 3}`);
  }
  const f = layout.frame;
  const right = meanOf(mesh, f.right, [0, 0, 0]);
  const left = meanOf(mesh, f.left, [0, 0, 0]);
  const top = meanOf(mesh, f.top, [0, 0, 0]);
  const bottom = meanOf(mesh, f.bottom, [0, 0, 0]);
  const ax = [left[0] - right[0], left[1] - right[1], left[2] - right[2]];
  const span = Math.hypot(ax[0], ax[1], ax[2]);
  if (!(span > 1e-9)) throw new FaceMeshError("the eye centres coincide: not a face mesh");
  for (let j = 0; j < 3; j++) ax[j] /= span;
  const up = [top[0] - bottom[0], top[1] - bottom[1], top[2] - bottom[2]];
  const along = up[0] * ax[0] + up[1] * ax[1] + up[2] * ax[2];
  const ay = [up[0] - along * ax[0], up[1] - along * ax[1], up[2] - along * ax[2]];
  const height = Math.hypot(ay[0], ay[1], ay[2]);
  if (!(height > 1e-9)) throw new FaceMeshError("the face's up vector lies along the eye axis: not a face mesh");
  for (let j = 0; j < 3; j++) ay[j] /= height;
  const az = [ax[1] * ay[2] - ax[2] * ay[1], ax[2] * ay[0] - ax[0] * ay[2], ax[0] * ay[1] - ax[1] * ay[0]];
  const origin = meanOf(mesh, layout.stable, [0, 0, 0]);
  return { rotation: [ax, ay, az], origin, scale: f.span / span };
}

/**
 * The layout's K feature points of one mesh in the face-fixed frame, written into `out`
 * (Float32Array K*3, the frame message's points) and returned with the frame.
 */
export function normaliseMesh(mesh, layout, out = new Float32Array(layout.features.length * 3)) {
  const frame = faceFrame(mesh, layout);
  const [ax, ay, az] = frame.rotation;
  const { origin, scale } = frame;
  const features = layout.features;
  for (let k = 0; k < features.length; k++) {
    const i = 3 * features[k];
    const dx = mesh[i] - origin[0];
    const dy = mesh[i + 1] - origin[1];
    const dz = mesh[i + 2] - origin[2];
    out[3 * k] = scale * (dx * ax[0] + dy * ax[1] + dz * ax[2]);
    out[3 * k + 1] = scale * (dx * ay[0] + dy * ay[1] + dz * ay[2]);
    out[3 * k + 2] = scale * (dx * az[0] + dy * az[1] + dz * az[2]);
  }
  return { points: out, frame };
}

/**
 * How far the head is turned from facing the camera, in degrees: yaw (about y), pitch
 * (about x) and roll (in the image plane).
 */
export function headAngles(frame) {
  const [ax, , az] = frame.rotation;
  const deg = 180 / Math.PI;
  return {
    yaw: Math.atan2(az[0], az[2]) * deg,
    pitch: Math.atan2(-az[1], az[2]) * deg,
    roll: Math.atan2(ax[1], ax[0]) * deg,
  };
}

function distance(mesh, a, b) {
  return Math.hypot(mesh[3 * a] - mesh[3 * b], mesh[3 * a + 1] - mesh[3 * b + 1], mesh[3 * a + 2] - mesh[3 * b + 2]);
}

/** Eye openness, lid gap over eye width (open ≈ 0.25–0.35, shut < 0.1), mean of both eyes. */
export function eyeOpenness(mesh, layout) {
  let sum = 0;
  for (const side of ["left", "right"]) {
    const e = layout.eyes[side];
    sum += distance(mesh, e.upper, e.lower) / Math.max(1e-9, distance(mesh, e.outer, e.inner));
  }
  return sum / 2;
}

/** Index of the largest face (by box area) among detections with a `box` [x, y, w, h]. */
export function largestFace(faces) {
  let best = -1;
  let bestArea = -1;
  faces.forEach((face, i) => {
    const area = face.box[2] * face.box[3];
    if (area > bestArea) {
      best = i;
      bestArea = area;
    }
  });
  return best;
}
