// The server's clock as this page estimates it (PROTOCOL.md §5.4): every stage stamp is on
// it, so a figure never mixes two clocks. Fed by the Link's ping/pong; no I/O here.
//
// A pong's midpoint guess is off by at most half its round trip, and a page whose main
// thread is busy (a face model's run, a software-GL draw's commit) handles its pongs late:
// their round trips are long and their error one-sided. So the sample kept is the one with
// the smallest bound on its error now — half its round trip, plus the two clocks' drift
// since it was taken (MAX_DRIFT) — however old: one quiet moment's pong serves for
// minutes. (A window of the last 8 pongs, 40 s, was replaced: on a viewer whose every
// draw held the page 1.3 s, all 8 were late and its offset was off by 650 ms.)

const MAX_DRIFT = 1e-4; // two clocks' rate difference at the most (100 ppm: crystal tolerances)

export class ServerClock {
  constructor() {
    this.best = null; // {rttMs, offsetMs, atMs}
    this.offsetMs = 0; // server clock − this page's epoch clock, ms
    this.rttMs = null; // round trip of the sample in use
  }

  /** The bound on a sample's error at `nowMs` (performance.now()). */
  static errorBoundMs(sample, nowMs) {
    return sample.rttMs / 2 + MAX_DRIFT * Math.max(0, nowMs - sample.atMs);
  }

  /** A pong: `sentMs`, `receivedMs` on performance.now(), `serverTs` the pong's server_ts (s). */
  sample(sentMs, receivedMs, serverTs) {
    if (typeof serverTs !== "number" || !Number.isFinite(serverTs)) return;
    const rttMs = receivedMs - sentMs;
    if (!(rttMs >= 0)) return;
    const offsetMs = serverTs * 1000 - (performance.timeOrigin + (sentMs + receivedMs) / 2);
    const fresh = { rttMs, offsetMs, atMs: receivedMs };
    const bound = ServerClock.errorBoundMs;
    if (this.best === null || bound(fresh, receivedMs) <= bound(this.best, receivedMs)) this.best = fresh;
    this.offsetMs = this.best.offsetMs;
    this.rttMs = this.best.rttMs;
  }

  /** A performance.now() time (ms) as the server's clock, seconds since the Unix epoch. */
  toServer(perfMs) {
    return (performance.timeOrigin + perfMs + this.offsetMs) / 1000;
  }
}
