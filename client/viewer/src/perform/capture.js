// One calibration capture: ~1 s of normalised feature points -> a robust average, how well
// it was held, and whether to refuse it. Pure arithmetic on arrays, no DOM.

/** The bounds a capture must meet; every refusal names the bound it crossed. */
export const CAPTURE_LIMITS = Object.freeze({
  minFrames: 8, // frames with a face that a capture needs at the least
  minFoundShare: 0.6, // of the frames seen during the capture, the share with a face
  // The face frame's z axis leans back ~10° on a frontal face (its up vector runs from the
  // nose tip to the forehead), so pitch gets more room than yaw.
  maxYawDeg: 15, // the neutral: head turned left/right from facing the camera (median)
  maxPitchDeg: 25, // the neutral: head tilted up/down
  maxTurnDeg: 12, // other expressions: head turned away from where it was for the neutral
  maxHeadMotionDeg: 6, // any frame's head angles this far from the capture's median
  shutEyes: 0.12, // eye openness (lid gap / eye width) below this is eyes shut
  shutShare: 0.5, // other expressions: openness under this share of the neutral's is shut
  blinkShare: 0.6, // a frame whose openness is under this share of the capture's median is a blink
  outlierMads: 4, // frames this many MADs (scaled to σ) beyond the median distance are out
  maxSpread: 0.25, // layout units (≈ cm): held worse than this is a refusal, not a capture
});

/**
 * Whether a capture in progress has what it needs: its time (`until`) and the frames with a
 * face that a capture needs at the least, or, for a tracker too slow for those, its
 * `deadline` (the summary then says what was missing). `summary`, what `summariseCapture`
 * makes of the frames so far: one refused as `short` (too few frames, once blinks and
 * outliers are out) is held on for more, to the deadline: a tracker at 8 frames a second
 * lost one outlier of its 8 and was refused on every try, where a ninth frame would do.
 */
export function captureDone(recording, now, limits = CAPTURE_LIMITS, summary = null) {
  if (now >= recording.deadline) return true;
  if (now < recording.until || recording.samples.length < limits.minFrames) return false;
  return summary === null || !summary.short;
}

// Names of expressions made with the eyes shut: for those, shut eyes are the point.
const EYES_SHUT_NAMES = /blink|eyes?[_ -]?(closed?|shut)|sleep/i;

export function expectsEyesShut(name) {
  return EYES_SHUT_NAMES.test(name);
}

function median(values) {
  const sorted = Float64Array.from(values).sort();
  const n = sorted.length;
  if (!n) return NaN;
  return n % 2 ? sorted[(n - 1) / 2] : 0.5 * (sorted[n / 2 - 1] + sorted[n / 2]);
}

function headOf(samples) {
  const head = {};
  for (const axis of ["yaw", "pitch", "roll"]) head[axis] = median(samples.map((s) => s.head[axis]));
  return head;
}

function headTurnReason(head, reference, limits) {
  if (reference) {
    reference = reference.head;
    const turn = Math.hypot(head.yaw - reference.yaw, head.pitch - reference.pitch);
    if (turn > limits.maxTurnDeg) {
      return `head turned ${turn.toFixed(0)}° from where it was for the neutral (at most ${limits.maxTurnDeg}°): face the camera as then and redo`;
    }
    return null;
  }
  if (Math.abs(head.yaw) > limits.maxYawDeg) {
    return `head turned ${Math.abs(head.yaw).toFixed(0)}° to the side (at most ${limits.maxYawDeg}°): face the camera and redo`;
  }
  if (Math.abs(head.pitch) > limits.maxPitchDeg) {
    return `head tilted ${Math.abs(head.pitch).toFixed(0)}° up or down (at most ${limits.maxPitchDeg}°): face the camera and redo`;
  }
  return null;
}

/**
 * Summarise a capture.
 *
 * samples: [{points: Float32Array K*3, eyes: number, head: {yaw, pitch, roll} degrees}]
 *   (frames with a face)
 * seen: frames the tracker processed during the capture (with or without a face)
 * name: the expression being captured ("neutral" first)
 * reference: the neutral capture's {head, eyes} (null for the neutral itself)
 *
 * Returns {ok, reason, points: K×3 arrays (the robust average), spread (RMS per-coordinate
 * σ of the kept frames, layout units), held (the kept frames, in order, each K×3 arrays: the
 * server measures the landmark noise from them), kept, blinks, outliers, head, headMotion,
 * eyes, short (refused for too few frames alone: `captureDone` holds such a capture on)}.
 */
export function summariseCapture(samples, seen, name, reference = null, limits = CAPTURE_LIMITS) {
  // short: refused for too few frames alone, which more frames of the same would mend.
  const result = { ok: false, reason: null, points: null, spread: null, kept: 0, blinks: 0, outliers: 0, short: false };
  const found = samples.length;
  if (found < limits.minFrames || found < limits.minFoundShare * seen) {
    result.reason = `the face was found in ${found} of ${seen} frames: stay in view and redo`;
    result.short = found < limits.minFrames && found >= limits.minFoundShare * seen;
    return result;
  }
  const head = headOf(samples);
  result.head = head;
  result.headMotion = Math.max(
    ...samples.map((s) => Math.hypot(s.head.yaw - head.yaw, s.head.pitch - head.pitch, s.head.roll - head.roll)),
  );
  result.eyes = median(samples.map((s) => s.eyes));
  result.reason = headTurnReason(head, reference, limits);
  if (result.reason) return result;
  if (result.headMotion > limits.maxHeadMotionDeg) {
    result.reason = `head moved ${result.headMotion.toFixed(0)}° during the capture (at most ${limits.maxHeadMotionDeg}°): hold still and redo`;
    return result;
  }
  const shutWanted = expectsEyesShut(name);
  if (!shutWanted && result.eyes < limits.shutEyes) {
    result.reason = `eyes shut (openness ${result.eyes.toFixed(2)}, open is above ${limits.shutEyes}): open your eyes and redo`;
    return result;
  }
  if (!shutWanted && reference && result.eyes < limits.shutShare * reference.eyes) {
    result.reason =
      `eyes nearly shut (openness ${result.eyes.toFixed(2)} against ${reference.eyes.toFixed(2)} for the neutral): ` +
      "open your eyes as for the neutral and redo";
    return result;
  }
  // Blinks out (not for an eyes-shut expression), then frames far from the median shape.
  let kept = shutWanted ? samples : samples.filter((s) => s.eyes >= limits.blinkShare * result.eyes);
  result.blinks = found - kept.length;
  const k3 = samples[0].points.length;
  const centre = new Float64Array(k3);
  for (let j = 0; j < k3; j++) centre[j] = median(kept.map((s) => s.points[j]));
  const dist = kept.map((s) => {
    let sum = 0;
    for (let j = 0; j < k3; j++) sum += (s.points[j] - centre[j]) ** 2;
    return Math.sqrt(sum);
  });
  const med = median(dist);
  const mad = median(dist.map((d) => Math.abs(d - med))) * 1.4826;
  const cut = med + limits.outlierMads * Math.max(mad, 1e-6);
  const inliers = kept.filter((_, i) => dist[i] <= cut);
  result.outliers = kept.length - inliers.length;
  kept = inliers;
  result.kept = kept.length;
  if (kept.length < limits.minFrames) {
    result.reason = `only ${kept.length} steady frames (blinks ${result.blinks}, outliers ${result.outliers}): hold the expression and redo`;
    result.short = true;
    return result;
  }
  let variance = 0;
  const points = [];
  for (let k = 0; k < k3 / 3; k++) {
    const point = [];
    for (let c = 0; c < 3; c++) {
      const j = 3 * k + c;
      const values = kept.map((s) => s.points[j]);
      const m = median(values);
      point.push(m);
      variance += values.reduce((acc, v) => acc + (v - m) ** 2, 0) / values.length;
    }
    points.push(point);
  }
  result.points = points;
  result.spread = Math.sqrt(variance / k3);
  if (result.spread > limits.maxSpread) {
    result.reason = `held loosely (spread ${result.spread.toFixed(3)}, at most ${limits.maxSpread}): hold still and redo`;
    result.points = null;
    return result;
  }
  result.held = kept.map((s) => {
    const frame = [];
    for (let k = 0; k < k3 / 3; k++) frame.push([s.points[3 * k], s.points[3 * k + 1], s.points[3 * k + 2]]);
    return frame;
  });
  result.ok = true;
  return result;
}

/** Most captures whose held frames a fit sends (the neutral first): enough frames to
 * measure the noise, and the body well inside the server's 1 MiB capture limit. */
export const HELD_CAPTURES = 12;

/**
 * The capture body's `held` for the accepted captures [{name, result}]: each one's kept
 * frames, rounded to 1e-4 layout units (1 µm, far below any tracker's noise), for at most
 * HELD_CAPTURES of them. The server measures σ from them (SERVER.md, "Performers").
 */
export function heldFrames(accepted) {
  const round = (v) => Math.round(v * 1e4) / 1e4;
  return Object.fromEntries(
    accepted
      .filter((c) => c.result && c.result.ok && c.result.held && c.result.held.length >= 2)
      .slice(0, HELD_CAPTURES)
      .map((c) => [c.name, c.result.held.map((frame) => frame.map((p) => p.map(round)))]),
  );
}

/**
 * The landmark noise σ of a capture's held frames (K×3 arrays each, in order), layout
 * units: half the mean squared frame-to-frame step per coordinate, square-rooted — the
 * rule of facecast.rig.estimate_noise, so a face relaxing slowly is not counted. The
 * neutral's goes with the calibrate (PROTOCOL.md §5.1.3): the server re-bases a generic
 * rig noise-aware and bounded with it. 0 for fewer than 2 frames (a still image: 0 too).
 */
export function heldNoise(held) {
  if (!held || held.length < 2) return 0;
  let sum = 0;
  let count = 0;
  for (let f = 1; f < held.length; f++) {
    const a = held[f - 1];
    const b = held[f];
    for (let k = 0; k < b.length; k++) {
      for (let c = 0; c < 3; c++) {
        sum += (b[k][c] - a[k][c]) ** 2;
        count += 1;
      }
    }
  }
  return Math.sqrt(sum / count / 2);
}

/** How the fit's landmark noise was found, for the performer (layout units ≈ cm, shown in mm). */
export function noiseText(answer) {
  if (typeof answer.noise !== "number") return "";
  const mm = `${(answer.noise * 10).toFixed(2)} mm`;
  if (answer.noise_source === "held_frames") return `, landmark noise σ = ${mm} measured from ${answer.held_frames} held frames`;
  return `, landmark noise σ = ${mm}`;
}
