// What the page shows besides the character: connection state, fps, latency, weights and
// errors. DOM only; it never decides anything about connections.

const STATE_CLASSES = ["connecting", "live", "idle", "waiting", "failed"];
// Widest weight label; longer names are cut with an ellipsis.
const LABEL_MAX_CH = 16;
// More weights than this go in two columns of shorter rows (viewer.html's "many"):
// an ARKit character's 52-63 then fit a 540 px window.
const ONE_COLUMN_MAX = 24;

export class Hud {
  constructor(doc, { showStats }) {
    this.doc = doc;
    this.showStats = showStats;
    this.el = {
      hud: doc.getElementById("hud"),
      state: doc.getElementById("state"),
      detail: doc.getElementById("detail"),
      stats: doc.getElementById("stats"),
      error: doc.getElementById("error"),
      weights: doc.getElementById("weights"),
      character: doc.getElementById("character"),
    };
    if (this.el.hud) this.el.hud.hidden = !showStats;
    this.bars = [];
    this.lastWeightsPaint = 0;
  }

  /** kind: one of STATE_CLASSES; text: short label; detail: longer, optional. */
  state(kind, text, detail = "") {
    if (!this.el.state) return;
    this.el.state.classList.remove(...STATE_CLASSES);
    this.el.state.classList.add(kind);
    this.el.state.textContent = text;
    if (this.el.detail) this.el.detail.textContent = detail;
  }

  /** A problem the user must act on: shown on every page, the overlay too. */
  error(text) {
    this.el.error.textContent = text;
    this.el.error.hidden = false;
  }

  clearError() {
    this.el.error.hidden = true;
    this.el.error.textContent = "";
  }

  /** The character file's description: format, name, authors, licence (VRM meta). */
  character(text) {
    if (!this.el.character) return;
    this.el.character.textContent = text;
    this.el.character.hidden = !text;
  }

  stats(s) {
    if (!this.el.stats) return;
    const ms = (v) => (v === null ? "–" : `${v.toFixed(1)} ms`);
    const latencyLabel = s.mode === "demo" ? "latency" : "age";
    // Capture → drawn, when the publisher stamps its frames (PROTOCOL.md §5.4).
    const glass = s.glassMs === null || s.glassMs === undefined ? "" : `capture→drawn ${ms(s.glassMs)} · `;
    this.el.stats.textContent =
      `${s.fps.toFixed(1)} fps · ${glass}${latencyLabel} ${ms(s.latencyMs)} · rtt ${ms(s.rttMs)} · ` +
      `frames ${s.frames} · dropped ${s.dropped} · connects ${s.connects}`;
  }

  names(names) {
    if (!this.el.weights) return;
    this.el.weights.replaceChildren();
    // One label column as wide as the longest name (up to LABEL_MAX_CH, then "…" with the
    // full name on hover); each bar lives in its own track beside it, so it cannot reach
    // into the labels however large the weight.
    const longest = names.reduce((n, name) => Math.max(n, name.length), 1);
    this.el.weights.style.setProperty("--label-ch", `${Math.min(longest, LABEL_MAX_CH)}ch`);
    const many = names.length > ONE_COLUMN_MAX;
    this.el.weights.classList.toggle("many", many);
    this.doc.body.classList.toggle("many-weights", many && this.showStats);
    this.bars = names.map((name) => {
      const row = this.doc.createElement("div");
      row.className = "weight";
      const label = this.doc.createElement("span");
      label.textContent = name;
      label.title = name;
      const track = this.doc.createElement("b");
      const bar = this.doc.createElement("i");
      track.append(bar);
      row.append(label, track);
      this.el.weights.append(row);
      return bar;
    });
  }

  /** Paint weight bars, at most ~15 times a second (the DOM is slower than the canvas). */
  weights(weights) {
    if (!this.showStats || !this.bars.length) return;
    const now = performance.now();
    if (now - this.lastWeightsPaint < 66) return;
    this.lastWeightsPaint = now;
    for (let i = 0; i < this.bars.length && i < weights.length; i++) {
      // The track is |w| = 1.5 wide: weights past it stop at its end.
      const w = Math.max(-1.5, Math.min(1.5, weights[i]));
      this.bars[i].style.width = `${(Math.abs(w) / 1.5) * 100}%`;
      this.bars[i].classList.toggle("negative", w < 0);
    }
  }
}
