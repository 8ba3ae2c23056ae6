// The performer page's settings, read once from its URL (/perform?channel=NAME&rig=ID,
// plus token, performer, server like the viewer). No network, no DOM beyond the URL.

import { ParamError, readParams } from "../params.js";

const PERFORMER = /^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$/;
// TensorFlow.js backends the face model can run on (docs/perform.md compares them).
const BACKENDS = new Set(["wasm", "webgl", "cpu"]);
// The live filter of the published points (the server's, PROTOCOL.md §5.1.1).
const SMOOTHING = new Set(["auto", "off"]);

/**
 * channel (required): publish to /v1/channels/{channel}/publish
 * rig: the rig the channel is published for (its K must be the layout's feature count to
 *      publish; any rig's character can be calibrated for)
 * performer: name of the performer profile a calibration makes (default "performer")
 * backend: the face model's TensorFlow.js backend, wasm (default) | webgl | cpu
 * smoothing: auto (default: the hello asks for the server's auto filter, the Kalman on
 *      the neutral's noise, PROTOCOL.md §5.1.1) | off (viewers get the points unfiltered)
 * blink: LOW,HIGH, the performer's own blink curve for a character's rig, sent with the
 *      walk-through's closed eyes (PROTOCOL.md §5.1.3 blink_contrast; 0 <= LOW < HIGH <= 1):
 *      raise LOW if the character half-closes its eyes when you look down, lower HIGH if
 *      your blinks do not close them (default: the server's, 0.4,0.8 for a character
 *      with eye-look shapes, 0.4,0.7 for one without)
 */
export function readPerformParams(href) {
  const q = new URL(href).searchParams;
  if (!q.get("channel")) throw new ParamError("channel=NAME is required: the channel to publish to");
  const params = readParams(href, "perform");
  const performer = q.get("performer") || "performer";
  if (!PERFORMER.test(performer)) {
    throw new ParamError("performer must be 1 to 64 of A-Z a-z 0-9 . _ - (starting with a letter or digit)");
  }
  const backend = q.get("backend") || "wasm";
  if (!BACKENDS.has(backend)) throw new ParamError(`backend must be wasm, webgl or cpu, got ${backend}`);
  const smoothing = q.get("smoothing") || "auto";
  if (!SMOOTHING.has(smoothing)) throw new ParamError(`smoothing must be auto or off, got ${smoothing}`);
  const blinkContrast = readBlinkContrast(q.get("blink"));
  // A performer's own rig is named {character}@{performer}: calibrating again starts from
  // the character, not from the rig made by the last calibration.
  const character = params.rig.split("@")[0];
  return { ...params, mode: "publish", performer, character, backend, smoothing, blinkContrast };
}

/** `blink=LOW,HIGH` as [low, high] (0 <= low < high <= 1), or null when absent. */
function readBlinkContrast(text) {
  if (text === null || text === "") return null;
  const parts = text.split(",");
  const [low, high] = parts.map((part) => (part.trim() === "" ? Number.NaN : Number(part)));
  if (parts.length !== 2 || !(low >= 0 && low < high && high <= 1)) {
    throw new ParamError(`blink must be LOW,HIGH with 0 <= LOW < HIGH <= 1, e.g. 0.5,0.9; got ${text}`);
  }
  return [low, high];
}
