// Entry point of /perform: camera -> face mesh -> the layout's feature points (head pose
// and distance removed) -> published on the channel, with the head pose as the frame's
// `head` (headpose.js); the character's live pose beside
// the camera; the calibration walk-through (studio.js). Publishes window.facecastStats.

import { Link } from "../link.js";
import { authHeaders, socketTarget } from "../params.js";
import { encodeCalibrate, encodeHello, ErrorCode, errorName } from "../protocol.js";
import { metaText } from "../character.js";
import { FaceView } from "../scene.js";
import { cameraFrames, drawPoints, openCamera } from "./camera.js";
import { drives, eyeOpenness, headAngles } from "./facemesh.js";
import { encodePerformFrame } from "./headpose.js";
import { readPerformParams } from "./params.js";
import { FacePipeline, LAYOUT as layout } from "./pipeline.js";
import { Studio } from "./studio.js";
import { Rolling } from "./timing.js";
const K = layout.features.length;
const CHIN = layout.feature_names.indexOf("chin"); // shown live (the layout's last point no more)
// Newest frame only at the publisher's socket: a frame is sent only when the socket holds
// nothing unsent, so at most the frame being sent waits there; a stalled socket drops frames
// (counted in `skipped`) instead of queueing them (was 64 KiB: ~140 frames, 4 s at 30 fps).
const MAX_BUFFERED_BYTES = 1;
const WINDOW = 120; // frames in the rolling timing statistics
const DRAW_SHARE = 0.1; // of the page's time the character's drawing may block it

/** Counters for people and tests (tests wait on them instead of sleeping). */
const stats = {
  page: "perform",
  layout: layout.name,
  backend: null,
  backendFeatures: null, // wasm: {simd, threads}, as loaded
  track: "starting", // starting | loading | tracking | no-camera | failed
  trackDetail: "",
  publish: "off", // off | connecting | live | waiting | failed | unsuitable
  publishDetail: "",
  error: null,
  tracked: 0, // frames the model ran on
  withFace: 0, // of those, frames with a face
  faces: 0, // faces in the last frame
  faceFound: false,
  trackFps: 0,
  modelMs: null, // model time per frame (mean over the window)
  firstModelMs: null, // the first frame's model time (WebGL: shader compilation)
  published: 0, // frames sent
  heldForNeutral: 0, // frames not sent: a generic rig waits for the performer's neutral
  skipped: 0, // frames not sent: socket backed up
  publishFps: 0,
  seq: null,
  results: 0, // results (weights) received back for our frames
  latencyMs: null, // landmarks ready -> frame handed to the socket (mean, p95, max)
  latencyP95Ms: null,
  latencyMaxMs: null,
  overlayMs: null, // drawing the points over the camera image (mean)
  addedMs: null, // everything facecast adds per frame (normalise, encode, send, draw), mean
  addedP95Ms: null,
  renderMs: null, // drawing the character (three.js; the GPU's work, or SwiftShader's), mean
  waitMs: null, // waiting for the camera's next frame once the last was tracked (mean)
  drawn: 0, // times the character was drawn
  poses: 0, // weights applied to the character (live results, or an example the studio shows)
  posesDrawn: 0, // of those, how many were applied before the last finished draw began
  drawCostMs: null, // what a draw of the character blocks the page: draw -> next task (mean)
  frameSource: null, // "processor" (MediaStreamTrackProcessor) or "video" (frame callbacks)
  captureSource: null, // where frames' capture times come from (camera.js CaptureTimes)
  cameraFrames: 0, // frames the camera's <video> presented (requestVideoFrameCallback's count)
  points: null, // the last tracked points, K*3 (a rig of an earlier count gets the first rigK)
  rigK: null, // the points a frame the connected rig takes (K, or the layout's earlier count)
  head: null, // {yaw, pitch, roll} of the last frame, degrees
  eyes: null,
  clockOffsetMs: 0, // the server's clock − this page's, as the link estimates it (§5.4)
  clockRttMs: null, // the round trip of the pong that estimate comes from
  rebased: false, // a generic rig re-based on the performer's captured neutral (calibrated)
  smoothing: null, // the server's filter of the points ("kalman", "one-euro"; null: none)
  neutralNoise: null, // σ of the neutral capture's held frames, sent with the calibrate
  closedEyes: [], // the captured closed eyes sent with it (eyeBlinkLeft / eyeBlinkRight)
  blinkContrast: null, // the performer's own blink curve sent with them (?blink=), or null
  calibrateSentAt: null, // frames published before the last calibrate was sent
  rig: null,
  channel: null,
  character: null, // the rig's character file as shown: {format, meshes, vrm, bound, head, meta}
};
window.facecastStats = stats;

const $ = (id) => document.getElementById(id);

function setTrack(kind, text, detail = "") {
  stats.track = kind;
  stats.trackDetail = detail;
  paintState($("track-state"), kind === "tracking" ? (stats.faceFound ? "live" : "idle") : kind === "failed" || kind === "no-camera" ? "failed" : "connecting", text);
  $("track-detail").textContent = detail;
}

function setPublish(kind, text, detail = "") {
  stats.publish = kind;
  stats.publishDetail = detail;
  const cls = { live: "live", waiting: "waiting", connecting: "connecting", failed: "failed", unsuitable: "failed" }[kind] || "idle";
  paintState($("publish-state"), cls, text);
  $("publish-detail").textContent = detail;
}

function paintState(el, cls, text) {
  el.className = `state ${cls}`;
  el.textContent = text;
}

function fatal(message) {
  stats.error = message;
  $("error").textContent = message;
  $("error").hidden = false;
}

/** What a 401/403/4xx problem means on this page, naming the role the token lacks. */
function problemText(response, problem, role, what) {
  const detail = problem.detail || response.statusText;
  if (response.status === 401) return `the token is not accepted (401 ${problem.code || "unauthorized"}): cannot ${what}. ${detail}`;
  if (response.status === 403 && problem.code === "performer_forbidden") {
    return `the token is bound to other performers: it may not ${what} as this one (403 performer_forbidden: ${detail})`;
  }
  if (response.status === 403) {
    return `the token lacks the role ${role} (or admin) needed to ${what} (403 ${problem.code || "forbidden"}: ${detail})`;
  }
  return `${response.status} ${problem.code || ""}: ${detail}`.trim();
}

async function fetchOk(params, path, what) {
  const response = await fetch(`${params.server}${path}`, { headers: authHeaders(params) });
  if (!response.ok) {
    const problem = await response.json().catch(() => ({}));
    const error = new Error(problemText(response, problem, "viewer", what));
    error.code = problem.code;
    throw error;
  }
  return response;
}

/**
 * Show the rig's character file as uploaded when it has one (its licence permitting),
 * else the rig's model.glb. Returns {names: the expressions (no neutral), bindNames: the
 * names the view takes weights in before the rig's `ready`}.
 */
async function loadModel(params, view) {
  const rigPath = `/v1/rigs/${encodeURIComponent(params.rig)}`;
  const what = `load the character of rig ${params.rig}`;
  const described = await (await fetchOk(params, rigPath, what)).json();
  const character = described.character;
  if (character) {
    view.setCharacterStatus("loading");
    try {
      const glb = await (await fetchOk(params, character.url, what)).arrayBuffer();
      const shown = await view.loadCharacter(glb, character);
      stats.character = { format: character.format, meta: character.meta, ...shown };
      $("stage-meta").textContent =
        metaText(character.meta, character.format) + (shown.vrmError ? " — shown as plain glTF (three-vrm refused it)" : "");
      return { names: described.names.filter((n) => n !== "neutral"), bindNames: described.names };
    } catch (err) {
      if (err.code !== "character_not_redistributable") {
        view.setCharacterStatus("error");
        throw err;
      }
      stats.character = { format: character.format, meta: character.meta, withheld: err.message };
      $("stage-meta").textContent = `${metaText(character.meta, character.format)} — not shown: its licence forbids redistribution to viewers without a token`;
    }
  }
  const model = await view.load(await (await fetchOk(params, `${rigPath}/model.glb`, what)).arrayBuffer());
  return { names: model.names, bindNames: model.names };
}

async function main() {
  let params;
  try {
    params = readPerformParams(window.location.href);
  } catch (err) {
    fatal(`Bad page URL: ${err.message}`);
    setTrack("failed", "not started", err.message);
    return;
  }
  stats.rig = params.rig;
  stats.channel = params.channel;

  const view = new FaceView($("stage"), { controls: false });
  // Tests (and the curious) read what is shown and how it is posed (FaceView.characterState).
  window.characterState = () => view.characterState();
  let names = [];
  let live = true; // the view follows the server's weights (else: showing a target example)
  // The view takes weights in one named order (FaceView.bindWeights: the GLB leaves out the
  // neutral): the rig's, from its `ready`, once both it and the model are here; until then
  // the model's own target names, so the studio can pose the character before publishing.
  let rigNames = null;
  let weightNames = [];
  let bindNames = [];
  const bindView = () => {
    if (!view.loaded) return;
    if (rigNames && view.bindWeights(rigNames)) weightNames = rigNames;
    else if (view.bindWeights(bindNames)) weightNames = bindNames;
  };
  const showWeights = (weights) => {
    view.setWeights(weights);
    view.dirty = true;
    stats.poses += 1;
  };
  const studio = new Studio(document, {
    stats,
    params,
    layoutName: layout.name,
    authHeaders: () => authHeaders(params),
    problemText,
    performHref: (rig) => {
      const url = new URL(window.location.href);
      url.searchParams.set("rig", rig);
      return url.toString();
    },
    showExample(name) {
      live = false;
      const weights = new Float32Array(weightNames.length);
      const i = weightNames.indexOf(name);
      if (i >= 0) weights[i] = 1;
      if (view.loaded) showWeights(weights);
    },
    showLive() {
      live = true;
    },
    neutralCaptured(points, noise) {
      neutral = Float32Array.from(points.flat());
      neutralNoise = noise;
      stats.neutralNoise = noise;
      rebase(link);
    },
    keyCaptured(name, points) {
      // The walk-through's closed eyes go with the neutral: the server reads them as closed
      // on the re-based rig (PROTOCOL.md §5.1.3 blinks), so a quick blink reads whole.
      if (!CLOSED_EYES.includes(name)) return;
      closedEyes[name] = Float32Array.from(points.flat());
      rebase(link);
    },
  });
  const modelLoad = loadModel(params, view)
    .then((model) => {
      names = model.names;
      bindNames = model.bindNames;
      bindView();
      studio.setNames(names);
      $("stage-label").textContent = `character · ${params.rig}`;
    })
    .catch((err) => {
      $("stage-label").textContent = `character not loaded: ${err.message}`;
      stats.modelError = err.message;
    });

  // Publishing: the channel's publisher session; tracking goes on whatever happens here.
  let publishing = false;
  // Generic first: a rig that is not the performer's own (no "@performer") is re-based on
  // the performer's captured neutral (PROTOCOL.md §5.1.3), on every connection, and gets
  // no frame until it is (``heldForNeutral`` counts the frames held back).
  const generic = !params.rig.includes("@");
  const NEUTRAL_FIRST =
    `rig ${params.rig} is not fitted on your face: press Calibrate and capture your neutral ` +
    "first; until then no frame is published (the character would be distorted)";
  let neutral = null;
  // The points the rig takes: K, or an earlier version's count of this layout (its prefix).
  let rigK = K;
  // The landmark noise of the neutral's held frames: with it the server re-bases the rig
  // noise-aware and bounded (weights in [0, 1]), never extrapolating for viewers.
  let neutralNoise = null;
  // The performer's captured closed eyes, by blink name: sent with the neutral.
  const CLOSED_EYES = ["eyeBlinkLeft", "eyeBlinkRight"];
  const closedEyes = {};
  const rebase = (l) => {
    if (!(neutral && publishing && generic)) return;
    const blinks = Object.fromEntries(Object.entries(closedEyes).map(([name, p]) => [name, p.subarray(0, rigK * 3)]));
    stats.closedEyes = neutralNoise === null ? [] : Object.keys(blinks);
    stats.blinkContrast = stats.closedEyes.length ? params.blinkContrast : null;
    stats.calibrateSentAt = stats.published;
    l.send(encodeCalibrate(neutral.subarray(0, rigK * 3), neutralNoise, blinks, params.blinkContrast));
  };
  // The server's filter, as the status says it ("", or ", Kalman-filtered").
  const filtered = () => (stats.smoothing ? `, ${stats.smoothing === "kalman" ? "Kalman" : stats.smoothing}-filtered` : "");
  let latencyEma = null;
  const link = new Link(socketTarget(params), {
    onPong() {
      stats.clockOffsetMs = link.clock.offsetMs;
      stats.clockRttMs = link.clock.rttMs;
    },
    onOpen(l) {
      setPublish("connecting", "opening session", `channel ${params.channel}, rig ${params.rig}`);
      // The server's auto filter (§5.1.1): on the performer's own rig (fitted with noise)
      // the Kalman from the start; on a generic one from the calibrate, with the
      // neutral's noise (§5.2.5). The viewers' jitter falls ~3x (README, option (a″)).
      const smoothing = params.smoothing === "off" ? null : { target: "points" };
      l.send(encodeHello({ rig: params.rig, output: "weights", dtype: "f32", smoothing }));
    },
    onState(kind, detail) {
      publishing = false;
      if (kind === "failed") {
        const forbidden = /FORBIDDEN|Not allowed/.test(detail);
        setPublish(
          "failed",
          "not publishing",
          forbidden ? `the token lacks the role publisher (or admin) needed to publish to ${params.channel}: ${detail}` : detail,
        );
      } else if (kind === "waiting") setPublish("waiting", "reconnecting", detail);
      else if (kind === "connecting") setPublish("connecting", detail);
    },
    onMessage(msg, l) {
      if (msg.type === "ready") {
        if (!drives(layout, msg.rig.k)) {
          l.fail("");
          setPublish(
            "unsuitable",
            "not publishing",
            `rig ${msg.rig.id} takes ${msg.rig.k} feature points, this page's layout gives ${K}: ` +
              "calibrate to make your own rig of this character, or open a rig fitted for this layout",
          );
          return;
        }
        // A rig fitted on the layout's earlier version takes its first k points (the
        // layout only grows by appending); its eyes have fewer points: re-capture for more.
        rigK = msg.rig.k;
        stats.rigK = rigK;
        stats.smoothing = typeof msg.smoothing === "string" ? msg.smoothing : null;
        l.healthy();
        rigNames = msg.rig.names;
        bindView();
        publishing = true;
        stats.rebased = false;
        if (generic && !neutral) {
          // Uncalibrated points far from the rig's neutral make its exact weights
          // extrapolate: every viewer would see a distorted character. Hold the frames.
          setPublish("waiting", "waiting for your neutral", NEUTRAL_FIRST);
        } else setPublish("live", `live · ${params.channel}`, `rig ${msg.rig.id}, ${rigK} points a frame${filtered()}`);
        rebase(l);
      } else if (msg.type === "calibrated") {
        stats.rebased = msg.active === true;
        if (typeof msg.smoothing === "string") stats.smoothing = msg.smoothing;
        if (stats.rebased) {
          // Which captured closed eyes went with it: those blinks read closed (§5.1.3 blinks).
          const curve = stats.blinkContrast ? `, read through ${stats.blinkContrast.join("–")}` : "";
          const eyes = stats.closedEyes.length ? ` and your closed eyes (${stats.closedEyes.join(", ")}${curve})` : "";
          setPublish("live", `live · ${params.channel}`, `rig ${params.rig} re-based on your neutral${eyes}, ${rigK} points a frame${filtered()}`);
        }
      } else if (msg.type === "result") {
        stats.results += 1;
        if (typeof msg.server_ts === "number") {
          const rtt = Date.now() - msg.server_ts * 1000;
          latencyEma = latencyEma === null ? rtt : 0.9 * latencyEma + 0.1 * rtt;
        }
        if (live && msg.weights && view.loaded && msg.weights.length === weightNames.length) showWeights(msg.weights);
        if (msg.head && view.loaded) view.setHead(msg.head.rotation);
      } else if (msg.type === "error") {
        const text = `${errorName(msg.code)}: ${msg.message}`;
        if (msg.code === ErrorCode.UNKNOWN_RIG) setPublish("failed", "not publishing", `unknown rig ${params.rig}: ${msg.message}`);
        else if (msg.code === ErrorCode.CHANNEL_BUSY) setPublish("waiting", "channel busy", `${text}; another performer publishes there`);
        else setPublish(stats.publish, $("publish-state").textContent, text);
      }
    },
  });
  link.start();

  // Camera and model.
  const video = $("video");
  setTrack("loading", "opening the camera");
  let stream;
  try {
    stream = await openCamera(video);
  } catch (err) {
    setTrack("no-camera", "no camera", err.message);
    fatal(err.message);
    return;
  }
  setTrack("loading", "loading the face model");
  const pipeline = new FacePipeline({ layout, backend: params.backend });
  try {
    stats.backend = await pipeline.load();
    stats.backendFeatures = pipeline.features;
  } catch (err) {
    setTrack("failed", "face model failed", err.message);
    fatal(`The face model did not load: ${err.message}`);
    return;
  }
  await modelLoad;

  const canvas = $("camera");
  canvas.width = video.videoWidth || 640;
  canvas.height = video.videoHeight || 480;
  $("camera-box").style.aspectRatio = `${canvas.width} / ${canvas.height}`;
  const ctx = canvas.getContext("2d");
  let drawnBox = null;
  const modelTimes = new Rolling(WINDOW);
  const latency = new Rolling(WINDOW);
  const overlay = new Rolling(WINDOW);
  const added = new Rolling(WINDOW);
  const render = new Rolling(WINDOW);
  const waiting = new Rolling(WINDOW);
  const drawCosts = new Rolling(WINDOW);
  const frameTimes = [];
  const publishTimes = [];
  let seq = 0;
  let lastPaint = 0;
  setTrack("tracking", "looking for a face");

  // The character is drawn on the browser's animation frames, never in the tracking loop,
  // and within a budget: without a GPU, Chromium reads the WebGL canvas back on the main
  // thread at the commit after each draw, waiting there for SwiftShader to finish it (100–
  // 250 ms a draw on these 2-core machines): drawn every frame, the character held the
  // tracker to a third of its rate. So each draw's cost (draw -> the next task after its
  // commit) is measured, and the next draw waits until that cost is at most DRAW_SHARE of
  // the time since: with a GPU (~1 ms) that is every animation frame; without, about one
  // draw a second (docs/perform.md, "Performance").
  const after = new MessageChannel();
  let drawnAt = null;
  let drawnPoses = 0;
  let nextDraw = 0;
  after.port1.onmessage = () => {
    const cost = performance.now() - drawnAt;
    drawCosts.push(cost);
    stats.drawn += 1;
    stats.posesDrawn = drawnPoses;
    nextDraw = drawnAt + cost / DRAW_SHARE;
    drawnAt = null;
  };
  const draw = () => {
    const now = performance.now();
    if (drawnAt === null && now >= nextDraw && view.loaded && view.dirty) {
      drawnPoses = stats.poses;
      view.render();
      render.push(performance.now() - now);
      drawnAt = now;
      after.port2.postMessage(null);
    }
    requestAnimationFrame(draw);
  };
  requestAnimationFrame(draw);

  // The rate is min(camera, 1 / model time): the next frame is asked for as soon as the
  // last is tracked (cameraFrames).
  const frames = cameraFrames(stream, video);
  stats.frameSource = frames.kind;
  for (;;) {
    const tWait = performance.now();
    let result;
    let capturedMs;
    try {
      const { frame, capturedMs: captured } = await frames.next();
      capturedMs = captured;
      waiting.push(performance.now() - tWait);
      try {
        result = frame ? await pipeline.trackFrame(frame) : await pipeline.track(video);
      } finally {
        if (frame) frame.close();
      }
    } catch (err) {
      setTrack("failed", "tracking failed", err.message);
      fatal(`Tracking failed: ${err.message}`);
      return;
    }
    const tLandmarks = performance.now();
    modelTimes.push(result.modelMs);
    if (stats.firstModelMs === null) stats.firstModelMs = result.modelMs;
    stats.tracked += 1;
    stats.faces = result.faces;
    frameTimes.push(tLandmarks);
    let sample = null;
    const { points } = result;
    if (points) {
      const head = headAngles(result.frame);
      const eyes = eyeOpenness(result.mesh, layout);
      if (publishing && generic && !stats.rebased) stats.heldForNeutral += 1;
      else if (publishing && link.bufferedAmount < MAX_BUFFERED_BYTES) {
        // The head pose goes in its own field (§5.3): the points stay pose-free. The
        // stamps (§5.4) are on the server's clock as the link estimates it.
        const clock = link.clock;
        const stamps = { captured: clock.toServer(capturedMs), tracked: clock.toServer(tLandmarks), sent: clock.toServer(performance.now()) };
        const sent = rigK === K ? points : points.subarray(0, rigK * 3);
        if (link.send(encodePerformFrame(seq, performance.now() / 1000, sent, result.head, stamps))) {
          stats.seq = seq;
          seq += 1;
          stats.published += 1;
          publishTimes.push(performance.now());
        }
      } else if (publishing) stats.skipped += 1;
      const tSent = performance.now();
      latency.push(tSent - tLandmarks);
      stats.withFace += 1;
      stats.faceFound = true;
      stats.points = Array.from(points);
      stats.head = head;
      stats.eyes = eyes;
      sample = { points: points.slice(), eyes, head };
    } else {
      stats.faceFound = false;
    }
    const tDraw = performance.now();
    drawnBox = drawPoints(ctx, result.face, drawnBox, layout);
    const tEnd = performance.now();
    overlay.push(tEnd - tDraw);
    added.push(tEnd - tLandmarks);
    studio.frame(sample);

    // Rolling rates over the last second.
    while (frameTimes.length && frameTimes[0] < tEnd - 1000) frameTimes.shift();
    while (publishTimes.length && publishTimes[0] < tEnd - 1000) publishTimes.shift();
    if (tEnd - lastPaint > 250) {
      lastPaint = tEnd;
      stats.trackFps = frameTimes.length;
      stats.publishFps = publishTimes.length;
      stats.modelMs = modelTimes.mean();
      stats.latencyMs = latency.mean();
      stats.latencyP95Ms = latency.quantile(0.95);
      stats.latencyMaxMs = latency.max();
      stats.overlayMs = overlay.mean();
      stats.addedMs = added.mean();
      stats.addedP95Ms = added.quantile(0.95);
      stats.serverLatencyMs = latencyEma;
      stats.renderMs = render.mean();
      stats.waitMs = waiting.mean();
      stats.drawCostMs = drawCosts.mean();
      stats.captureSource = frames.times.source;
      stats.cameraFrames = frames.times.presented;
      paintStats(result);
    }
  }
}

function paintStats(result) {
  const faceText =
    result.faces === 0 ? "no face in view" : result.faces > 1 ? `${result.faces} faces: tracking the largest` : "face found";
  setTrack("tracking", faceText, stats.head ? `head yaw ${stats.head.yaw.toFixed(0)}° pitch ${stats.head.pitch.toFixed(0)}° roll ${stats.head.roll.toFixed(0)}° · eyes ${stats.eyes.toFixed(2)}` : "");
  const fmt = (v, d = 2) => (v === null || v === undefined ? "–" : v.toFixed(d));
  $("stats").textContent = [
    `model ${stats.backend}${stats.backendFeatures?.simd ? " (SIMD)" : ""} · ${fmt(stats.modelMs, 0)} ms a frame`,
    `tracking ${stats.trackFps} fps (${stats.withFace}/${stats.tracked} frames with a face)`,
    `landmarks → publish ${fmt(stats.latencyMs)} ms (p95 ${fmt(stats.latencyP95Ms)}, max ${fmt(stats.latencyMaxMs)})`,
    `facecast per frame ${fmt(stats.addedMs)} ms (p95 ${fmt(stats.addedP95Ms)}; drawing ${fmt(stats.overlayMs)})`,
    `character render ${fmt(stats.renderMs, 1)} ms · server → back ${fmt(stats.serverLatencyMs, 0)} ms`,
  ].join("\n");
  const p = stats.points;
  $("published").textContent =
    stats.publish === "live"
      ? [
          `${stats.publishFps} frames/s · seq ${stats.seq ?? "–"} · ${stats.skipped} dropped`,
          `${K} points (${layout.name}, head pose removed, ≈ cm)${stats.rigK !== K ? `: the rig takes the first ${stats.rigK}` : ""}`,
          p && result.face ? `chin (${p.slice(3 * CHIN, 3 * CHIN + 3).map((v) => v.toFixed(2)).join(", ")})` : "face lost: nothing sent (viewers see face_lost)",
        ].join("\n")
      : "";
}

main().catch((err) => fatal(`Performer page error: ${err.message}`));
