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
  // A performer's own rig is named {character}@{performer}: calibrating again starts from
  // the character, not from the rig made by the last calibration.
  const character = params.rig.split("@")[0];
  return { ...params, mode: "publish", performer, character, backend, smoothing };
}
