// Entry point of the offline tracker (`facecast track`, facecast/cli/track.py): the /perform
// page's own FacePipeline (same model files, backend and normalisation) on video frames
// handed in one at a time, each tracked exactly once. Publishes window.facecastTrack; no
// camera, no network beyond the page's own origin, no drawing.

import { FacePipeline, LAYOUT } from "./pipeline.js";

let pipeline = null;
let prefetched = null; // {url, data: Promise<ArrayBuffer>}

async function fetchFrame(url) {
  const response = await fetch(url);
  if (!response.ok) throw new Error(`frame ${url}: ${response.status}`);
  return response.arrayBuffer();
}

const api = {
  layout: LAYOUT.name,
  k: LAYOUT.features.length,
  backend: null,
  features: null,

  /** Load the model on `backend`; returns {backend, features} as really running. */
  async load(backend = "wasm") {
    pipeline = new FacePipeline({ layout: LAYOUT, backend });
    api.backend = await pipeline.load();
    api.features = pipeline.features;
    return { backend: api.backend, features: api.features };
  },

  /**
   * Track the raw YUV frame at `url` (planar, `format` "I420", "I422" or "I444", as
   * WebCodecs names them). Chromium converts it to RGB as it converts its camera's
   * frames. `next`: the frame the following call will ask for, fetched while this one is
   * tracked. Returns {faces, points: [K*3] or null, head: [x, y, z, w] or null (the
   * quaternion the page sends as the frame's head.rotation), modelMs}.
   */
  async track(url, { format, width, height, colorSpace }, next = null) {
    const data = await (prefetched && prefetched.url === url ? prefetched.data : fetchFrame(url));
    prefetched = next === null ? null : { url: next, data: fetchFrame(next) };
    const frame = new VideoFrame(data, { format, codedWidth: width, codedHeight: height, timestamp: 0, colorSpace });
    let result;
    try {
      result = await pipeline.trackFrame(frame);
    } finally {
      frame.close();
    }
    return {
      faces: result.faces,
      points: result.points ? Array.from(result.points) : null,
      head: result.head ? Array.from(result.head) : null,
      modelMs: result.modelMs,
    };
  },
};
window.facecastTrack = api;
