// The camera side of /perform: opening the camera with errors a person can act on,
// handing its frames to the tracker, drawing the points over its image. DOM only; no
// tracking, no network.

/** Open the user-facing camera into `video`; rejects with a message saying what to do. */
export async function openCamera(video) {
  if (!navigator.mediaDevices || !navigator.mediaDevices.getUserMedia) {
    throw new Error("this browser gives no camera access here (getUserMedia needs https or localhost)");
  }
  let stream;
  try {
    stream = await navigator.mediaDevices.getUserMedia({ video: { width: { ideal: 640 }, height: { ideal: 480 }, facingMode: "user" }, audio: false });
  } catch (err) {
    if (err.name === "NotAllowedError" || err.name === "SecurityError") {
      throw new Error("camera access was denied: allow the camera for this page and reload");
    }
    if (err.name === "NotFoundError" || err.name === "OverconstrainedError") {
      throw new Error("no camera found: connect one and reload");
    }
    if (err.name === "NotReadableError") throw new Error("the camera is in use by another program: close it and reload");
    throw new Error(`cannot open the camera: ${err.name}: ${err.message}`);
  }
  video.srcObject = stream;
  await video.play();
  return stream;
}

/**
 * Resolves when `video` presents its next frame (each animation frame where unsupported),
 * with the frame's metadata (requestVideoFrameCallback's; null without it).
 */
export function nextVideoFrame(video) {
  return new Promise((resolve) => {
    if (video.requestVideoFrameCallback) video.requestVideoFrameCallback((now, metadata) => resolve(metadata));
    else requestAnimationFrame(() => resolve(null));
  });
}

const MAX_CAPTURE_AGE_MS = 1000; // a capture time older than this at arrival is not believed
const LOCK_VOTES = 3; // equal offsets seen before the processor's timestamps are trusted

/** A capture time (performance.now() ms) if plausible at `arrivedMs`, else the arrival. */
function plausible(capturedMs, arrivedMs) {
  return typeof capturedMs === "number" && capturedMs <= arrivedMs && capturedMs >= arrivedMs - MAX_CAPTURE_AGE_MS ? capturedMs : arrivedMs;
}

/**
 * The camera frames' capture times on performance.now()'s clock (PROTOCOL.md §5.4).
 * requestVideoFrameCallback gives them (`captureTime`, else `presentationTime`) for the
 * <video>'s frames. A MediaStreamTrackProcessor's VideoFrame has only its `timestamp`, on
 * the browser's own monotonic clock (Chromium: a constant away from performance.now()):
 * the offset is learnt from the <video>'s frames, the same camera frames: at each read
 * the smallest timestamp − captureTime over recent captures is this frame's own once its
 * capture is among them; once the same offset has come LOCK_VOTES times it is used.
 * Until then, and whenever a time is implausible, the frame's arrival stands in.
 */
export class CaptureTimes {
  constructor(video) {
    this.captures = []; // recent captureTime of the <video>'s frames
    this.offsetMs = null;
    this.votes = new Map();
    this.source = "arrival";
    this.presented = 0; // frames the <video> has presented (its metadata's count)
    if (!video.requestVideoFrameCallback) return;
    const seen = (now, metadata) => {
      this.presented = metadata.presentedFrames ?? this.presented + 1;
      const t = metadata.captureTime ?? metadata.presentationTime;
      if (typeof t === "number") {
        this.captures.push(t);
        if (this.captures.length > 8) this.captures.shift();
      }
      video.requestVideoFrameCallback(seen);
    };
    video.requestVideoFrameCallback(seen);
  }

  /** A <video> frame's capture time from its callback's metadata, arrived at `arrivedMs`. */
  ofVideo(metadata, arrivedMs) {
    const t = metadata ? (metadata.captureTime ?? metadata.presentationTime) : undefined;
    this.source = typeof t === "number" ? "video metadata" : "arrival";
    return plausible(t, arrivedMs);
  }

  /** A VideoFrame's capture time from its `timestamp` (µs), read at `arrivedMs`. */
  ofFrame(frame, arrivedMs) {
    const ts = frame.timestamp / 1000;
    if (this.offsetMs === null && this.captures.length) {
      let d = Infinity;
      for (const c of this.captures) if (ts - c < d) d = ts - c;
      const key = Math.round(d * 10) / 10;
      const votes = (this.votes.get(key) || 0) + 1;
      this.votes.set(key, votes);
      if (votes >= LOCK_VOTES) this.offsetMs = key;
      if (this.votes.size > 256) this.votes.clear();
    }
    if (this.offsetMs === null) return arrivedMs;
    this.source = "frame timestamp";
    return plausible(ts - this.offsetMs, arrivedMs);
  }
}

/**
 * The camera's frames as the tracker takes them: `next()` resolves with the newest frame
 * not yet tracked, `{frame}` (a VideoFrame the caller closes) where the browser has
 * MediaStreamTrackProcessor, else `{video}` (the element, on its next presented frame);
 * either with `capturedMs`, its capture time on performance.now()'s clock (CaptureTimes).
 *
 * The processor hands over the camera's frames as they arrive, outside the page's
 * rendering steps (where the <video> element's frame callbacks run), and as VideoFrames,
 * which the tracker converts as `facecast track` converts a file's (FacePipeline.trackFrame).
 * Measured in headless Chromium it tracks no faster than the callbacks (docs/perform.md,
 * "Performance"). A buffer of one frame: a frame that arrives while the model runs
 * replaces an older one, so what is tracked next is the newest.
 */
export function cameraFrames(stream, video) {
  const [track] = stream.getVideoTracks();
  const times = new CaptureTimes(video);
  if (typeof MediaStreamTrackProcessor === "function" && track) {
    const processor = new MediaStreamTrackProcessor({ track, maxBufferSize: 1 });
    const reader = processor.readable.getReader();
    return {
      kind: "processor",
      times,
      async next() {
        const { value, done } = await reader.read();
        if (done) throw new Error("the camera stopped");
        return { frame: value, capturedMs: times.ofFrame(value, performance.now()) };
      },
    };
  }
  let pending = nextVideoFrame(video);
  return {
    kind: "video",
    times,
    async next() {
      const metadata = await pending;
      const capturedMs = times.ofVideo(metadata, performance.now());
      // Ask for the frame after this one now: one presented while the model runs is
      // tracked as soon as the model is done.
      pending = nextVideoFrame(video);
      return { video, capturedMs };
    },
  };
}

/**
 * The feature points (and the stable ones, faint) over the camera image. The canvas has
 * the video's pixel size and is mirrored by CSS with the video; only the face's box is
 * cleared and drawn, so this costs the same whatever the camera's resolution.
 */
export function drawPoints(ctx, face, previousBox, layout) {
  if (previousBox) ctx.clearRect(previousBox[0] - 4, previousBox[1] - 4, previousBox[2] + 8, previousBox[3] + 8);
  if (!face) return null;
  const lm = face.landmarks;
  ctx.fillStyle = "rgba(160, 200, 255, 0.6)";
  for (const i of layout.stable) ctx.fillRect(lm[i][0] - 1, lm[i][1] - 1, 2, 2);
  ctx.fillStyle = "#ffb070";
  ctx.beginPath();
  for (const i of layout.features) {
    ctx.moveTo(lm[i][0] + 2.5, lm[i][1]);
    ctx.arc(lm[i][0], lm[i][1], 2.5, 0, 2 * Math.PI);
  }
  ctx.fill();
  const [bx, by, bw, bh] = face.box;
  ctx.strokeStyle = "rgba(61, 220, 132, 0.6)";
  ctx.strokeRect(bx, by, bw, bh);
  // Everything drawn lies within the box grown by the points that stick out of it.
  let [x0, y0, x1, y1] = [bx, by, bx + bw, by + bh];
  for (const p of lm) {
    if (p[0] < x0) x0 = p[0];
    if (p[1] < y0) y0 = p[1];
    if (p[0] > x1) x1 = p[0];
    if (p[1] > y1) y1 = p[1];
  }
  return [x0, y0, x1 - x0, y1 - y0];
}
