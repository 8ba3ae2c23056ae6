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

test("the demo stream may ask for the moving vertices only, a channel may not", () => {
  assert.equal(readParams("https://example.org/viewer?output=moving&dtype=f16", "viewer").output, "moving");
  assert.throws(() => readParams("https://example.org/viewer?channel=stage&output=moving", "viewer"), ParamError);
});
