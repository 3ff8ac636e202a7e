// The NavCam: access units from the station decoded in a Worker (WebCodecs) onto the canvas,
// and an honest overlay. Frame rate and latency are of the last second, never held; the age
// of the last drawn frame is always shown; no frame for one interval of the stream plus a
// margin (the interval again, at most 200 ms; at least 250 ms in all) marks the picture STALE ("NO VIDEO 1.4 s", greyed) with the station's reason when it knows
// one, and a button to ask for the stream again. The page's glass-to-glass p95 of the last
// second goes to the station once a second: the holder's heartbeats carry it to the
// platform's speed cap.

import { $, put } from "./common.js";
import { api, apiUrl, onBinary } from "./station.js";
import { notify, state, subscribe } from "./store.js";

const STALE_MIN_MS = 250;
const STALE_MARGIN_MAX_MS = 200;
const CHECK_MS = 50;

const canvas = $("#video");
const box = $("#video-box");
const message = $("#video-message");
const staleMark = $("#video-stale");
let worker = null;
let watching = null;       // the platform whose NavCam is asked for
let stale = false;
const staleMarks = [];     // [page ms the last frame was drawn, page ms STALE was shown]
const dumpWaiters = [];

function showMessage(text) {
  put(message, text);
  if (message.hidden !== !text) message.hidden = !text;
}

function wallNow() { return performance.timeOrigin + performance.now(); }

/** Age (ms) of the last drawn frame, or null before the first. */
export function videoAgeMs() {
  const drawn = state.video?.lastDrawnMs;
  return drawn == null ? null : wallNow() - drawn;
}

/** How long without a frame marks the picture STALE, for a stream drawing a frame every
 * ``interval`` ms: 400 ms at 5 fps, 250 ms at 30 fps (the mark within 500 ms down to 4 fps;
 * slower streams get one interval and 200 ms, so a frame on time is never marked). */
export function staleLimitMs(interval) {
  const every = interval ?? 0;
  return Math.max(STALE_MIN_MS, every + Math.min(every, STALE_MARGIN_MAX_MS));
}

function onWorkerMessage(data) {
  if (data.type === "stats") {
    state.video = data;
    canvas.dataset.framesDecoded = String(data.decoded);
    const latency = $("#latency");
    put(latency, data.lastLatencyMs == null ? "—" : `${data.lastLatencyMs.toFixed(1)} ms`);
    latency.dataset.ms = data.lastLatencyMs == null ? "" : data.lastLatencyMs.toFixed(2);
    latency.title = data.lastLatencyMs == null ? "no frame in the last second" :
      `capture → station ${data.lastNetworkMs?.toFixed(1)} ms; p95 of the last second ${data.p95Second?.toFixed(1)} ms`;
    put($("#fps"), `${data.fps} fps`);
    if (data.decoded > 0 && state.current) showMessage("");
    notify("video");
  } else if (data.type === "unsupported") {
    showMessage("No video: WebCodecs VideoDecoder is missing in workers of this browser.");
  } else if (data.type === "error") {
    console.warn("decoder:", data.message);
  } else if (data.type === "dump") {
    for (const resolve of dumpWaiters.splice(0)) resolve(data);
  }
}

function checkStale() {
  const age = videoAgeMs();
  put($("#video-age"), age == null ? "—" : `${(age / 1000).toFixed(1)} s`);
  const limit = staleLimitMs(state.video?.frameIntervalMs);
  const now = age != null && watching != null && age > limit;
  if (now && !stale) staleMarks.push([performance.now() - age, performance.now()]);
  if (now !== stale) { stale = now; box.dataset.stale = String(now); staleMark.hidden = !now; }
  if (age == null && watching != null) {
    // No first frame yet: the station's word on why, once it has one.
    const reason = state.videoState?.watching === watching ? state.videoState.reason : "";
    if (reason) showMessage(`No video from ${watching} yet: ${reason}.`);
  }
  if (now) {
    put($("#video-stale-age"), `NO VIDEO ${(age / 1000).toFixed(1)} s`);
    const reason = state.videoState?.watching === watching ? state.videoState.reason : "";
    put($("#video-stale-reason"), reason ? `${reason}.` : "waiting for the station's word…");
  }
}

async function watch(platformId) {
  if (!worker) return;
  watching = platformId;
  worker.postMessage({ type: "clear" });
  state.video = null;
  canvas.setAttribute("aria-label", `NavCam ${platformId}`);
  showMessage(`Waiting for ${platformId}'s NavCam…`);
  try {
    performance.mark("watch");
    await api.call("video_watch", { platform_id: platformId }, 10000);
    performance.mark("watching");
  } catch (error) {
    showMessage(`No video from ${platformId}: ${error.message}`);
  }
}

async function resume() {
  if (!watching) return;
  $("#video-stale-reason").textContent = "asking for the stream again…";
  try {
    await api.call("console_stream", { platform_id: watching, name: "navcam", action: "start" }, 8000);
    await api.call("video_watch", { platform_id: watching }, 10000);
  } catch (error) {
    $("#video-stale-reason").textContent = `the stream could not be started: ${error.message}.`;
  }
}

function reportLatency() {
  const p95 = state.video?.p95Second;
  if (p95 == null || !watching || watching !== state.current || !api.connected) return;
  api.call("console_latency", { platform_id: watching, p95_ms: p95 }, 2000).catch(() => {});
}

/** Start the NavCam view; returns the hooks tests and benchmarks read (window.navcam). */
export function startVideo() {
  if (!window.isSecureContext) {
    showMessage("No video: this page is not a secure context. Open it as http://127.0.0.1 or localhost, or over HTTPS (console.tls_cert).");
  } else if (typeof VideoDecoder === "undefined" || typeof OffscreenCanvas === "undefined") {
    showMessage("No video: this browser has no WebCodecs VideoDecoder. Use a current Chromium or Firefox.");
  } else {
    worker = new Worker("/static/video-worker.js", { type: "module" });
    const offscreen = canvas.transferControlToOffscreen();
    worker.postMessage({ type: "init", canvas: offscreen }, [offscreen]);
    worker.onmessage = (event) => onWorkerMessage(event.data);
  }
  onBinary(1, (buffer) => worker?.postMessage({ type: "frame", buffer, pageMs: wallNow() }, [buffer]));
  // The worker opens a socket of its own to the station for the NavCam (the frames then skip
  // this thread, busy with layout and paint); until it carries them they come through here.
  subscribe("session", () => worker?.postMessage({ type: "socket", url: apiUrl, session: state.session, token: state.mediaToken }));
  subscribe("clock", () => worker?.postMessage({ type: "clock", offsetMs: state.clockOffsetMs }));
  subscribe("shown", (platformId) => watch(platformId));
  subscribe("current", () => {
    if (state.current) return; // "shown" follows once connected
    watching = null;
    worker?.postMessage({ type: "clear" });
    state.video = null;
    showMessage("Select a platform to see its NavCam.");
  });
  $("#video-resume").onclick = resume;
  setInterval(checkStale, CHECK_MS);
  setInterval(reportLatency, 1000);
  return {
    stats: () => state.video,
    relayed: () => state.videoState?.viewer ?? null, // the station's side of this page's feed
    staleMarks: () => staleMarks.slice(),
    staleLimitMs: () => staleLimitMs(state.video?.frameIntervalMs),
    keepLatencies: (on) => worker?.postMessage({ type: "keep", on }),
    dump: () => new Promise((resolve) => { dumpWaiters.push(resolve); worker?.postMessage({ type: "dump" }); }),
  };
}
