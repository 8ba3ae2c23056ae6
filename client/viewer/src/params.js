// The page's settings, read once from its URL; every value is checked here so the rest
// of the viewer can trust them. No network, no DOM beyond the URL it is given.

const OUTPUTS = new Set(["weights", "vertices", "moving"]);
const DTYPES = new Set(["f32", "f16"]);
// RFC 7230 tchar: what a token may hold to travel as a WebSocket subprotocol (§2.2).
const TCHAR = /^[!#$%&'*+\-.^_`|~0-9A-Za-z]+$/;

export class ParamError extends Error {}

/**
 * Parse the page URL.
 *
 * server: base URL of the facecast server (default: the page's origin)
 * channel: watch /v1/channels/{channel}/watch; otherwise the demo performance is
 *          streamed through /v1/stream (`demo` / `stream` force that mode)
 * rig, token, output (weights|vertices|moving), dtype (f32|f16)
 * width, height: canvas size in CSS pixels (default: the window)
 * start: seconds into the demo performance to start from; stats: show the HUD on /overlay
 */
export function readParams(href, page) {
  const url = new URL(href);
  const q = url.searchParams;
  const server = new URL(q.get("server") || url.origin);
  if (server.protocol !== "http:" && server.protocol !== "https:") {
    throw new ParamError(`server must be an http(s) URL, got ${server.href}`);
  }
  const channel = q.get("channel");
  const wantsDemo = q.has("demo") || q.has("stream");
  if (channel !== null && (channel.length < 1 || channel.length > 256)) {
    throw new ParamError("channel must be 1 to 256 characters");
  }
  if (channel !== null && wantsDemo) {
    throw new ParamError("choose either channel=NAME or demo, not both");
  }
  const output = q.get("output") || "weights";
  if (!OUTPUTS.has(output)) throw new ParamError(`output must be weights, vertices or moving, got ${output}`);
  if (output === "moving" && channel !== null) {
    throw new ParamError("output moving is for the demo stream only; a channel serves weights or vertices");
  }
  const dtype = q.get("dtype") || "f32";
  if (!DTYPES.has(dtype)) throw new ParamError(`dtype must be f32 or f16, got ${dtype}`);
  const rig = q.get("rig") || "demo";
  // A character's rig id, or a performer's rig fitted from it: "ict@alice" (server/store.py).
  if (!/^[A-Za-z0-9][A-Za-z0-9._-]{0,63}(@[A-Za-z0-9][A-Za-z0-9._-]{0,63})?$/.test(rig)) {
    throw new ParamError(`invalid rig id ${rig}`);
  }
  const token = q.get("token") || null;
  return {
    page,
    mode: channel !== null ? "watch" : "demo",
    server: server.origin + server.pathname.replace(/\/$/, ""),
    channel,
    rig,
    token,
    tokenAsSubprotocol: token !== null && TCHAR.test(token),
    output,
    dtype,
    width: size(q, "width"),
    height: size(q, "height"),
    start: number(q, "start", 0),
    stats: page === "viewer" || q.get("stats") === "1",
  };
}

function size(q, name) {
  if (!q.has(name)) return null;
  const value = Number(q.get(name));
  if (!Number.isInteger(value) || value < 16 || value > 8192) {
    throw new ParamError(`${name} must be an integer from 16 to 8192 (pixels)`);
  }
  return value;
}

function number(q, name, fallback) {
  if (!q.has(name)) return fallback;
  const value = Number(q.get(name));
  if (!Number.isFinite(value) || value < 0) throw new ParamError(`${name} must be a number >= 0`);
  return value;
}

/** The WebSocket URL and subprotocols for the page's mode (auth per PROTOCOL.md §2.2). */
export function socketTarget(params) {
  const base = params.server.replace(/^http/, "ws");
  let url;
  if (params.mode === "watch") {
    const q = new URLSearchParams({ rig: params.rig, output: params.output, dtype: params.dtype });
    url = `${base}/v1/channels/${encodeURIComponent(params.channel)}/watch?${q}`;
  } else if (params.mode === "publish") {
    // The performer page (/perform): the channel's publisher, hello sent on open.
    url = `${base}/v1/channels/${encodeURIComponent(params.channel)}/publish`;
  } else {
    url = `${base}/v1/stream`;
  }
  const protocols = ["facecast.v1"];
  if (params.token !== null) {
    if (params.tokenAsSubprotocol) protocols.push(`facecast.bearer.${params.token}`);
    // A token a subprotocol cannot carry goes in the query string: the last resort.
    else url += `${url.includes("?") ? "&" : "?"}token=${encodeURIComponent(params.token)}`;
  }
  return { url, protocols };
}

/** Headers for fetch() against the REST API. */
export function authHeaders(params) {
  return params.token !== null ? { Authorization: `Bearer ${params.token}` } : {};
}
