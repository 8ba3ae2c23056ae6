// The calibration walk-through: neutral first, then each of the character's target
// examples shown posed on the character; capture ~1 s of each, redo or skip any, then
// fit the performer's own rig on the server. DOM and fetch; the math is in capture.js.

import { CAPTURE_LIMITS, captureDone, heldFrames, heldNoise, noiseText, summariseCapture } from "./capture.js";

export const CAPTURE_MS = 1000;
// A slow tracker (under capture.js's minFrames frames a second: a busy laptop, a software
// GPU) holds the capture on until it has those frames, up to this long, rather than be
// refused for too few frames every time.
export const CAPTURE_MAX_MS = 4000;

/**
 * host: {stats, params, layoutName, authHeaders(), problemText(response, problem, role, what),
 *        performHref(rigId), showExample(name), showLive(),
 *        neutralCaptured(points K×3, noise: σ of its held frames),
 *        keyCaptured(name, points K×3): any other accepted capture}
 */
export class Studio {
  constructor(doc, host) {
    this.host = host;
    this.el = Object.fromEntries(
      ["calibrate", "capture", "skip", "fit", "live-view", "prompt", "steps", "verdict", "report", "stage-label"].map(
        (id) => [id, doc.getElementById(id)],
      ),
    );
    this.doc = doc;
    this.steps = [];
    this.current = -1;
    this.recording = null; // {name, samples, seen, until, deadline, summary, resolve}
    this.stats = host.stats.calibration = { active: false, step: null, captures: {}, fit: null, fitError: null, noise: null };
    this.el.calibrate.addEventListener("click", () => this.start());
    this.el.capture.addEventListener("click", () => this.capture());
    this.el.skip.addEventListener("click", () => this.skip());
    this.el.fit.addEventListener("click", () => this.fit());
    this.el["live-view"].addEventListener("click", () => this.stop());
  }

  /** Called by the page when the character's names are known (model loaded). */
  setNames(names) {
    const others = names.filter((n) => n !== "neutral");
    this.steps = ["neutral", ...others].map((name) => ({ name, status: "pending", result: null }));
    this.renderSteps();
  }

  start() {
    if (!this.steps.length) {
      this.verdict("the character's model is not loaded: nothing to calibrate against", true);
      return;
    }
    this.stats.active = true;
    this.el["live-view"].disabled = false;
    this.goTo(0);
  }

  stop() {
    this.stats.active = false;
    this.current = -1;
    this.stats.step = null;
    this.el.capture.disabled = this.el.skip.disabled = true;
    this.el["live-view"].disabled = true;
    this.el["stage-label"].textContent = "character · live";
    this.el.prompt.textContent = "Live. Calibrate again to redo or add expressions.";
    this.renderSteps();
    this.host.showLive();
  }

  goTo(index) {
    this.current = index;
    const step = this.steps[index];
    this.stats.step = step.name;
    this.host.showExample(step.name);
    this.el["stage-label"].textContent = `target: ${step.name}`;
    this.el.prompt.textContent =
      step.name === "neutral"
        ? "Neutral: relax your face, look at the camera, then press Capture and hold still for a second."
        : `Make the character's “${step.name}” (shown), press Capture and hold it for a second.`;
    this.el.capture.disabled = false;
    this.el.skip.disabled = step.name === "neutral";
    this.renderSteps();
  }

  /** The page feeds every tracked frame here; a capture in progress keeps it. */
  frame(sample) {
    const rec = this.recording;
    if (!rec) return;
    rec.seen += 1;
    if (sample) rec.samples.push(sample);
    const now = performance.now();
    // Once its time is up with frames enough, whether blinks and outliers leave enough;
    // the capture's verdict when it ends here (made on these very frames).
    rec.summary =
      now >= rec.until && rec.samples.length >= CAPTURE_LIMITS.minFrames
        ? summariseCapture(rec.samples, rec.seen, rec.name, this.reference(rec.name))
        : null;
    if (captureDone(rec, now, CAPTURE_LIMITS, rec.summary)) {
      this.recording = null;
      rec.resolve(rec);
    }
  }

  /** What a capture of `name` is checked against: the accepted neutral's, or null. */
  reference(name) {
    const neutral = this.steps[0];
    return name !== "neutral" && neutral.status === "ok" ? neutral.result : null;
  }

  async capture() {
    if (this.current < 0 || this.recording) return;
    const step = this.steps[this.current];
    this.el.capture.disabled = this.el.skip.disabled = true;
    this.verdict(`capturing ${step.name}… hold it`);
    const rec = await new Promise((resolve) => {
      const start = performance.now();
      this.recording = {
        name: step.name, samples: [], seen: 0, until: start + CAPTURE_MS, deadline: start + CAPTURE_MAX_MS, summary: null, resolve,
      };
    });
    const summary = rec.summary ?? summariseCapture(rec.samples, rec.seen, step.name, this.reference(step.name));
    step.result = summary;
    step.status = summary.ok ? "ok" : "refused";
    this.stats.captures[step.name] = {
      ok: summary.ok,
      reason: summary.reason,
      spread: summary.spread,
      head: summary.head,
      headMotion: summary.headMotion,
      eyes: summary.eyes,
      kept: summary.kept,
      blinks: summary.blinks,
      outliers: summary.outliers,
      frames: rec.samples.length,
    };
    if (summary.ok) {
      if (step.name === "neutral") this.host.neutralCaptured(summary.points, heldNoise(summary.held));
      else this.host.keyCaptured?.(step.name, summary.points);
      this.verdict(
        `${step.name}: held well — spread ${(summary.spread * 10).toFixed(2)} mm, head yaw ${summary.head.yaw.toFixed(0)}° ` +
          `pitch ${summary.head.pitch.toFixed(0)}° (moved ${summary.headMotion.toFixed(1)}°), ${summary.kept} frames kept, ` +
          `${summary.blinks} blink and ${summary.outliers} outlier frames out`,
      );
      const next = this.steps.findIndex((s, i) => i > this.current && s.status === "pending");
      if (next >= 0) this.goTo(next);
      else {
        this.el.capture.disabled = false;
        this.el.prompt.textContent = "All expressions done: redo or skip any, or fit your rig.";
      }
    } else {
      this.verdict(`${step.name} refused: ${summary.reason}`, true);
      this.el.capture.disabled = false;
      this.el.skip.disabled = step.name === "neutral";
    }
    this.renderSteps();
  }

  skip() {
    if (this.current <= 0) return; // neutral cannot be skipped
    this.steps[this.current].status = "skipped";
    this.steps[this.current].result = null;
    delete this.stats.captures[this.steps[this.current].name];
    const next = this.steps.findIndex((s, i) => i > this.current && s.status === "pending");
    if (next >= 0) this.goTo(next);
    else this.renderSteps();
  }

  async fit() {
    const accepted = this.steps.filter((s) => s.status === "ok");
    if (!accepted.some((s) => s.name === "neutral")) {
      this.verdict("capture the neutral first", true);
      return;
    }
    // The server measures the landmark noise from the held frames and fits with it.
    const held = heldFrames(accepted);
    const body = {
      layout: this.host.layoutName,
      points: Object.fromEntries(accepted.map((s) => [s.name, s.result.points])),
      held,
    };
    const { params } = this.host;
    const url = `${params.server}/v1/rigs/${encodeURIComponent(params.character)}/performer/${encodeURIComponent(params.performer)}`;
    this.el.fit.disabled = true;
    const frames = Object.values(held).reduce((n, f) => n + f.length, 0);
    this.verdict(`fitting ${params.character}@${params.performer} from ${accepted.length} expressions (noise from ${frames} held frames)…`);
    let response;
    try {
      response = await fetch(url, {
        method: "PUT",
        headers: { ...this.host.authHeaders(), "Content-Type": "application/json" },
        body: JSON.stringify(body),
      });
    } catch (err) {
      this.fitFailed(`the server is unreachable: ${err.message}; try again`);
      return;
    }
    const answer = await response.json().catch(() => ({}));
    if (!response.ok) {
      this.fitFailed(this.host.problemText(response, answer, "performer", "fit a performer rig"));
      return;
    }
    this.stats.fit = answer;
    this.stats.noise = answer.noise;
    this.stats.fitError = null;
    this.showReport(answer);
    this.el.fit.disabled = false;
  }

  fitFailed(text) {
    this.stats.fitError = text;
    this.verdict(`fit failed: ${text}`, true);
    this.el.fit.disabled = false;
  }

  showReport(answer) {
    const report = this.el.report;
    report.textContent = "";
    const warnings = answer.warnings || [];
    const summary = { ...answer };
    delete summary.warnings;
    const line = this.doc.createElement("div");
    const perform = this.host.performHref(answer.id);
    line.append(`Fitted ${answer.id}: `);
    const a = this.doc.createElement("a");
    a.href = perform;
    a.id = "perform-link";
    a.textContent = `perform on ${answer.id}`;
    line.append(a);
    report.append(line);
    for (const w of warnings) {
      const div = this.doc.createElement("div");
      div.className = "warning";
      div.textContent = `warning: ${typeof w === "string" ? w : JSON.stringify(w)}`;
      report.append(div);
    }
    const pre = this.doc.createElement("div");
    pre.textContent = JSON.stringify(summary, null, 1);
    report.append(pre);
    this.verdict(
      `rig ${answer.id} fitted${warnings.length ? ` with ${warnings.length} warning(s)` : ""}` +
        noiseText(answer),
    );
  }

  verdict(text, refused = false) {
    this.el.verdict.textContent = text;
    this.el.verdict.classList.toggle("refused", refused);
  }

  renderSteps() {
    const box = this.el.steps;
    box.textContent = "";
    this.steps.forEach((step, i) => {
      const b = this.doc.createElement("button");
      b.textContent = step.name;
      b.dataset.name = step.name;
      b.title = step.result?.reason || step.status;
      b.className = `${step.status}${i === this.current ? " current" : ""}`;
      b.addEventListener("click", () => {
        if (!this.stats.active) this.start();
        if (step.status === "skipped") step.status = "pending";
        this.goTo(i);
      });
      box.append(b);
    });
    this.el.fit.disabled = !this.steps.some((s) => s.name === "neutral" && s.status === "ok");
  }
}
