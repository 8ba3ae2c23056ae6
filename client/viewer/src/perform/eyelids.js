// The eyelids refined by MediaPipe's iris model (@vladmandic/human's iris.json): each eye
// cropped from the image around FaceMesh's own corners (where the last frames put them,
// EyeBoxes), its 71-point contour predicted, and FaceMesh's lid points replaced by it. No
// DOM; the weights come from the page's own server.
//
// Why not Human's own `face.iris`: it also replaces the eye corners (the face frame's
// points, facemesh.js) and the brows with the iris model's guesses, which moved the brows
// 7–17 mm and doubled every point's noise on the webcam benchmark; and Human 3.3.6 flips
// *both* eyes' crops but un-flips only the left eye's answer, so the subject's right lid
// comes back mirrored in its box. Here only the lids are replaced, and only the subject's
// left eye is mirrored (in and back out), as MediaPipe does: the model sees right eyes.
// See README "The eyes clip".

/** FaceMesh's lid contours (Human's meshAnnotations *EyeUpper0 / *EyeLower0), outer corner
 * first, and which of the iris model's 71 contour points each is (Human's irisIndices). */
const UPPER = { right: [246, 161, 160, 159, 158, 157, 173], left: [466, 388, 387, 386, 385, 384, 398] };
const LOWER = { right: [33, 7, 163, 144, 145, 153, 154, 155, 133], left: [263, 249, 390, 373, 374, 380, 381, 382, 362] };
const UPPER_CONTOUR = [9, 10, 11, 12, 13, 14, 15];
const LOWER_CONTOUR = [0, 1, 2, 3, 4, 5, 6, 7, 8];
/** Numbers the model gives per eye: 71 contour and 5 iris points, x y z each. */
const EYE_VALUES = 76 * 3;
/** Where the iris points go after FaceMesh's 468, as in MediaPipe's 478-point mesh: the
 * subject's right eye's 5 at 468-472, the left's at 473-477, each eye's centre first (the
 * model gives its 5 iris points after its 71 contour points in that order). */
export const IRIS_MESH = { right: 468, left: 473 };
const IRIS_CONTOUR = 71;
/** The crop: the corners' box enlarged this much, made square (Human's default). */
export const EYE_CROP_SCALE = 2.3;
/** Frames over which each crop's place and size are the median: a quick blink (3–5 frames at
 * 30 fps) is fewer than half of them, so it never moves the crop. */
export const EYE_BOX_FRAMES = 9;
/** FaceMesh's nose tip, the point the crops are placed from: FaceMesh moves its whole upper
 * face, the eye corners included, 4–7 px down when both eyes close, never its nose tip. */
export const EYE_BOX_ANCHOR = 4;

/**
 * The square crop around one eye, in image pixels: {x, y, size} (top-left corner, side),
 * from its two corners `a`, `b` ([x, y]).
 */
export function eyeBox(a, b, scale = EYE_CROP_SCALE) {
  const cx = (a[0] + b[0]) / 2;
  const cy = (a[1] + b[1]) / 2;
  const size = scale * Math.max(Math.abs(a[0] - b[0]), Math.abs(a[1] - b[1]));
  return { x: cx - size / 2, y: cy - size / 2, size };
}

function median(values) {
  const sorted = [...values].sort((a, b) => a - b);
  const mid = sorted.length >> 1;
  return sorted.length % 2 ? sorted[mid] : (sorted[mid - 1] + sorted[mid]) / 2;
}

/**
 * Where the eyes are cropped, frame after frame. FaceMesh's corners, which `eyeBox` crops
 * around, move 4–5 px down with its lids when both eyes close, and the iris model's lids
 * depend on where the eye lies in its crop (a quick blink closed the subject's right eye
 * to 0.55 of its gap at rest, where the same eye in the same crop as a wink's closed to
 * 0.40): so each crop is the median, over the last `frames` frames, of `eyeBox`'s place and
 * size in the face's own axes — from the nose tip, along the line through the outer eye
 * corners, in units of their distance — put back at this frame's nose tip and axes. The
 * head's motion in the image (a shift, a roll, a zoom) moves the crops at once; a blink
 * does not last long enough to move the median. `reset` when the face is lost.
 */
export class EyeBoxes {
  constructor(frames = EYE_BOX_FRAMES) {
    this.frames = frames;
    this.reset();
  }

  reset() {
    this.history = { right: [], left: [] };
  }

  /** This frame's crops {right, left} ({x, y, size} each) from FaceMesh's `landmarks`. */
  place(landmarks) {
    const [ox, oy] = landmarks[EYE_BOX_ANCHOR];
    const a = landmarks[LOWER.right[0]];
    const b = landmarks[LOWER.left[0]];
    const span = Math.hypot(b[0] - a[0], b[1] - a[1]);
    const u = [(b[0] - a[0]) / span, (b[1] - a[1]) / span]; // along the eyes
    const v = [-u[1], u[0]]; // across them
    const boxes = {};
    for (const side of ["right", "left"]) {
      const box = eyeBox(landmarks[LOWER[side][0]], landmarks[LOWER[side][8]]);
      const dx = box.x + box.size / 2 - ox;
      const dy = box.y + box.size / 2 - oy;
      const history = this.history[side];
      history.push([(dx * u[0] + dy * u[1]) / span, (dx * v[0] + dy * v[1]) / span, box.size / span]);
      if (history.length > this.frames) history.shift();
      const [along, across, size] = [0, 1, 2].map((j) => span * median(history.map((h) => h[j])));
      const cx = ox + along * u[0] + across * v[0];
      const cy = oy + along * u[1] + across * v[1];
      boxes[side] = { x: cx - size / 2, y: cy - size / 2, size };
    }
    return boxes;
  }
}

/**
 * One eye's model output (`values`, the eye's EYE_VALUES numbers in crop pixels of an
 * `input`-sided crop) written into `landmarks` (image pixels, [x, y, z] each): the lid
 * points' x and y; the corners and z stay FaceMesh's (the model's depth is its crop's).
 * And the eye's 5 iris points appended where MediaPipe's 478-point mesh has them
 * (IRIS_MESH), their z the lid centres' (the layout's iris features: README, option (n)).
 * `mirrored`: the crop was flipped left-right before the model saw it.
 */
export function replaceLids(landmarks, side, values, box, input, mirrored) {
  const place = (meshIndex, contour) => {
    const u = values[3 * contour] / input;
    const v = values[3 * contour + 1] / input;
    const old = landmarks[meshIndex];
    landmarks[meshIndex] = [box.x + (mirrored ? 1 - u : u) * box.size, box.y + v * box.size, old[2]];
  };
  UPPER[side].forEach((index, j) => place(index, UPPER_CONTOUR[j]));
  // The lower contour's first and last points are the corners: kept (the face frame's).
  for (let j = 1; j < LOWER[side].length - 1; j++) place(LOWER[side][j], LOWER_CONTOUR[j]);
  const z = (landmarks[UPPER[side][3]][2] + landmarks[LOWER[side][4]][2]) / 2;
  for (let j = 0; j < 5; j++) {
    const u = values[3 * (IRIS_CONTOUR + j)] / input;
    const v = values[3 * (IRIS_CONTOUR + j) + 1] / input;
    landmarks[IRIS_MESH[side] + j] = [box.x + (mirrored ? 1 - u : u) * box.size, box.y + v * box.size, z];
  }
  return landmarks;
}

/** Runs the iris model on both eyes of one face. `tf`: Human's TensorFlow.js. */
export class EyelidModel {
  constructor(tf, url) {
    this.tf = tf;
    this.url = url;
    this.model = null;
    this.input = 64;
    this.boxes = new EyeBoxes();
  }

  async load() {
    this.model = await this.tf.loadGraphModel(this.url);
    const shape = this.model.inputs?.[0]?.shape;
    if (shape && shape[1] > 0) this.input = shape[1];
  }

  /** The face was lost: the next face's crops start afresh. */
  reset() {
    this.boxes.reset();
  }

  /**
   * Refine the lids of `landmarks` (FaceMesh's, image pixels; changed in place and
   * returned) from `image` (what was tracked: a canvas, a video, an ImageData...), the
   * frames of one face in order (EyeBoxes).
   */
  async refine(image, landmarks) {
    const tf = this.tf;
    const boxes = this.boxes.place(landmarks);
    const values = tf.tidy(() => {
      const pixels = tf.browser.fromPixels(image);
      const [h, w] = pixels.shape;
      const crop = (b) => [b.y / h, b.x / w, (b.y + b.size) / h, (b.x + b.size) / w];
      // Crop the two eyes first, then scale them to [0, 1]: not the whole frame each frame.
      const eyes = tf.image.cropAndResize(tf.expandDims(pixels, 0), [crop(boxes.right), crop(boxes.left)], [0, 0], [this.input, this.input]);
      const crops = tf.div(eyes, 255);
      // The model takes right eyes (the image's left one): the left eye goes in mirrored.
      const [right, left] = tf.split(crops, 2, 0);
      const input = tf.concat([right, tf.reverse(left, 2)], 0);
      return this.model.execute(input);
    });
    const data = await values.data();
    values.dispose();
    replaceLids(landmarks, "right", data.subarray(0, EYE_VALUES), boxes.right, this.input, false);
    replaceLids(landmarks, "left", data.subarray(EYE_VALUES, 2 * EYE_VALUES), boxes.left, this.input, true);
    return landmarks;
  }
}
