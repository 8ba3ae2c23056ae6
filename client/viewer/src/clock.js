// The server's clock as this page estimates it (PROTOCOL.md §5.4): every stage stamp is on
// it, so a figure never mixes two clocks. Fed by the Link's ping/pong; no I/O here.

const KEEP = 8; // recent samples; the one of the shortest round trip wins (NTP's filter)

export class ServerClock {
  constructor() {
    this.samples = []; // [{rttMs, offsetMs}]
    this.offsetMs = 0; // server clock − this page's epoch clock, ms
    this.rttMs = null; // round trip of the sample in use
  }

  /** A pong: `sentMs`, `receivedMs` on performance.now(), `serverTs` the pong's server_ts (s). */
  sample(sentMs, receivedMs, serverTs) {
    if (typeof serverTs !== "number" || !Number.isFinite(serverTs)) return;
    const rttMs = receivedMs - sentMs;
    if (!(rttMs >= 0)) return;
    const offsetMs = serverTs * 1000 - (performance.timeOrigin + (sentMs + receivedMs) / 2);
    this.samples.push({ rttMs, offsetMs });
    if (this.samples.length > KEEP) this.samples.shift();
    let best = this.samples[0];
    for (const s of this.samples) if (s.rttMs < best.rttMs) best = s;
    this.offsetMs = best.offsetMs;
    this.rttMs = best.rttMs;
  }

  /** A performance.now() time (ms) as the server's clock, seconds since the Unix epoch. */
  toServer(perfMs) {
    return (performance.timeOrigin + perfMs + this.offsetMs) / 1000;
  }
}
