// Page URL parsing and the WebSocket target it leads to (PROTOCOL.md §2.1, §2.2).
import assert from "node:assert/strict";
import { test } from "node:test";

import { authHeaders, ParamError, readParams, socketTarget } from "../src/params.js";

test("defaults: demo mode on the page's own server, rig demo, f32 weights", () => {
  const p = readParams("http://127.0.0.1:8000/viewer", "viewer");
  assert.equal(p.mode, "demo");
  assert.equal(p.server, "http://127.0.0.1:8000");
  assert.deepEqual([p.rig, p.output, p.dtype], ["demo", "weights", "f32"]);
  assert.deepEqual(socketTarget(p), { url: "ws://127.0.0.1:8000/v1/stream", protocols: ["facecast.v1"] });
});

test("channel mode watches the channel with rig, output and dtype in the query", () => {
  const p = readParams("https://example.org/overlay?channel=main%20stage&rig=cat&output=vertices&dtype=f16", "overlay");
  assert.equal(p.mode, "watch");
  assert.equal(
    socketTarget(p).url,
    "wss://example.org/v1/channels/main%20stage/watch?rig=cat&output=vertices&dtype=f16",
  );
});

test("a performer's rig id (character@performer) is a rig id", () => {
  const p = readParams("http://h/viewer?channel=live&rig=ict%40alice", "viewer");
  assert.equal(p.rig, "ict@alice");
  assert.throws(() => readParams("http://h/viewer?rig=ict@alice@bob", "viewer"), ParamError);
  assert.throws(() => readParams("http://h/viewer?rig=ict@", "viewer"), ParamError);
});

test("a token travels as the bearer subprotocol and as a Bearer header", () => {
  const p = readParams("http://h/viewer?token=s3cr3t-_.", "viewer");
  assert.deepEqual(socketTarget(p).protocols, ["facecast.v1", "facecast.bearer.s3cr3t-_."]);
  assert.deepEqual(authHeaders(p), { Authorization: "Bearer s3cr3t-_." });
});

test("a token a subprotocol cannot carry goes in the query string instead", () => {
  const p = readParams("http://h/viewer?token=a%20b", "viewer");
  const target = socketTarget(p);
  assert.deepEqual(target.protocols, ["facecast.v1"]);
  assert.equal(target.url, "ws://h/v1/stream?token=a%20b");
});

test("another server can be named; its path prefix is kept", () => {
  const p = readParams("http://page/viewer?server=https://api.example.org/facecast/", "viewer");
  assert.equal(p.server, "https://api.example.org/facecast");
  assert.equal(socketTarget(p).url, "wss://api.example.org/facecast/v1/stream");
});

for (const query of ["output=mesh", "dtype=f64", "width=5", "height=x", "rig=../x", "channel=a&demo", "server=ftp://x"]) {
  test(`bad parameter ${query} is refused with a message`, () => {
    assert.throws(() => readParams(`http://h/viewer?${query}`, "viewer"), ParamError);
  });
}

test("the performer page publishes to its channel; a performer's own rig id is accepted", async () => {
  const { readPerformParams } = await import("../src/perform/params.js");
  const p = readPerformParams("http://h:1/perform?channel=live%201&rig=cat@ann&performer=ann&token=tk");
  assert.deepEqual([p.mode, p.rig, p.character, p.performer], ["publish", "cat@ann", "cat", "ann"]);
  assert.deepEqual(socketTarget(p), { url: "ws://h:1/v1/channels/live%201/publish", protocols: ["facecast.v1", "facecast.bearer.tk"] });
  assert.throws(() => readPerformParams("http://h/perform?rig=cat"), /channel=NAME is required/);
  assert.throws(() => readPerformParams("http://h/perform?channel=c&performer=a/b"), /performer must be/);
  assert.equal(p.backend, "wasm");
  assert.equal(readPerformParams("http://h/perform?channel=c&backend=webgl").backend, "webgl");
  assert.throws(() => readPerformParams("http://h/perform?channel=c&backend=webgpu"), /backend must be/);
  assert.equal(p.smoothing, "auto");
  assert.equal(readPerformParams("http://h/perform?channel=c&smoothing=off").smoothing, "off");
  assert.throws(() => readPerformParams("http://h/perform?channel=c&smoothing=kalman"), /smoothing must be auto or off/);
  assert.equal(p.blinkContrast, null);
  assert.deepEqual(readPerformParams("http://h/perform?channel=c&blink=0.5,0.9").blinkContrast, [0.5, 0.9]);
  for (const bad of ["0.9,0.5", "0.5", "0.5,", "a,b", "0.5,1.2", "-0.1,0.5", "0.5,0.5,0.9"]) {
    assert.throws(() => readPerformParams(`http://h/perform?channel=c&blink=${bad}`), /blink must be LOW,HIGH/, bad);
  }
  assert.throws(() => readParams("http://h/viewer?rig=cat@", "viewer"), ParamError);
});

test("the demo stream may ask for the moving vertices only, a channel may not", () => {
  assert.equal(readParams("https://example.org/viewer?output=moving&dtype=f16", "viewer").output, "moving");
  assert.throws(() => readParams("https://example.org/viewer?channel=stage&output=moving", "viewer"), ParamError);
});
