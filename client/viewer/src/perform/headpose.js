// The tracked face frame -> the protocol's head pose (PROTOCOL.md §5.3), and the frame
// message that carries it. Pure arithmetic and encoding: no DOM, no network.
//
// facemesh.js's face frame has its axes (x the performer's left, y up, z out of the face)
// in the camera's mesh coordinates (x the image's right, y up, z towards the camera); M,
// the matrix whose columns are the axes, is the face frame's rotation. Its y runs from the
// nose to the forehead, which leans back: a head facing the camera has a frame pitched
// by REST_PITCH_DEG (looking up). The head's rotation, in facecast's face frame
// (facecast.rig.sources.source_rig.head_rotation's convention), is H = M Rx(-REST_PITCH);
// the protocol's is Unity's (VMC's): S H S with S = diag(-1, 1, 1), as
// cli/bridges/head_pose.py makes it from a tracker's angles. Signs and sizes checked
// against rendered ICT-FaceKit heads turned by known angles: tests/perform/test_head_pose.py
// and docs/perform.md ("Head pose").

/** The face frame's pitch, degrees, for a head facing the camera: measured with the page's
 * tracker on the rendered ICT-FaceKit head (−11.4°), as the page shows a performer facing
 * it (about −12°). */
export const REST_PITCH_DEG = -11.4;
const REST_COS = Math.cos((REST_PITCH_DEG * Math.PI) / 180);
const REST_SIN = Math.sin((REST_PITCH_DEG * Math.PI) / 180);

import { encode as msgpackEncode } from "@msgpack/msgpack";

import { arrayToWire, PROTOCOL_VERSION } from "../protocol.js";

/**
 * The unit quaternion (x, y, z, w), w >= 0, of the head rotation a face frame (facemesh.js)
 * shows, in Unity's frame: the frame message's `head.rotation`. Written into `out`
 * (Float32Array 4) and returned.
 */
export function headQuaternion(frame, out = new Float32Array(4)) {
  const [ax, fy, fz] = frame.rotation;
  // H = M Rx(-REST_PITCH): the frame's y and z axes turned back by the rest pitch.
  const ay = [0, 1, 2].map((i) => REST_COS * fy[i] - REST_SIN * fz[i]);
  const az = [0, 1, 2].map((i) => REST_SIN * fy[i] + REST_COS * fz[i]);
  // U = S H S: H[i][j] = axis_j[i]; entries with exactly one index 0 change sign.
  const m00 = ax[0], m01 = -ay[0], m02 = -az[0];
  const m10 = -ax[1], m11 = ay[1], m12 = az[1];
  const m20 = -ax[2], m21 = ay[2], m22 = az[2];
  // Shepperd's method: the largest of w, x, y, z first, so no division by a small number.
  const trace = m00 + m11 + m22;
  let x, y, z, w;
  if (trace > 0) {
    const s = 2 * Math.sqrt(1 + trace);
    w = 0.25 * s;
    x = (m21 - m12) / s;
    y = (m02 - m20) / s;
    z = (m10 - m01) / s;
  } else if (m00 > m11 && m00 > m22) {
    const s = 2 * Math.sqrt(1 + m00 - m11 - m22);
    w = (m21 - m12) / s;
    x = 0.25 * s;
    y = (m01 + m10) / s;
    z = (m02 + m20) / s;
  } else if (m11 > m22) {
    const s = 2 * Math.sqrt(1 + m11 - m00 - m22);
    w = (m02 - m20) / s;
    x = (m01 + m10) / s;
    y = 0.25 * s;
    z = (m12 + m21) / s;
  } else {
    const s = 2 * Math.sqrt(1 + m22 - m00 - m11);
    w = (m10 - m01) / s;
    x = (m02 + m20) / s;
    y = (m12 + m21) / s;
    z = 0.25 * s;
  }
  // w >= 0 (the same rotation either way), renormalised against rounding.
  const sign = w < 0 ? -1 : 1;
  const norm = sign * Math.hypot(x, y, z, w);
  out[0] = x / norm;
  out[1] = y / norm;
  out[2] = z / norm;
  out[3] = w / norm;
  return out;
}

/**
 * A frame message (§5.1.2) of `points` (Float32Array K*3) and, when `rotation` (the
 * Float32Array 4 of headQuaternion) is given, the head pose (§5.3). Without it, the bytes
 * are protocol.js's encodeFrame's.
 */
export function encodePerformFrame(seq, ts, points, rotation = null, stamps = null) {
  if (!Number.isInteger(seq) || seq < 0) throw new RangeError("seq must be a non-negative integer");
  const message = {
    v: PROTOCOL_VERSION,
    type: "frame",
    seq,
    ts,
    points: arrayToWire(points, [points.length / 3, 3]),
  };
  if (rotation) message.head = { rotation: arrayToWire(rotation, [4]) };
  // §5.4: the stages' times on the server's clock (captured, tracked, sent).
  if (stamps) message.stamps = stamps;
  return msgpackEncode(message);
}
