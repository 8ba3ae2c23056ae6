// Entry point of /viewer and /overlay: loads the rig's model, connects (demo stream or
// channel watch), applies results to the view and publishes window.facecastStats.

import { DemoPlayer } from "./demo.js";
import { Hud } from "./hud.js";
import { LiveLatency } from "./latency.js";
import { Link } from "./link.js";
import { authHeaders, readParams, socketTarget } from "./params.js";
import { decodeAnimation, encodeHello, ErrorCode, errorName } from "./protocol.js";
import { metaText } from "./character.js";
import { FaceView } from "./scene.js";

const RETRY_FIRST_MS = 250;
const RETRY_MAX_MS = 5000;

/** Counters for people and tests (tests wait on them instead of sleeping). */
const stats = {
  page: document.body.dataset.page,
  mode: null,
  state: "starting",
  detail: "",
  error: null,
  frames: 0, // results received
  appliedSeq: null, // the seq of the last result applied to the view (drawn, or already on screen)
  rendered: 0, // canvas redraws
  connects: 0,
  fps: 0,
  latencyMs: null,
  glassMs: null, // capture → drawn, p50 of the recent frames (channel mode, stamped frames)
  rttMs: null,
  seq: null,
  demoTime: null, // demo mode: seconds into the performance of the frame shown
  dropped: 0,
  channel: null,
  rig: null,
  character: null, // the rig's character file as shown: {format, meshes, vrm, bound, head, meta}
  head: null, // the last result's head rotation (x, y, z, w), channel mode
};
window.facecastStats = stats;

/** An error another attempt would only repeat (bad token, unknown rig, bad URL). */
class Permanent extends Error {
  constructor(message, code = null) {
    super(message);
    this.code = code;
  }
}

const hud = new Hud(document, { showStats: stats.page === "viewer" });

function setState(kind, text, detail = "") {
  stats.state = kind;
  stats.detail = detail;
  hud.state(kind, text, detail);
}

function failed(message) {
  stats.error = message;
  setState("failed", "error", message);
  hud.error(message);
}

async function fetchBinary(params, path, what, read = (response) => response.arrayBuffer()) {
  let attempt = 0;
  for (;;) {
    let response;
    try {
      response = await fetch(`${params.server}${path}`, { headers: authHeaders(params) });
    } catch (err) {
      response = null;
      setState("waiting", "waiting for the server", `${what}: ${err.message}`);
    }
    if (response && response.ok) return read(response);
    if (response) {
      const problem = await response.json().catch(() => ({}));
      const detail = problem.detail || response.statusText;
      if (response.status === 401) throw new Permanent(`Authentication failed (401 ${problem.code || "unauthorized"}): ${detail}`);
      if (response.status === 403) throw new Permanent(`Not allowed (403 ${problem.code || "forbidden"}): ${detail}`, problem.code);
      if (response.status === 404 || response.status === 400 || response.status === 409) {
        throw new Permanent(`${what}: ${detail}`, problem.code);
      }
      setState("waiting", "waiting for the server", `${what}: HTTP ${response.status} ${detail}`);
    }
    const delay = Math.min(RETRY_MAX_MS, RETRY_FIRST_MS * 2 ** attempt++);
    await new Promise((resolve) => setTimeout(resolve, delay));
  }
}

/**
 * The rig's character file as uploaded when it has one and the page shows weights (the
 * vertex outputs pose the rig's own mesh: PROTOCOL.md §5.2), else the rig's model.glb.
 * A VRM whose licence keeps it from anonymous viewers (403) falls back to model.glb.
 */
async function loadModel(params, view) {
  const rigPath = `/v1/rigs/${encodeURIComponent(params.rig)}`;
  const described = await fetchBinary(params, rigPath, `rig ${params.rig}`, (r) => r.json());
  const character = described.character;
  if (character && params.output === "weights") {
    view.setCharacterStatus("loading");
    try {
      const glb = await fetchBinary(params, character.url, `character of rig ${params.rig}`);
      const shown = await view.loadCharacter(glb, character);
      stats.character = { format: character.format, meta: character.meta, ...shown };
      hud.character(
        metaText(character.meta, character.format) +
          (character.rights_holder && character.meta && character.meta.redistribution === false
            ? " — shown to everyone: its uploader holds the rights"
            : "") +
          (shown.vrmError ? ` — shown as plain glTF (three-vrm refused it: ${shown.vrmError})` : ""),
      );
      return { names: described.names, vertexCount: described.num_vertices };
    } catch (err) {
      if (!(err instanceof Permanent && err.code === "character_not_redistributable")) {
        view.setCharacterStatus("error");
        throw err;
      }
      stats.character = { format: character.format, meta: character.meta, withheld: err.message };
      hud.character(`${metaText(character.meta, character.format)} — not shown: its licence forbids redistribution to viewers without a token`);
    }
  }
  return view.load(await fetchBinary(params, `${rigPath}/model.glb`, `rig ${params.rig}`));
}

async function main() {
  let params;
  try {
    params = readParams(window.location.href, stats.page);
  } catch (err) {
    failed(`Bad page URL: ${err.message}`);
    return;
  }
  stats.mode = params.mode;
  stats.rig = params.rig;
  stats.channel = params.channel;
  hud.showStats = params.stats;
  if (document.getElementById("hud")) document.getElementById("hud").hidden = !params.stats;

  const view = new FaceView(document.getElementById("stage"), {
    transparent: params.page === "overlay",
    controls: params.page === "viewer",
    width: params.width,
    height: params.height,
  });
  if (view.controls) view.controls.addEventListener("change", () => (view.dirty = true));
  // Tests (and the curious) read what is shown and how it is posed (FaceView.characterState).
  window.characterState = () => view.characterState();
  // What the rig's mesh was last posed with, for tests and the curious (read-only, like
  // facecastStats; docs/viewer.md): the seq of the last result applied, the demo
  // performance's frame index it answers (null when watching a channel), and the mesh as
  // posed — its vertex positions and its morph influences by target name. null until a
  // result is applied.
  let applied = null; // {seq, frame} of the last result applied to the view
  window.facecastApplied = () => applied && { ...applied, output: params.output, ...view.meshState() };

  setState("connecting", "loading", `rig ${params.rig}`);
  let model;
  let player = null;
  try {
    const [loaded, animation] = await Promise.all([
      loadModel(params, view),
      // The performance on the rig's own source points: the demo rig's, or the generic
      // ARKit set's for a character uploaded as a file (server/pages/viewer.py).
      params.mode === "demo"
        ? fetchBinary(params, `/v1/demo/animation?rig=${encodeURIComponent(params.rig)}`, "demo animation")
        : null,
    ]);
    model = loaded;
    if (animation) player = new DemoPlayer(decodeAnimation(animation), { start: params.start });
  } catch (err) {
    failed(err instanceof Permanent ? err.message : `Cannot load: ${err.message}`);
    return;
  }
  view.render();

  let latencyEma = null;
  let pendingWeights = null;
  let pendingVertices = null;
  let pendingHead = null;
  let pendingResult = null; // {seq, frame} of the result pending*, applied at the next tick
  let moving = null; // output "moving": the indices of the vertices results carry

  const link = new Link(socketTarget(params), {
    onOpen(link) {
      stats.connects = link.connects;
      setState("connecting", params.mode === "demo" ? "opening session" : "joining channel");
      if (params.mode === "demo") {
        link.send(encodeHello({ rig: params.rig, output: params.output, dtype: params.dtype }));
      }
    },
    onState(kind, detail) {
      if (kind === "failed") {
        if (player) player.stop();
        failed(detail);
      } else if (kind === "waiting") {
        if (player) player.stop();
        setState("waiting", "reconnecting", detail);
      } else if (kind === "connecting") {
        setState("connecting", detail);
      }
    },
    onPong(rtt) {
      stats.rttMs = rtt;
    },
    onMessage(msg, link) {
      switch (msg.type) {
        case "ready": {
          const rig = msg.rig;
          if (msg.output === "weights" && !view.bindWeights(rig.names)) {
            // The rig was replaced on the server: its model is stale.
            link.fail(`rig ${rig.id} changed on the server (weights no longer match the model); reload the page`);
            return;
          }
          moving = rig.moving;
          if ((msg.output === "vertices" || msg.output === "moving") && rig.v !== model.vertexCount) {
            link.fail(`rig ${rig.id} has ${rig.v} vertices but its model ${model.vertexCount}; reload the page`);
            return;
          }
          hud.names(rig.names);
          view.resize(); // the panel widens for many weights (viewer.html), the stage narrows
          link.healthy();
          hud.clearError();
          stats.error = null;
          if (player) {
            if (rig.k !== player.animation.k) {
              link.fail(
                `the demo performance has ${player.animation.k} points per frame but rig ${rig.id} needs ${rig.k}: ` +
                  "reload the page (the rig was replaced), or watch a channel instead",
              );
              return;
            }
            player.play(link);
          }
          setState("live", params.mode === "demo" ? "live · demo" : `live · ${params.channel}`);
          break;
        }
        case "result": {
          stats.frames += 1;
          stats.seq = msg.seq;
          live.receive(msg, performance.now());
          stats.dropped = msg.dropped;
          let latency = null;
          pendingResult = { seq: msg.seq, frame: null };
          if (player) {
            const frame = player.received(msg.seq);
            if (frame) {
              latency = frame.latencyMs;
              stats.demoTime = frame.demoTime;
              pendingResult.frame = frame.index;
            }
          } else if (typeof msg.server_ts === "number") latency = Date.now() - msg.server_ts * 1000;
          if (latency !== null) {
            latencyEma = latencyEma === null ? latency : 0.9 * latencyEma + 0.1 * latency;
            stats.latencyMs = latencyEma;
          }
          if (msg.weights) pendingWeights = msg.weights;
          else pendingVertices = msg.vertices;
          if (msg.head) pendingHead = msg.head.rotation;
          break;
        }
        case "channel_idle":
          setState("idle", `idle · ${msg.channel}`, "waiting for a publisher");
          break;
        case "channel_live":
          setState("live", `live · ${msg.channel}`);
          break;
        case "face_lost":
          setState("idle", "face lost", `no face since ${msg.since.toFixed?.(2) ?? msg.since}`);
          break;
        case "error":
          if (msg.fatal) {
            stats.error = `${errorName(msg.code)}: ${msg.message}`;
            if (msg.code === ErrorCode.UNKNOWN_RIG) hud.error(`Unknown rig: ${msg.message}`);
          } else {
            setState(stats.state, `${errorName(msg.code)}`, msg.message);
          }
          break;
        default:
          break;
      }
    },
  });
  // Glass to glass (PROTOCOL.md §5.4): the stamped results' stages, received to drawn.
  const live = new LiveLatency(link.clock);
  window.liveLatency = (detail = false) => live.report(detail);
  link.start();

  // What a draw holds the page: from render() to the next task, which runs after the
  // draw's commit (without a GPU, Chromium reads the WebGL canvas back there).
  const after = new MessageChannel();
  let costFrom = null;
  after.port1.onmessage = () => {
    live.drawCost(performance.now() - costFrom);
    costFrom = null;
  };

  // Apply at most one pose per display frame: results can outpace the screen.
  let fpsFrames = 0;
  let fpsSince = performance.now();
  const tick = (now) => {
    let appliedNow = false;
    try {
      if (pendingWeights) view.setWeights(pendingWeights);
      if (pendingHead) {
        view.setHead(pendingHead);
        stats.head = Array.from(pendingHead);
      }
      if (pendingVertices && moving) view.setMovingVertices(moving, pendingVertices);
      else if (pendingVertices) view.setVertices(pendingVertices);
      if (pendingWeights) hud.weights(pendingWeights);
      if (pendingWeights || pendingVertices) {
        applied = pendingResult;
        stats.appliedSeq = applied.seq;
        appliedNow = true;
      }
    } catch (err) {
      link.fail(err.message);
    }
    pendingWeights = pendingVertices = pendingHead = pendingResult = null;
    if (appliedNow && !view.dirty) {
      // The result's pose is the one on screen (a still face): nothing to draw, and the
      // viewer sees it from this frame on.
      live.drawn(performance.now());
    }
    if (view.dirty) {
      const started = performance.now();
      view.render();
      stats.rendered += 1;
      const submitted = performance.now();
      live.drawn(submitted, submitted - started); // the newest result is drawn
      if (costFrom === null) {
        costFrom = started;
        after.port2.postMessage(null);
      }
    }
    if (now - fpsSince >= 500) {
      stats.fps = ((stats.frames - fpsFrames) * 1000) / (now - fpsSince);
      fpsFrames = stats.frames;
      fpsSince = now;
      stats.glassMs = live.median();
      hud.stats(stats);
    }
    requestAnimationFrame(tick);
  };
  requestAnimationFrame(tick);
}

main().catch((err) => failed(`Viewer error: ${err.message}`));
