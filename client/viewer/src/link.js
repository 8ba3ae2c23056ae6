// One WebSocket to the facecast server that comes back by itself: reconnects with
// exponential backoff after a drop; stops for good only on errors retrying cannot fix.

import { ServerClock } from "./clock.js";
import { decodeServer, encodePing, ErrorCode, errorName, ProtocolError } from "./protocol.js";

const BACKOFF_FIRST_MS = 250;
const BACKOFF_MAX_MS = 5000;
const PING_INTERVAL_MS = 5000; // keeps a watch session (which sends nothing else) alive
// A few pings right after opening: the server clock's offset is known within a second,
// and more chances in the first seconds (a page busy loading its character handles pongs
// late; clock.js keeps the best).
const FIRST_PINGS_MS = [250, 500, 750, 1500, 2500, 3500];
// Errors that another attempt with the same page settings would only repeat.
const PERMANENT = new Set([ErrorCode.UNAUTHORIZED, ErrorCode.FORBIDDEN, ErrorCode.UNSUPPORTED_VERSION]);

/**
 * handlers: onOpen(link) after the socket opens (send hello there), onMessage(msg, link),
 * onState(state, detail) with state one of connecting | open | waiting | failed,
 * onPong(rttMs). `clock` is the server's clock as estimated from the pongs (clock.js).
 */
export class Link {
  constructor(target, handlers) {
    this.target = target;
    this.handlers = handlers;
    this.ws = null;
    this.attempt = 0;
    this.connects = 0;
    this.stopped = false;
    this.timer = null;
    this.pinger = null;
    this.pingId = 0;
    this.pings = new Map();
    this.lastError = null;
    this.clock = new ServerClock();
  }

  start() {
    this.stopped = false;
    this._connect();
  }

  /** Stop for good, showing `reason` (a permanent error). */
  fail(reason) {
    this.stopped = true;
    clearTimeout(this.timer);
    this._closeSocket();
    this.handlers.onState("failed", reason);
  }

  /** Mark the current connection healthy: the next drop starts the backoff afresh. */
  healthy() {
    this.attempt = 0;
  }

  send(bytes) {
    if (this.ws && this.ws.readyState === WebSocket.OPEN) {
      this.ws.send(bytes);
      return true;
    }
    return false;
  }

  get bufferedAmount() {
    return this.ws ? this.ws.bufferedAmount : 0;
  }

  _connect() {
    this.handlers.onState("connecting", this.connects ? "reconnecting" : "connecting");
    let ws;
    try {
      ws = new WebSocket(this.target.url, this.target.protocols);
    } catch (err) {
      this.fail(`cannot open a WebSocket to ${this.target.url}: ${err.message}`);
      return;
    }
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    this.lastError = null;
    ws.onopen = () => {
      this.connects += 1;
      this.handlers.onState("open", "");
      this.handlers.onOpen(this);
      this._ping();
      for (const ms of FIRST_PINGS_MS) setTimeout(() => ws === this.ws && this._ping(), ms);
      this.pinger = setInterval(() => this._ping(), PING_INTERVAL_MS);
    };
    ws.onmessage = (event) => this._receive(event.data);
    ws.onclose = (event) => this._closed(ws, event);
    // onclose always follows onerror; the close decides what to do.
    ws.onerror = () => {};
  }

  _receive(data) {
    if (typeof data === "string") return; // not part of the protocol (§2.3)
    let msg;
    try {
      msg = decodeServer(data);
    } catch (err) {
      if (err instanceof ProtocolError) {
        console.warn(`facecast: ignoring a bad server message: ${err.message}`);
        return;
      }
      throw err;
    }
    if (msg.type === "pong") {
      const sent = this.pings.get(msg.id);
      this.pings.delete(msg.id);
      if (sent === undefined) return;
      const now = performance.now();
      this.clock.sample(sent, now, msg.server_ts);
      if (this.handlers.onPong) this.handlers.onPong(now - sent);
      return;
    }
    if (msg.type === "error" && msg.fatal) {
      this.lastError = msg;
      if (PERMANENT.has(msg.code)) {
        const what =
          msg.code === ErrorCode.UNAUTHORIZED
            ? "Authentication failed"
            : msg.code === ErrorCode.FORBIDDEN
              ? "Not allowed"
              : "Protocol error";
        this.fail(`${what} (${errorName(msg.code)}): ${msg.message}`);
        return;
      }
    }
    this.handlers.onMessage(msg, this);
  }

  _ping() {
    const id = ++this.pingId;
    this.pings.set(id, performance.now());
    if (this.pings.size > 16) this.pings.delete(this.pings.keys().next().value);
    this.send(encodePing(id, performance.now() / 1000));
  }

  _closed(ws, event) {
    if (ws !== this.ws) return;
    clearInterval(this.pinger);
    this.ws = null;
    if (this.stopped) return;
    const delay = Math.min(BACKOFF_MAX_MS, BACKOFF_FIRST_MS * 2 ** this.attempt);
    this.attempt += 1;
    // Jitter spreads the reconnects of many viewers after a server restart.
    const wait = Math.round(delay * (0.75 + 0.5 * Math.random()));
    const why = this.lastError
      ? `${errorName(this.lastError.code)}: ${this.lastError.message}`
      : `connection closed (${event.code}${event.reason ? " " + event.reason : ""})`;
    this.handlers.onState("waiting", `${why}; retrying in ${(wait / 1000).toFixed(1)} s`);
    this.timer = setTimeout(() => this._connect(), wait);
  }

  _closeSocket() {
    clearInterval(this.pinger);
    if (this.ws) {
      const ws = this.ws;
      this.ws = null;
      ws.onclose = null;
      ws.close(1000);
    }
  }
}
