// Glass-to-glass figures (latency.js, clock.js) and the stamped frame's bytes (§10.16).
import assert from "node:assert/strict";
import { test } from "node:test";

import { ServerClock } from "../src/clock.js";
import { LiveLatency } from "../src/latency.js";
import { encodePerformFrame } from "../src/perform/headpose.js";

const hex = (text) => Uint8Array.from(text.trim().split(/\s+/), (b) => parseInt(b, 16));

test("a stamped frame encodes to the bytes of PROTOCOL.md §10.16", () => {
  const expected = hex(`86 a1 76 01 a4 74 79 70 65 a5 66 72 61 6d 65 a3
    73 65 71 07 a2 74 73 cb 40 29 00 00 00 00 00 00
    a6 70 6f 69 6e 74 73 83 a5 64 74 79 70 65 a3 66
    33 32 a5 73 68 61 70 65 92 02 03 a4 64 61 74 61
    c4 18 00 00 00 00 00 00 80 3f 00 00 00 40 00 00
    00 bf 00 00 80 3e 00 00 c0 3f a6 73 74 61 6d 70
    73 83 a8 63 61 70 74 75 72 65 64 cb 41 d9 54 fc
    40 08 00 00 a7 74 72 61 63 6b 65 64 cb 41 d9 54
    fc 40 10 00 00 a4 73 65 6e 74 cb 41 d9 54 fc 40
    14 00 00`);
  const points = new Float32Array([0, 1, 2, -0.5, 0.25, 1.5]);
  const stamps = { captured: 1700000000.125, tracked: 1700000000.25, sent: 1700000000.3125 };
  assert.deepEqual(encodePerformFrame(7, 12.5, points, null, stamps), expected);
});

test("the clock keeps the offset of the shortest round trip", () => {
  const clock = new ServerClock();
  const origin = performance.timeOrigin;
  // Server 250 ms ahead; a slow pong's midpoint guess is off by its asymmetry.
  clock.sample(1000, 1100, (origin + 1000 + 250 + 90) / 1000);
  clock.sample(2000, 2002, (origin + 2001 + 250) / 1000);
  clock.sample(3000, 3050, (origin + 3000 + 250 + 40) / 1000);
  assert.ok(Math.abs(clock.offsetMs - 250) < 0.01, `offset ${clock.offsetMs}`);
  assert.equal(clock.rttMs, 2);
  assert.ok(Math.abs(clock.toServer(5000) - (origin + 5250) / 1000) < 1e-5);
});

test("one quiet pong outlasts a run of late ones, until drift makes a new one better", () => {
  const clock = new ServerClock();
  const origin = performance.timeOrigin;
  clock.sample(1000, 1002, (origin + 1001 + 250) / 1000); // quiet: 2 ms round trip
  // Then 40 pongs 5 s apart, each handled 1.3 s late (a draw held the page): the old
  // window of 8 kept only these, 650 ms off.
  for (let i = 1; i <= 40; i++) {
    const sent = 1000 + 5000 * i;
    clock.sample(sent, sent + 1302, (origin + sent + 1 + 250) / 1000);
  }
  assert.ok(Math.abs(clock.offsetMs - 250) < 0.01, `offset ${clock.offsetMs}`);
  assert.equal(clock.rttMs, 2);
  // 201 s on, the quiet pong's bound (1 + 20.1 ms of drift) loses to a fresh 10 ms one (5).
  clock.sample(202000, 202010, (origin + 202005 + 251) / 1000);
  assert.ok(Math.abs(clock.offsetMs - 251) < 0.01, `offset ${clock.offsetMs}`);
  assert.equal(clock.rttMs, 10);
});

test("a pong without server_ts changes nothing", () => {
  const clock = new ServerClock();
  clock.sample(0, 1, undefined);
  clock.sample(0, 1, NaN);
  assert.equal(clock.offsetMs, 0);
});

function stamped(seq, capturedS, clock) {
  const at = (ms) => clock.toServer(ms);
  return { seq, server_ts: at(capturedS + 20), stamps: { captured: at(capturedS), tracked: at(capturedS + 10), sent: at(capturedS + 11), server_in: at(capturedS + 12) } };
}

test("capture to drawn and each stage come out of the stamps", () => {
  const clock = new ServerClock();
  const live = new LiveLatency(clock);
  for (let i = 0; i < 10; i++) {
    live.receive(stamped(i, 1000 * i, clock), 1000 * i + 25);
    live.drawn(1000 * i + 33);
  }
  const r = live.report();
  assert.equal(r.frames, 10);
  assert.ok(Math.abs(r.glassToGlass.p50 - 33) < 0.01);
  const near = (a, b) => Math.abs(a - b) < 0.01;
  assert.ok(near(r.stages.track.p50, 10) && near(r.stages.publish.p50, 1) && near(r.stages.uplink.p50, 1));
  assert.ok(near(r.stages.server.p50, 8) && near(r.stages.downlink.p50, 5) && near(r.stages.draw.p50, 8));
});

test("a capture from the future or the far past is not a figure, and a short hop clamps to 0", () => {
  const clock = new ServerClock();
  const live = new LiveLatency(clock);
  live.receive({ seq: 0, server_ts: clock.toServer(10), stamps: { captured: clock.toServer(5000), server_in: clock.toServer(11) } }, 12);
  live.drawn(13);
  live.receive({ seq: 1, server_ts: clock.toServer(30), stamps: { captured: clock.toServer(-60000) } }, 31);
  live.drawn(32);
  const r = live.report();
  assert.equal(r.frames, 0);
  assert.equal(r.glassToGlass.p50, null);
  assert.equal(r.stages.server.p50, 0); // server_in after server_out by 1 ms: clamped
});

test("results never drawn (a hidden page) stay bounded and are counted", () => {
  const clock = new ServerClock();
  const live = new LiveLatency(clock, 50);
  for (let i = 0; i < 5000; i++) live.receive(stamped(i, i, clock), i + 1);
  assert.ok(live.pending.length <= 8);
  assert.equal(live.superseded, 5000 - live.pending.length);
  for (let i = 0; i < 200; i++) {
    live.receive(stamped(5000 + i, i, clock), i + 1);
    live.drawn(i + 2);
  }
  assert.equal(live.frames.length, 50);
});

test("gaps in seq count the frames lost before the page", () => {
  const clock = new ServerClock();
  const live = new LiveLatency(clock);
  for (const seq of [0, 1, 4, 5, 9]) live.receive({ seq }, 0);
  assert.equal(live.report().seqGaps, 5);
});
