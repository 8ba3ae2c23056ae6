// The facecast wire protocol (protocol/PROTOCOL.md), the part a viewer needs, in the browser.
// Pure functions from messages to bytes and back; no sockets, no DOM, no three.js.

import { decode as msgpackDecode, encode as msgpackEncode } from "@msgpack/msgpack";

export const PROTOCOL_VERSION = 1;
export const SUBPROTOCOL = "facecast.v1"; // §2.3
export const BEARER_SUBPROTOCOL_PREFIX = "facecast.bearer."; // §2.2
export const STREAM_PATH = "/v1/stream";

// §6.1; clients must accept codes they do not know.
export const ErrorCode = Object.freeze({
  MALFORMED: 1001,
  INVALID_MESSAGE: 1002,
  UNKNOWN_TYPE: 1003,
  UNSUPPORTED_VERSION: 1004,
  INVALID_FIELD: 1005,
  MESSAGE_TOO_LARGE: 1006,
  INVALID_ARRAY: 1007,
  NON_FINITE: 1008,
  WRONG_STATE: 1009,
  TEXT_NOT_SUPPORTED: 1010,
  UNKNOWN_RIG: 2001,
  WRONG_POINT_COUNT: 2002,
  RATE_LIMITED: 2003,
  IDLE_TIMEOUT: 2004,
  UNAUTHORIZED: 2005,
  FORBIDDEN: 2006,
  OVERLOADED: 2007,
  CHANNEL_BUSY: 2008,
  CALIBRATION_FAILED: 2009,
  POINTS_OUT_OF_RANGE: 2010,
  RESULT_NOT_FINITE: 2011,
  INTERNAL: 3000,
});

const CODE_NAMES = Object.fromEntries(Object.entries(ErrorCode).map(([k, v]) => [v, k]));

export function errorName(code) {
  return CODE_NAMES[code] ?? `ERROR_${code}`;
}

// §7: the largest server -> client message and the element bounds a decoder enforces.
export const LIMITS = Object.freeze({
  maxServerMessageBytes: 64 * 1024 * 1024,
  maxString: 256,
  maxNames: 4096,
  maxKeys: 64,
});

const ITEM_SIZE = { f16: 2, f32: 4, f64: 8 };
const SERVER_TYPES = new Set([
  "ready",
  "result",
  "error",
  "pong",
  "calibrated",
  "channel_idle",
  "channel_live",
  "face_lost",
]);

/** A message that does not follow the protocol; `code` is one of ErrorCode. */
export class ProtocolError extends Error {
  constructor(code, message) {
    super(message);
    this.name = "ProtocolError";
    this.code = code;
  }
}

// -- arrays (§4) ------------------------------------------------------------------------

/** Expand IEEE 754 binary16 values (as uint16 bit patterns) to float32. */
export function halfToFloat(bits) {
  const out = new Float32Array(bits.length);
  for (let i = 0; i < bits.length; i++) {
    const h = bits[i];
    const sign = h & 0x8000 ? -1 : 1;
    const exponent = (h >> 10) & 0x1f;
    const fraction = h & 0x3ff;
    if (exponent === 0) {
      out[i] = sign * fraction * 2 ** -24; // subnormal (and zero)
    } else if (exponent === 31) {
      out[i] = fraction ? NaN : sign * Infinity;
    } else {
      out[i] = sign * (1 + fraction / 1024) * 2 ** (exponent - 15);
    }
  }
  return out;
}

/**
 * Decode an array map into { shape, data: Float32Array } (f64 is narrowed: a viewer
 * renders in float32 anyway).
 */
export function arrayFromWire(value, { ndim, trailing = [] } = {}) {
  if (!isMap(value)) throw new ProtocolError(ErrorCode.INVALID_ARRAY, "array: not a map");
  const { dtype, shape, data } = value;
  const itemSize = ITEM_SIZE[dtype];
  if (!itemSize) throw new ProtocolError(ErrorCode.INVALID_ARRAY, `array: unknown dtype ${dtype}`);
  if (!Array.isArray(shape) || !shape.every((d) => Number.isInteger(d) && d >= 0)) {
    throw new ProtocolError(ErrorCode.INVALID_ARRAY, "array: shape must be a list of ints");
  }
  if (ndim !== undefined && shape.length !== ndim) {
    throw new ProtocolError(ErrorCode.INVALID_ARRAY, `array: expected ${ndim} dimensions`);
  }
  trailing.forEach((size, i) => {
    if (shape[shape.length - trailing.length + i] !== size) {
      throw new ProtocolError(ErrorCode.INVALID_ARRAY, `array: trailing dimension must be ${size}`);
    }
  });
  if (shape.length && shape[0] < 1) throw new ProtocolError(ErrorCode.INVALID_ARRAY, "array: empty");
  if (!(data instanceof Uint8Array)) throw new ProtocolError(ErrorCode.INVALID_ARRAY, "array: data must be bin");
  const count = shape.reduce((a, b) => a * b, 1);
  if (data.byteLength !== count * itemSize) {
    throw new ProtocolError(ErrorCode.INVALID_ARRAY, "array: data length does not match shape");
  }
  // The bin may sit at any offset inside the message: copy to an aligned buffer (§12).
  const bytes = data.slice();
  const view = new DataView(bytes.buffer);
  let out;
  if (dtype === "f16") {
    const bits = new Uint16Array(count);
    for (let i = 0; i < count; i++) bits[i] = view.getUint16(2 * i, true);
    out = halfToFloat(bits);
  } else if (dtype === "f32") {
    out = new Float32Array(count);
    for (let i = 0; i < count; i++) out[i] = view.getFloat32(4 * i, true);
  } else {
    out = new Float32Array(count);
    for (let i = 0; i < count; i++) out[i] = view.getFloat64(8 * i, true);
  }
  for (let i = 0; i < count; i++) {
    if (!Number.isFinite(out[i])) throw new ProtocolError(ErrorCode.NON_FINITE, "array: non-finite value");
  }
  return { shape, data: out };
}

/** An f32 array map of `values` (a Float32Array) with `shape`, little-endian (§4). */
export function arrayToWire(values, shape) {
  const bytes = new Uint8Array(values.length * 4);
  const view = new DataView(bytes.buffer);
  for (let i = 0; i < values.length; i++) view.setFloat32(4 * i, values[i], true);
  return { dtype: "f32", shape, data: bytes };
}

// -- client -> server (§5.1) ------------------------------------------------------------

/**
 * A hello (§5.1.1) for `rig`; with `smoothing` (a map of §5.1.1's keys, `{}` or
 * `{target: "points"}` for the server's auto choice) in `options`, absent otherwise.
 */
export function encodeHello({ rig, output = "weights", dtype = "f32", smoothing = null }) {
  const message = { v: PROTOCOL_VERSION, type: "hello", rig, output, dtype };
  if (smoothing) message.options = { smoothing };
  return msgpackEncode(message);
}

/** `points` is a Float32Array of K*3 values; `seq` must be an integer (§12). */
export function encodeFrame(seq, ts, points) {
  if (!Number.isInteger(seq) || seq < 0) throw new RangeError("seq must be a non-negative integer");
  return msgpackEncode({
    v: PROTOCOL_VERSION,
    type: "frame",
    seq,
    ts,
    points: arrayToWire(points, [points.length / 3, 3]),
  });
}

/** §5.1.3: re-base the session's rig on this neutral (`points`: Float32Array K*3); with
 * `noise` (the performer's landmark σ, a number ≥ 0) noise-aware and bounded. */
/**
 * A calibrate with the neutral `points` (Float32Array, K×3 flat), the held frames' `noise`
 * and, with the noise, the performer's captured closed eyes: `blinks` {eyeBlinkLeft?,
 * eyeBlinkRight?: Float32Array K×3} (PROTOCOL.md §5.1.3; absent on the wire unless given),
 * with the performer's own curve for them, `contrast` [low, high] (blink_contrast; absent
 * unless given with closed eyes).
 */
export function encodeCalibrate(points, noise = null, blinks = null, contrast = null) {
  const message = { v: PROTOCOL_VERSION, type: "calibrate", points: arrayToWire(points, [points.length / 3, 3]), reset: false };
  if (typeof noise === "number" && Number.isFinite(noise) && noise >= 0) {
    message.noise = noise;
    const closed = Object.entries(blinks || {}).filter(([, p]) => p && p.length === points.length);
    if (closed.length) message.blinks = Object.fromEntries(closed.map(([name, p]) => [name, arrayToWire(p, [p.length / 3, 3])]));
    if (closed.length && contrast) message.blink_contrast = [contrast[0], contrast[1]];
  }
  return msgpackEncode(message);
}

export function encodePing(id, ts) {
  return msgpackEncode({ v: PROTOCOL_VERSION, type: "ping", id, ts });
}

// -- server -> client (§5.2) ------------------------------------------------------------

/** Decode one server message (ArrayBuffer or Uint8Array) into a plain object. */
export function decodeServer(buffer) {
  const bytes = buffer instanceof Uint8Array ? buffer : new Uint8Array(buffer);
  if (bytes.byteLength > LIMITS.maxServerMessageBytes) {
    throw new ProtocolError(ErrorCode.MESSAGE_TOO_LARGE, "message too large");
  }
  let value;
  try {
    value = msgpackDecode(bytes, {
      maxStrLength: 4 * LIMITS.maxString,
      maxBinLength: LIMITS.maxServerMessageBytes,
      maxArrayLength: LIMITS.maxNames,
      maxMapLength: LIMITS.maxKeys,
      maxExtLength: 0,
    });
  } catch (err) {
    throw new ProtocolError(ErrorCode.MALFORMED, `not one msgpack value: ${err.message}`);
  }
  if (!isMap(value)) throw new ProtocolError(ErrorCode.INVALID_MESSAGE, "message is not a map");
  if (!Number.isInteger(value.v)) throw new ProtocolError(ErrorCode.INVALID_MESSAGE, "v missing");
  if (value.v !== PROTOCOL_VERSION) {
    throw new ProtocolError(ErrorCode.UNSUPPORTED_VERSION, `unsupported protocol version ${value.v}`);
  }
  if (typeof value.type !== "string") throw new ProtocolError(ErrorCode.INVALID_MESSAGE, "type missing");
  if (!SERVER_TYPES.has(value.type)) {
    throw new ProtocolError(ErrorCode.UNKNOWN_TYPE, `unknown message type ${value.type}`);
  }
  const parse = PARSERS[value.type];
  return parse ? parse(value) : value;
}

const PARSERS = {
  ready(m) {
    const rig = m.rig;
    if (!isMap(rig) || typeof rig.id !== "string" || !Array.isArray(rig.names)) {
      throw new ProtocolError(ErrorCode.INVALID_FIELD, "ready: rig must be a map with id and names");
    }
    for (const key of ["m", "k", "v"]) {
      if (!Number.isInteger(rig[key]) || rig[key] < 0) {
        throw new ProtocolError(ErrorCode.INVALID_FIELD, `ready: rig.${key} must be a uint`);
      }
    }
    if (rig.m !== rig.names.length) throw new ProtocolError(ErrorCode.INVALID_FIELD, "ready: rig.m != len(names)");
    const moving = m.output === "moving" ? movingFromWire(rig.moving, rig.v) : null;
    if (moving === null && rig.moving != null) {
      throw new ProtocolError(ErrorCode.INVALID_FIELD, "ready: rig.moving is only sent with output moving");
    }
    return { ...m, rig: { ...rig, moving }, limits: isMap(m.limits) ? m.limits : {} };
  },
  result(m) {
    requireUint(m, "seq");
    requireNumber(m, "ts");
    const hasWeights = m.weights != null;
    if (hasWeights === (m.vertices != null)) {
      throw new ProtocolError(ErrorCode.INVALID_FIELD, "result: exactly one of weights and vertices");
    }
    const out = { ...m, proc_us: m.proc_us ?? 0, dropped: m.dropped ?? 0 };
    if (hasWeights) out.weights = arrayFromWire(m.weights, { ndim: 1 }).data;
    else out.vertices = arrayFromWire(m.vertices, { ndim: 2, trailing: [3] }).data;
    // §5.3: the publisher's head pose, relayed unchanged (the server checked it).
    if (isMap(m.head) && m.head.rotation != null) {
      const rotation = arrayFromWire(m.head.rotation, { ndim: 1 }).data;
      if (rotation.length !== 4) throw new ProtocolError(ErrorCode.INVALID_ARRAY, "result: head.rotation must have 4 values");
      out.head = { rotation };
    } else delete out.head;
    // §5.4: stage stamps, figures only (latency.js checks each value).
    if (!isMap(m.stamps)) delete out.stamps;
    return out;
  },
  error(m) {
    requireUint(m, "code");
    return {
      ...m,
      message: typeof m.message === "string" ? m.message : "",
      seq: m.seq ?? null,
      fatal: m.fatal === true,
    };
  },
  pong(m) {
    requireUint(m, "id");
    requireNumber(m, "ts");
    return m;
  },
};

/**
 * ready.rig.moving (§5.2.1): a bin of N little-endian uint32, strictly increasing vertex
 * indices below v, as a Uint32Array.
 */
export function movingFromWire(data, v) {
  if (!(data instanceof Uint8Array) || data.byteLength === 0 || data.byteLength % 4) {
    throw new ProtocolError(ErrorCode.INVALID_FIELD, "ready: rig.moving must be a bin of uint32");
  }
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const moving = new Uint32Array(data.byteLength / 4);
  for (let i = 0; i < moving.length; i++) {
    moving[i] = view.getUint32(4 * i, true);
    if (moving[i] >= v || (i > 0 && moving[i] <= moving[i - 1])) {
      throw new ProtocolError(ErrorCode.INVALID_FIELD, "ready: rig.moving must increase and stay below v");
    }
  }
  return moving;
}

/**
 * Write a "moving" result's vertices (Float32Array of 3N) into a mesh's positions
 * (Float32Array of 3V) at the indices `moving`; the other vertices keep their values
 * (the neutral's: no example moves them).
 */
export function applyMoving(positions, moving, vertices) {
  if (vertices.length !== 3 * moving.length) {
    throw new ProtocolError(ErrorCode.INVALID_FIELD, `result: ${vertices.length / 3} vertices for ${moving.length} moving`);
  }
  for (let i = 0; i < moving.length; i++) {
    const at = 3 * moving[i];
    positions[at] = vertices[3 * i];
    positions[at + 1] = vertices[3 * i + 1];
    positions[at + 2] = vertices[3 * i + 2];
  }
}

function requireUint(m, key) {
  if (!Number.isInteger(m[key]) && typeof m[key] !== "bigint") {
    throw new ProtocolError(ErrorCode.INVALID_FIELD, `${m.type}: ${key} must be a uint`);
  }
}

function requireNumber(m, key) {
  if (typeof m[key] !== "number" || !Number.isFinite(m[key])) {
    throw new ProtocolError(ErrorCode.INVALID_FIELD, `${m.type}: ${key} must be a finite number`);
  }
}

function isMap(value) {
  return value !== null && typeof value === "object" && !Array.isArray(value) && !(value instanceof Uint8Array);
}

// -- the demo performance (server route GET /v1/demo/animation) -----------------------

/** Decode the demo animation: { fps, k, frames, points: Float32Array(F*K*3) }. */
export function decodeAnimation(buffer) {
  let value;
  try {
    value = msgpackDecode(new Uint8Array(buffer), { maxExtLength: 0 });
  } catch (err) {
    throw new ProtocolError(ErrorCode.MALFORMED, `demo animation: ${err.message}`);
  }
  if (!isMap(value) || value.type !== "animation") {
    throw new ProtocolError(ErrorCode.INVALID_MESSAGE, "demo animation: not an animation map");
  }
  const { shape, data } = arrayFromWire(value.points, { ndim: 3, trailing: [3] });
  if (typeof value.fps !== "number" || !(value.fps > 0)) {
    throw new ProtocolError(ErrorCode.INVALID_FIELD, "demo animation: fps must be > 0");
  }
  return { fps: value.fps, frames: shape[0], k: shape[1], points: data };
}
