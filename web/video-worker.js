// NavCam decoder (a Worker): H.264 access units (Annex B, as the station forwards them) →
// WebCodecs VideoDecoder (optimizeForLatency) → the page's canvas as an OffscreenCanvas.
//
// Message header (big-endian, see stationd/video_feed.py): u8 type, u8 flags (1 key,
// 2 replayed, 4 after gap), u16 feed, u32 seq, f64 capture ms (platform clock), f64 arrival
// ms (station clock), then the access unit.
//
// Glass-to-glass latency = time the frame is drawn − capture time. The capture stamp is the
// platform's wall clock; the draw time is this page's wall clock (performance.timeOrigin +
// performance.now()) corrected by the station's clock offset the page measured. It assumes the
// platform's and station's clocks agree (one host on loopback; NTP between hosts otherwise).
//
// A module worker (video.js starts it with type "module"): it imports the codec string.

import { codecFromSps } from "./h264.js";

const HEADER = 24;
const LATE_MS = 150; // a delta frame that reached the station longer ago than this is skipped
const FLAG_KEY = 1, FLAG_REPLAYED = 2;
let canvas = null, context = null, decoder = null;
let codec = "", waitingForKey = true, lastSeq = -1, feed = -1;
let clockOffsetMs = 0;
const inFlight = new Map();
const stats = { ownSocket: 0, copied: 0, firstDrawMs: 0, late: 0, lastNetworkMs: null, received: 0, decoded: 0, dropped: 0, errors: 0, replayed: 0, gaps: 0, lastLatencyMs: null };
const recent = [];      // latencies of the last ~300 live frames
const drawnTimes = [];  // draw times of the last second
const lastSecond = [];  // [drawn, latency] of the live frames of the last second
let lastDrawnMs = null; // wall-clock time the last frame was drawn
let keepAll = null;     // every frame's stage times (see ``stages``), while a benchmark asks

function now() { return performance.timeOrigin + performance.now(); }

function makeDecoder() {
  epoch += 1;
  if (decoder && decoder.state !== "closed") decoder.close();
  decoder = new VideoDecoder({ output: onDecoded, error: (e) => { stats.errors += 1; post({ type: "error", message: String(e) }); reset(); } });
  if (codec) decoder.configure({ codec, optimizeForLatency: true });
}

function reset() {
  waitingForKey = true;
  inFlight.clear();
  try { makeDecoder(); } catch (e) { post({ type: "error", message: String(e) }); }
}

// The decoder's output, drawn in order: a draw that waits on the frame's pixels (below) never
// lets a later frame overtake it.
let drawing = Promise.resolve();
let epoch = 0; // a clear or a new decoder: a frame still being converted is not drawn
function onDecoded(frame) {
  const decodedMs = now(), of = epoch;
  drawing = drawing.then(() => (of === epoch ? draw(frame, decodedMs, of) : frame.close())).catch((e) => { stats.errors += 1; post({ type: "error", message: String(e) }); });
}

// The frame's pixels converted to RGBA by the browser (VideoFrame.copyTo with a format: one
// YUV → RGB pass) and written to the canvas as they are: ~1 ms at 640×480 on a software
// canvas where drawImage(frame) takes ~2 (it converts into an image of its own, then draws
// that). The same pixels either way; a browser without the conversion gets drawImage.
let rgbaCopy = true;
let image = null; // reused, one frame's RGBA
async function paint(frame, of) {
  const width = frame.displayWidth, height = frame.displayHeight;
  if (rgbaCopy && frame.visibleRect?.width === width && frame.visibleRect?.height === height) {
    if (!image || image.width !== width || image.height !== height) image = new ImageData(width, height);
    try {
      await frame.copyTo(image.data, { format: "RGBA", colorSpace: "srgb" });
      if (of !== epoch) return false;
      context.putImageData(image, 0, 0);
      stats.copied += 1;
      return true;
    } catch {
      rgbaCopy = false;
    }
  }
  context.drawImage(frame, 0, 0);
  return true;
}

async function draw(frame, decodedMs, of) {
  const info = inFlight.get(frame.timestamp);
  if (info) info.decodedMs = decodedMs;
  inFlight.delete(frame.timestamp);
  if (canvas.width !== frame.displayWidth || canvas.height !== frame.displayHeight) {
    canvas.width = frame.displayWidth;
    canvas.height = frame.displayHeight;
  }
  let drew = false;
  try { drew = await paint(frame, of); } finally { frame.close(); }
  if (!drew) return;
  const drawn = now();
  if (!stats.firstDrawMs) stats.firstDrawMs = drawn;
  stats.decoded += 1;
  drawnTimes.push(drawn);
  lastDrawnMs = drawn;
  if (info && !info.replayed && info.captureMs > 0) {
    const latency = drawn + clockOffsetMs - info.captureMs;
    stats.lastLatencyMs = latency;
    stats.lastNetworkMs = info.arrivalMs - info.captureMs; // platform → station
    recent.push(latency);
    lastSecond.push([drawn, latency]);
    if (recent.length > 300) recent.shift();
    if (keepAll) {
      // Not part of glass-to-glass: from the draw to the worker's next display frame, when the
      // compositor takes the canvas (the display's own wait, as for any page).
      const entry = stages(info, latency, drawn);
      keepAll.push(entry);
      self.requestAnimationFrame?.(() => { entry.present = now() - drawn; });
    }
  }
}

/** One frame's way, in ms (a benchmark's breakdown of glass-to-glass): capture → station
 * (platform encode and send, the station's receive), station → page (the station's relay,
 * the WebSocket; the page's main thread too until the worker's own socket carries the frames),
 * page → worker (0 on the worker's socket), decode, draw. */
function stages(info, latency, drawn) {
  return {
    total: latency,
    network: info.arrivalMs - info.captureMs,
    relay: info.pageMs + clockOffsetMs - info.arrivalMs,
    handoff: info.workerMs - info.pageMs,
    decode: info.decodedMs - info.workerMs,
    draw: drawn - info.decodedMs,
    key: info.key,
    bytes: info.bytes,
  };
}

function onFrame(buffer, pageMs) {
  const workerMs = now();
  const view = new DataView(buffer);
  if (buffer.byteLength <= HEADER || view.getUint8(0) !== 1) return;
  const flags = view.getUint8(1), number = view.getUint16(2), seq = view.getUint32(4);
  const captureMs = view.getFloat64(8), arrivalMs = view.getFloat64(16);
  const key = (flags & FLAG_KEY) !== 0, replayed = (flags & FLAG_REPLAYED) !== 0;
  const data = new Uint8Array(buffer, HEADER);
  stats.received += 1;
  if (replayed) stats.replayed += 1;
  if (number !== feed) { feed = number; lastSeq = -1; waitingForKey = true; }
  if (lastSeq >= 0 && seq !== lastSeq + 1 && !key) { stats.gaps += 1; waitingForKey = true; }
  lastSeq = seq;
  if (key) {
    const found = codecFromSps(data);
    if (found && found !== codec) { codec = found; makeDecoder(); }
    waitingForKey = false;
  }
  // Freeze instead of smearing: nothing but a keyframe after a gap. A page that falls behind
  // (its decoder's queue grows, or frames sat in socket buffers: late against the station's
  // arrival stamp) skips to the next keyframe, as the station does for its send queue.
  const behind = !key && !replayed && decoder &&
    (decoder.decodeQueueSize > 4 || now() + clockOffsetMs - arrivalMs > LATE_MS);
  if (behind) { stats.late += 1; waitingForKey = true; }
  if (waitingForKey || !codec || decoder.state !== "configured") {
    stats.dropped += 1;
    return;
  }
  inFlight.set(seq, { captureMs, arrivalMs, replayed, key, bytes: data.byteLength, pageMs: pageMs ?? workerMs, workerMs });
  try {
    decoder.decode(new EncodedVideoChunk({ type: key ? "key" : "delta", timestamp: seq, data }));
  } catch (e) {
    stats.errors += 1;
    post({ type: "error", message: String(e) });
    reset();
  }
}

// The worker's own socket to the station (``console_media``): once it brings a frame, the
// frames the page's main thread forwards (its socket's, sent before the switch) are ignored.
let socket = null;
let socketCarries = false;

function openSocket(url, session, token) {
  if (socket) { socket.onclose = null; socket.close(); }
  socketCarries = false;
  const ws = new WebSocket(url);
  ws.binaryType = "arraybuffer";
  ws.onopen = () => ws.send(JSON.stringify({ jsonrpc: "2.0", id: 1, method: "console_media", params: { session, token } }));
  ws.onmessage = (event) => {
    if (typeof event.data === "string") {
      const answer = JSON.parse(event.data);
      if (answer.error) { // an older station: the page's socket keeps carrying the frames
        post({ type: "error", message: `video socket: ${answer.error.message}` });
        ws.close();
      }
      return;
    }
    if (new Uint8Array(event.data, 0, 1)[0] !== 1) return;
    socketCarries = true;
    stats.ownSocket += 1;
    onFrame(event.data, now());
  };
  // The page's socket carries the frames again (the station sends there without this one).
  ws.onclose = () => { if (socket === ws) { socket = null; socketCarries = false; } };
  socket = ws;
}

function percentile(values, p) {
  if (!values.length) return null;
  const sorted = [...values].sort((a, b) => a - b);
  return sorted[Math.min(sorted.length - 1, Math.floor(sorted.length * p))];
}

function post(message) { self.postMessage(message); }

function report() {
  // Of the last second only, never held: a stream that stops reads 0 fps and no latency.
  const at = now();
  while (drawnTimes.length && at - drawnTimes[0] > 1000) drawnTimes.shift();
  while (lastSecond.length && at - lastSecond[0][0] > 1000) lastSecond.shift();
  const second = lastSecond.map(([, latency]) => latency);
  const intervals = drawnTimes.slice(1).map((t, i) => t - drawnTimes[i]);
  post({
    type: "stats",
    ...stats,
    lastLatencyMs: second.length ? second[second.length - 1] : null,
    lastNetworkMs: second.length ? stats.lastNetworkMs : null,
    lastDrawnMs,
    frameIntervalMs: percentile(intervals, 0.5),
    fps: drawnTimes.length,
    p50: percentile(recent, 0.5),
    p95: percentile(recent, 0.95),
    p95Second: percentile(second, 0.95),
    codec,
    width: canvas ? canvas.width : 0,
    height: canvas ? canvas.height : 0,
  });
}

self.onmessage = (event) => {
  const message = event.data;
  if (message.type === "frame") { if (!socketCarries) onFrame(message.buffer, message.pageMs); }
  else if (message.type === "socket") openSocket(message.url, message.session, message.token);
  else if (message.type === "init") {
    canvas = message.canvas;
    context = canvas.getContext("2d", { alpha: false });
    if (typeof VideoDecoder === "undefined") { post({ type: "unsupported" }); return; }
    setInterval(report, 100);
  } else if (message.type === "clock") clockOffsetMs = message.offsetMs;
  else if (message.type === "clear") {
    feed = -1; lastSeq = -1; waitingForKey = true; codec = ""; recent.length = 0; drawnTimes.length = 0; lastSecond.length = 0; lastDrawnMs = null;
    for (const name of Object.keys(stats)) stats[name] = name.startsWith("last") ? null : 0;
    if (decoder && decoder.state !== "closed") decoder.close();
    decoder = null;
    epoch += 1;
    if (context) { context.fillStyle = "#000"; context.fillRect(0, 0, canvas.width, canvas.height); }
  } else if (message.type === "keep") { keepAll = message.on ? [] : null; }
  else if (message.type === "dump") { post({ type: "dump", latencies: keepAll ? [...keepAll] : [], stats: { ...stats } }); }
};
