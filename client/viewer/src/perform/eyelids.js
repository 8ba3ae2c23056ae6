// The eyelids refined by MediaPipe's iris model (@vladmandic/human's iris.json): each eye
// cropped from the image around FaceMesh's own corners, its 71-point contour predicted, and
// FaceMesh's lid points replaced by it. No DOM; the weights come from the page's own server.
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
/** The crop: the corners' box enlarged this much, made square (Human's default). */
export const EYE_CROP_SCALE = 2.3;

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

/**
 * One eye's model output (`values`, the eye's EYE_VALUES numbers in crop pixels of an
 * `input`-sided crop) written into `landmarks` (image pixels, [x, y, z] each): the lid
 * points' x and y; the corners and z stay FaceMesh's (the model's depth is its crop's).
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
  return landmarks;
}

/** Runs the iris model on both eyes of one face. `tf`: Human's TensorFlow.js. */
export class EyelidModel {
  constructor(tf, url) {
    this.tf = tf;
    this.url = url;
    this.model = null;
    this.input = 64;
  }

  async load() {
    this.model = await this.tf.loadGraphModel(this.url);
    const shape = this.model.inputs?.[0]?.shape;
    if (shape && shape[1] > 0) this.input = shape[1];
  }

  /**
   * Refine the lids of `landmarks` (FaceMesh's, image pixels; changed in place and
   * returned) from `image` (what was tracked: a canvas, a video, an ImageData...).
   */
  async refine(image, landmarks) {
    const tf = this.tf;
    const boxes = {
      right: eyeBox(landmarks[LOWER.right[0]], landmarks[LOWER.right[8]]),
      left: eyeBox(landmarks[LOWER.left[0]], landmarks[LOWER.left[8]]),
    };
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
