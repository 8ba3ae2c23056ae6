// The viewer's protocol code against the byte examples of protocol/PROTOCOL.md §10.
import assert from "node:assert/strict";
import { test } from "node:test";

import { decode as msgpackDecode } from "@msgpack/msgpack";

import {
  applyMoving,
  arrayFromWire,
  decodeServer,
  encodeCalibrate,
  encodeFrame,
  encodeHello,
  encodePing,
  ErrorCode,
  halfToFloat,
  ProtocolError,
} from "../src/protocol.js";

const decode = (bytes) => msgpackDecode(bytes);
const hex = (text) => Uint8Array.from(text.trim().split(/\s+/), (b) => parseInt(b, 16));

test("frame encodes to the bytes of PROTOCOL.md §10.2", () => {
  const expected = hex(`85 a1 76 01 a4 74 79 70 65 a5 66 72 61 6d 65 a3
    73 65 71 07 a2 74 73 cb 40 29 00 00 00 00 00 00
    a6 70 6f 69 6e 74 73 83 a5 64 74 79 70 65 a3 66
    33 32 a5 73 68 61 70 65 92 02 03 a4 64 61 74 61
    c4 18 00 00 00 00 00 00 80 3f 00 00 00 40 00 00
    00 bf 00 00 80 3e 00 00 c0 3f`);
  const points = new Float32Array([0, 1, 2, -0.5, 0.25, 1.5]);
  // 12.5 is not an integer, so msgpack writes float 64 as the spec's example does.
  assert.deepEqual(encodeFrame(7, 12.5, points), expected);
});

test("hello carries options.smoothing only when given (PROTOCOL.md §5.1.1)", () => {
  const plain = decode(encodeHello({ rig: "cat" }));
  assert.deepEqual(plain, { v: 1, type: "hello", rig: "cat", output: "weights", dtype: "f32" });
  const auto = decode(encodeHello({ rig: "cat", smoothing: { target: "points" } }));
  assert.deepEqual(auto.options, { smoothing: { target: "points" } });
});

test("calibrated says the filter that runs from it on (PROTOCOL.md §10.9)", () => {
  const bytes = hex(`85 a1 76 01 a4 74 79 70 65 aa 63 61 6c 69 62 72
    61 74 65 64 a6 61 63 74 69 76 65 c3 a3 73 65 71
    09 a9 73 6d 6f 6f 74 68 69 6e 67 a6 6b 61 6c 6d
    61 6e`);
  const message = decodeServer(bytes);
  assert.deepEqual([message.type, message.active, message.seq, message.smoothing], ["calibrated", true, 9, "kalman"]);
});

test("calibrate carries its noise only when given (PROTOCOL.md §5.1.3)", () => {
  const points = new Float32Array([0, 1, 2, -0.5, 0.25, 1.5]);
  const plain = decode(encodeCalibrate(points));
  const noisy = decode(encodeCalibrate(points, 0.015625));
  assert.equal("noise" in plain, false);
  assert.equal(noisy.noise, 0.015625);
  assert.equal("noise" in decode(encodeCalibrate(points, Number.NaN)), false);
});

// PROTOCOL.md §10.4's calibrate with the left eye closed, after its map's header byte (86:
// six keys; 87 with a seventh, the blink contrast, after these).
const CLOSED_EYE_CALIBRATE = `a1 76 01 a4 74 79 70 65 a9 63 61 6c 69 62 72
    61 74 65 a6 70 6f 69 6e 74 73 83 a5 64 74 79 70
    65 a3 66 33 32 a5 73 68 61 70 65 92 01 03 a4 64
    61 74 61 c4 0c 00 00 00 00 00 00 00 00 00 00 00
    00 a5 72 65 73 65 74 c2 a5 6e 6f 69 73 65 cb 3f
    90 00 00 00 00 00 00 a6 62 6c 69 6e 6b 73 81 ac
    65 79 65 42 6c 69 6e 6b 4c 65 66 74 83 a5 64 74
    79 70 65 a3 66 33 32 a5 73 68 61 70 65 92 01 03
    a4 64 61 74 61 c4 0c 00 00 00 00 00 00 80 be 00
    00 00 00`;

test("calibrate with the closed eyes encodes to the bytes of PROTOCOL.md §10.4", () => {
  const expected = hex(`86 ${CLOSED_EYE_CALIBRATE}`);
  const blinks = { eyeBlinkLeft: new Float32Array([0, -0.25, 0]) };
  assert.deepEqual(encodeCalibrate(new Float32Array(3), 0.015625, blinks), expected);
  // Without the noise, or of another point count, the closed eyes are not sent.
  assert.equal("blinks" in decode(encodeCalibrate(new Float32Array(3), null, blinks)), false);
  const other = { eyeBlinkLeft: new Float32Array(6) };
  assert.equal("blinks" in decode(encodeCalibrate(new Float32Array(3), 0.01, other)), false);
});

test("ping encodes to the bytes of PROTOCOL.md §10.5", () => {
  const expected = hex(`84 a1 76 01 a4 74 79 70 65 a4 70 69 6e 67 a2 69
    64 01 a2 74 73 cb 40 0a 00 00 00 00 00 00`);
  assert.deepEqual(encodePing(1, 3.25), expected);
});

test("result of PROTOCOL.md §10.3 decodes to its weights", () => {
  const bytes = hex(`87 a1 76 01 a4 74 79 70 65 a6 72 65 73 75 6c 74
    a3 73 65 71 07 a2 74 73 cb 40 29 00 00 00 00 00
    00 a7 77 65 69 67 68 74 73 83 a5 64 74 79 70 65
    a3 66 33 32 a5 73 68 61 70 65 91 03 a4 64 61 74
    61 c4 0c 00 00 00 3f 00 00 80 3e 00 00 80 3e a7
    70 72 6f 63 5f 75 73 cc b4 a7 64 72 6f 70 70 65
    64 02`);
  const msg = decodeServer(bytes);
  assert.equal(msg.type, "result");
  assert.equal(msg.seq, 7);
  assert.equal(msg.ts, 12.5);
  assert.deepEqual(Array.from(msg.weights), [0.5, 0.25, 0.25]);
  assert.equal(msg.proc_us, 180);
  assert.equal(msg.dropped, 2);
});

test("error of PROTOCOL.md §10.7 decodes with its code", () => {
  const bytes = hex(`86 a1 76 01 a4 74 79 70 65 a5 65 72 72 6f 72 a4
    63 6f 64 65 cd 07 d2 a7 6d 65 73 73 61 67 65 af
    6e 65 65 64 20 4b 3d 32 20 70 6f 69 6e 74 73 a3
    73 65 71 08 a5 66 61 74 61 6c c2`);
  const msg = decodeServer(bytes);
  assert.equal(msg.code, ErrorCode.WRONG_POINT_COUNT);
  assert.equal(msg.message, "need K=2 points");
  assert.equal(msg.fatal, false);
});

test("f16 expands exactly, including subnormals and signs", () => {
  // 1.0, -2.0, 0.5, 65504 (max), 2^-24 (smallest subnormal), -0
  const bits = new Uint16Array([0x3c00, 0xc000, 0x3800, 0x7bff, 0x0001, 0x8000]);
  assert.deepEqual(Array.from(halfToFloat(bits)), [1, -2, 0.5, 65504, 2 ** -24, -0]);
});

test("f16 array data at an odd offset decodes little-endian", () => {
  const backing = new Uint8Array(5);
  backing.set([0x00, 0x3c, 0x00, 0xc0], 1);
  const { data } = arrayFromWire({ dtype: "f16", shape: [2], data: backing.subarray(1) }, { ndim: 1 });
  assert.deepEqual(Array.from(data), [1, -2]);
});

test("array with a wrong data length is refused with INVALID_ARRAY", () => {
  assert.throws(
    () => arrayFromWire({ dtype: "f32", shape: [2], data: new Uint8Array(4) }),
    (err) => err instanceof ProtocolError && err.code === ErrorCode.INVALID_ARRAY,
  );
});

test("non-finite weights are refused with NON_FINITE", () => {
  const data = new Uint8Array(new Float32Array([NaN]).buffer);
  assert.throws(
    () => arrayFromWire({ dtype: "f32", shape: [1], data }),
    (err) => err instanceof ProtocolError && err.code === ErrorCode.NON_FINITE,
  );
});

test("a message of another version is refused with UNSUPPORTED_VERSION", () => {
  // {"v": 2, "type": "pong", "id": 1, "ts": 0}
  const bytes = hex("84 a1 76 02 a4 74 79 70 65 a4 70 6f 6e 67 a2 69 64 01 a2 74 73 00");
  assert.throws(
    () => decodeServer(bytes),
    (err) => err instanceof ProtocolError && err.code === ErrorCode.UNSUPPORTED_VERSION,
  );
});

test("truncated bytes are refused with MALFORMED", () => {
  assert.throws(
    () => decodeServer(hex("84 a1 76 01 a4 74 79")),
    (err) => err instanceof ProtocolError && err.code === ErrorCode.MALFORMED,
  );
});

const READY_MOVING = `87 a1 76 01 a4 74 79 70 65 a5 72 65 61 64 79 a7
  73 65 73 73 69 6f 6e a2 73 31 a3 72 69 67 86 a2
  69 64 a4 64 65 6d 6f a1 6d 02 a5 6e 61 6d 65 73
  92 a7 6e 65 75 74 72 61 6c a5 73 6d 69 6c 65 a1
  6b 02 a1 76 04 a6 6d 6f 76 69 6e 67 c4 08 01 00
  00 00 03 00 00 00 a6 6f 75 74 70 75 74 a6 6d 6f
  76 69 6e 67 a5 64 74 79 70 65 a3 66 31 36 a6 6c
  69 6d 69 74 73 80`;

test("ready of PROTOCOL.md §10.12 decodes to the moving vertices' indices", () => {
  const msg = decodeServer(hex(READY_MOVING));
  assert.equal(msg.output, "moving");
  assert.deepEqual(Array.from(msg.rig.moving), [1, 3]);
});

test("a moving result of PROTOCOL.md §10.12 lands on the moving vertices of the mesh", () => {
  const ready = decodeServer(hex(READY_MOVING));
  const result = decodeServer(
    hex(`87 a1 76 01 a4 74 79 70 65 a6 72 65 73 75 6c 74
      a3 73 65 71 07 a2 74 73 cb 40 29 00 00 00 00 00
      00 a8 76 65 72 74 69 63 65 73 83 a5 64 74 79 70
      65 a3 66 31 36 a5 73 68 61 70 65 92 02 03 a4 64
      61 74 61 c4 0c 00 00 00 3c 00 40 00 b8 00 34 00
      3e a7 70 72 6f 63 5f 75 73 cc b4 a7 64 72 6f 70
      70 65 64 00`),
  );
  const positions = new Float32Array([9, 9, 9, 8, 8, 8, 7, 7, 7, 6, 6, 6]); // the neutral
  applyMoving(positions, ready.rig.moving, result.vertices);
  assert.deepEqual(Array.from(positions), [9, 9, 9, 0, 1, 2, 7, 7, 7, -0.5, 0.25, 1.5]);
});

test("ready refuses moving indices that do not increase", () => {
  const bytes = hex(READY_MOVING);
  bytes[bytes.indexOf(0x03, 80)] = 0x01; // moving [1, 1]
  assert.throws(() => decodeServer(bytes), (err) => err instanceof ProtocolError && err.code === ErrorCode.INVALID_FIELD);
});

test("a moving result of the wrong length is refused", () => {
  const moving = new Uint32Array([1, 3]);
  assert.throws(() => applyMoving(new Float32Array(12), moving, new Float32Array(3)), ProtocolError);
});

test("calibrate with the performer's own blink contrast encodes to the bytes of PROTOCOL.md §10.4", () => {
  const expected = hex(`87 ${CLOSED_EYE_CALIBRATE} ae 62 6c 69 6e 6b 5f 63 6f 6e 74 72 61
    73 74 92 cb 3f e0 00 00 00 00 00 00 cb 3f ec 00 00 00 00 00 00`);
  const blinks = { eyeBlinkLeft: new Float32Array([0, -0.25, 0]) };
  assert.deepEqual(encodeCalibrate(new Float32Array(3), 0.015625, blinks, [0.5, 0.875]), expected);
  // Without closed eyes to shape, no curve is sent.
  assert.equal("blink_contrast" in decode(encodeCalibrate(new Float32Array(3), 0.01, {}, [0.5, 0.875])), false);
});
