// Glass to glass on a viewer page (PROTOCOL.md §5.4): each result's stage stamps plus this
// page's received and drawn, the recent frames' capture → drawn latencies and per-stage
// figures for window.liveLatency(). Bounded (the last WINDOW frames); no DOM, no I/O.

const WINDOW = 600; // frames kept (20 s at 30 fps)
const MAX_MS = 10000; // a figure beyond 10 s is a wrong clock, not a latency: ignored
const PENDING = 8; // received, not yet drawn: more means drawing stopped (hidden tab)

/** The path's stages, each from one stamp to the next (names as in docs/viewer.md). */
export const STAGES = [
  ["track", "captured", "tracked"],
  ["publish", "tracked", "sent"],
  ["uplink", "sent", "server_in"],
  ["server", "server_in", "server_out"],
  ["downlink", "server_out", "received"],
  ["draw", "received", "drawn"],
];

function quantiles(values) {
  if (!values.length) return { n: 0, p50: null, p95: null, p99: null, max: null };
  const sorted = Float64Array.from(values).sort();
  const at = (q) => sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
  return { n: sorted.length, p50: at(0.5), p95: at(0.95), p99: at(0.99), max: sorted[sorted.length - 1] };
}

function finite(value) {
  return typeof value === "number" && Number.isFinite(value) ? value : null;
}

export class LiveLatency {
  constructor(clock, window = WINDOW) {
    this.clock = clock;
    this.window = window;
    this.frames = []; // drawn frames, oldest first: {seq, stamps (s), e2eMs}
    this.pending = []; // received, waiting for a draw
    this.received = 0; // results with stamps received
    this.drawnCount = 0; // of those, drawn
    this.superseded = 0; // received but replaced by a newer one before a draw
    this.lastSeq = null;
    this.seqGaps = 0; // frames the path lost before this page (gaps in seq)
    this.renders = []; // the recent draws' own time (render() call), ms
    this.costs = []; // what each draw held the page: render() to the next task after its commit, ms
  }

  /** A draw held the page `ms` (render() to the next task: without a GPU, the readback). */
  drawCost(ms) {
    this.costs.push(ms);
    if (this.costs.length > this.window) this.costs.shift();
  }

  /** A result arrived at `perfMs` (performance.now()); only results with stamps count. */
  receive(msg, perfMs) {
    if (typeof msg.seq === "number") {
      if (this.lastSeq !== null && msg.seq > this.lastSeq + 1) this.seqGaps += msg.seq - this.lastSeq - 1;
      if (this.lastSeq === null || msg.seq > this.lastSeq) this.lastSeq = msg.seq;
    }
    const s = msg.stamps;
    if (!s || typeof s !== "object") return;
    const stamps = {
      captured: finite(s.captured),
      tracked: finite(s.tracked),
      sent: finite(s.sent),
      server_in: finite(s.server_in),
      server_out: finite(msg.server_ts),
      received: this.clock.toServer(perfMs),
      drawn: null,
    };
    this.received += 1;
    // Drawn on arrival or at the next draw: what waits longer than PENDING frames was
    // never drawn (a hidden page draws nothing): counted, not kept.
    this.pending.push({ seq: msg.seq, stamps });
    while (this.pending.length > PENDING) {
      this.pending.shift();
      this.superseded += 1;
    }
  }

  /**
   * A draw was submitted at `perfMs` (taking `renderMs` itself): the newest pending frame
   * is what it shows.
   */
  drawn(perfMs, renderMs = null) {
    if (renderMs !== null) {
      this.renders.push(renderMs);
      if (this.renders.length > this.window) this.renders.shift();
    }
    if (!this.pending.length) return;
    const frame = this.pending.pop();
    this.superseded += this.pending.length;
    this.pending.length = 0;
    frame.stamps.drawn = this.clock.toServer(perfMs);
    const captured = frame.stamps.captured;
    const e2eMs = captured === null ? null : (frame.stamps.drawn - captured) * 1000;
    frame.e2eMs = e2eMs !== null && e2eMs >= 0 && e2eMs <= MAX_MS ? e2eMs : null;
    this.drawnCount += 1;
    this.frames.push(frame);
    if (this.frames.length > this.window) this.frames.shift();
  }

  /**
   * The recent frames' figures, in ms (what window.liveLatency() returns); with `detail`
   * also `records`, every kept frame's stamps (seconds, server clock) and capture → drawn.
   */
  report(detail = false) {
    const e2e = [];
    const stages = {};
    for (const [name] of STAGES) stages[name] = [];
    for (const f of this.frames) {
      if (f.e2eMs !== null) e2e.push(f.e2eMs);
      for (const [name, from, to] of STAGES) {
        const a = f.stamps[from];
        const b = f.stamps[to];
        if (a === null || b === null) continue;
        const ms = (b - a) * 1000;
        // A clock estimate off by a few ms makes a short hop negative: clamped to 0; a
        // figure beyond MAX_MS is a wrong clock: ignored.
        if (ms <= MAX_MS && ms >= -MAX_MS) stages[name].push(Math.max(0, ms));
      }
    }
    const out = {
      frames: e2e.length,
      latenciesMs: e2e.slice(-120),
      glassToGlass: quantiles(e2e),
      stages: {},
      received: this.received,
      drawn: this.drawnCount,
      superseded: this.superseded,
      seqGaps: this.seqGaps,
      clockOffsetMs: this.clock.offsetMs,
      clockRttMs: this.clock.rttMs,
      renderMs: quantiles(this.renders),
      drawCostMs: quantiles(this.costs),
    };
    if (detail) out.records = this.frames.map((f) => ({ seq: f.seq, e2eMs: f.e2eMs, ...f.stamps }));
    for (const [name] of STAGES) out.stages[name] = quantiles(stages[name]);
    return out;
  }

  /** p50 of the recent capture → drawn latencies (ms), for the HUD; null before any. */
  median() {
    const e2e = this.frames.slice(-60).map((f) => f.e2eMs).filter((v) => v !== null);
    return quantiles(e2e).p50;
  }
}
