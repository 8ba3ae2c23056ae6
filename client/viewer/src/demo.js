// Plays the server's demo performance as a streaming client: sends its frames to an open
// /v1/stream session at the performance's frame rate. Sends only; results go elsewhere.

import { encodeFrame } from "./protocol.js";

// Frames allowed in flight before the player skips one (PROTOCOL.md §8: do not send
// faster than results come back).
const MAX_IN_FLIGHT = 4;
const MAX_BUFFERED_BYTES = 1 << 20;

export class DemoPlayer {
  /** animation: {fps, frames, k, points}; start: seconds into the performance. */
  constructor(animation, { start = 0 } = {}) {
    this.animation = animation;
    this.start = start;
    this.timer = null;
    this.sentAt = new Map();
    this.seq = 0;
    this.lastResultSeq = -1;
  }

  /** Start sending into `link` (a fresh session: seq restarts at 0). */
  play(link) {
    this.stop();
    this.seq = 0;
    this.lastResultSeq = -1;
    this.sentAt.clear();
    const t0 = performance.now();
    const { fps, frames, k, points } = this.animation;
    let lastIndex = -1;
    this.timer = setInterval(() => {
      const elapsed = (performance.now() - t0) / 1000 + this.start;
      const index = Math.floor(elapsed * fps) % frames;
      if (index === lastIndex) return;
      lastIndex = index;
      if (this.seq - this.lastResultSeq > MAX_IN_FLIGHT || link.bufferedAmount > MAX_BUFFERED_BYTES) {
        return;
      }
      const frame = points.subarray(index * k * 3, (index + 1) * k * 3);
      const sentAt = performance.now();
      if (link.send(encodeFrame(this.seq, sentAt / 1000, frame))) {
        this.sentAt.set(this.seq, { sentAt, elapsed, index });
        this.seq += 1;
      }
    }, 1000 / fps / 2);
  }

  stop() {
    clearInterval(this.timer);
    this.timer = null;
  }

  /**
   * Account for the result of frame `seq`: {latencyMs, demoTime, index} (ms from sending
   * it to now; seconds into the performance, not wrapped; the performance's frame sent),
   * or null if the frame is not ours.
   */
  received(seq) {
    this.lastResultSeq = Math.max(this.lastResultSeq, seq);
    const sent = this.sentAt.get(seq);
    // Results can skip seqs (§8): forget everything up to this one.
    for (const key of this.sentAt.keys()) {
      if (key > seq) break;
      this.sentAt.delete(key);
    }
    if (sent === undefined) return null;
    return { latencyMs: performance.now() - sent.sentAt, demoTime: sent.elapsed, index: sent.index };
  }
}
