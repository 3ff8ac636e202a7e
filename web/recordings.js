// The recordings view (issue 23): replay a platform's MCAP recording in the console — a
// timeline with seek and speed (0.5× to 8×), the track on a map, the NavCam frame of that
// moment, the instruments and the log, in step. The station fetches the file from the platform
// once (recording_open) and answers the state at any time (recording_state): position,
// telemetry sections, log lines and the access units from the keyframe before it, decoded
// here with WebCodecs. A view of its own: its DOM, started by the wiring (console.js).

import { element, fixed } from "./common.js";
import { codecFromSps } from "./h264.js";
import { api } from "./station.js";
import { state } from "./store.js";

const SPEEDS = [0.5, 1, 2, 4, 8];
const TICK_MS = 250;
const KMH = 3.6;
/** A frame this much older than the moment shown (recording time) is from another time. */
const NO_VIDEO_AFTER_NS = 1e9;


const toggle = element("button", { id: "recordings-toggle", type: "button", "aria-pressed": "false" }, "recordings");
const platformInput = element("input", { id: "rec-platform", type: "text", placeholder: "platform id", "aria-label": "platform" });
const listButton = element("button", { id: "rec-list-button", type: "button" }, "list");
const list = element("select", { id: "rec-list", "aria-label": "recording" });
const openButton = element("button", { id: "rec-open", type: "button" }, "open");
const timeline = element("input", { id: "rec-time", type: "range", min: "0", max: "0", step: "any", value: "0", "aria-label": "time" });
const clock = element("span", { id: "rec-clock", role: "status" }, "—");
const play = element("button", { id: "rec-play", type: "button", "aria-pressed": "false" }, "play");
const speed = element("select", { id: "rec-speed", "aria-label": "speed" });
for (const s of SPEEDS) speed.append(element("option", s === 1 ? { value: String(s), selected: "" } : { value: String(s) }, `${s}×`));
const canvas = element("canvas", { id: "rec-video", width: "640", height: "480", "aria-label": "recorded NavCam" });
const mapBox = element("div", { id: "rec-map", "aria-label": "recorded track" });
const position = element("p", { id: "rec-position", role: "status" }, "position —");
const instruments = element("dl", { id: "rec-instruments", "aria-label": "instruments" });
const log = element("ol", { id: "rec-log", "aria-label": "recorded log" });
const plot = element("canvas", { id: "rec-plot", width: "1200", height: "120", "aria-label": "plots" });
// Outside recorded video the picture says so, as the live view's NO VIDEO does: the frame up
// is from another time (or there is none), greyed, with its age against the moment shown.
const noVideoAge = element("strong", { id: "rec-no-video-age" }, "NO VIDEO");
const noVideoText = element("span", { id: "rec-no-video-text" });
const noVideo = element("div", { id: "rec-no-video", class: "video-stale", role: "alert", "aria-label": "no recorded video", hidden: "" }, noVideoAge, noVideoText);
const videoBox = element("div", { class: "rec-video-box" }, canvas, noVideo);
const message = element("p", { id: "rec-message", role: "status" });
const view = element(
  "section",
  { id: "recordings", "aria-label": "recordings", hidden: "" },
  element("div", { class: "rec-tools" }, platformInput, listButton, list, openButton, message),
  element("div", { class: "rec-timeline" }, play, speed, timeline, clock),
  // At 1366x768 everything above the fold: the picture with its instruments under it, the
  // track with the log under it, the plots across the bottom.
  element("div", { class: "rec-panes" },
    element("div", { class: "rec-column" }, videoBox, position, instruments),
    element("div", { class: "rec-column" }, mapBox, log)),
  plot,
);
// Looks: console.css (#recordings), the live view's dark theme.

/** The recordings button in the header and its view (hidden until asked for). */
export function startRecordings() {
  document.querySelector("header")?.append(toggle);
  document.body.append(view);
}

let recording = null; // {name, platform, start_ns, end_ns, track, ...}
let playing = false;
let inFlight = false;
let pendingSeek = null;
let map = null;
let marker = null;
let previousNs = null; // the moment shown at the previous tick while playing

toggle.addEventListener("click", () => {
  const shown = view.hidden;
  view.hidden = !shown;
  toggle.setAttribute("aria-pressed", String(shown));
  if (shown && !platformInput.value) {
    if (state.current) platformInput.value = state.current;
  }
});

listButton.addEventListener("click", async () => {
  message.textContent = "";
  list.replaceChildren();
  try {
    const answer = await api.call("recordings_list", { platform_id: platformInput.value.trim() }, 15000);
    for (const item of answer.recordings) {
      if (item.recording) continue; // being written: replay finished files
      const label = `${item.name} (${item.duration_s ?? "?"} s, ${(item.size / 1e6).toFixed(1)} MB)`;
      list.append(element("option", { value: item.name }, label));
    }
    message.textContent = `${list.options.length} recordings${answer.recording ? "" : ` — not recording: ${answer.reason}`}`;
  } catch (error) {
    message.textContent = `cannot list: ${error.message}`;
  }
});

openButton.addEventListener("click", async () => {
  const name = list.value;
  if (!name) return;
  message.textContent = `opening ${name}…`;
  try {
    const index = await api.call("recording_open", { platform_id: platformInput.value.trim(), name }, 120000);
    recording = { ...index, platform: platformInput.value.trim() };
    timeline.max = String((recording.end_ns - recording.start_ns) / 1e9);
    timeline.value = "0";
    view.dataset.recording = name;
    drawTrack();
    message.textContent = `${name}: ${Number(timeline.max).toFixed(1)} s`;
    await seek(recording.start_ns);
  } catch (error) {
    message.textContent = `cannot open: ${error.message}`;
  }
});

timeline.addEventListener("input", () => {
  if (recording) seek(recording.start_ns + Math.round(Number(timeline.value) * 1e9));
});

play.addEventListener("click", () => {
  playing = !playing;
  play.textContent = playing ? "pause" : "play";
  play.setAttribute("aria-pressed", String(playing));
});

setInterval(() => {
  if (!playing || !recording) return;
  const next = Number(timeline.value) + (TICK_MS / 1000) * Number(speed.value);
  if (next >= Number(timeline.max)) { playing = false; play.textContent = "play"; play.setAttribute("aria-pressed", "false"); }
  timeline.value = String(Math.min(next, Number(timeline.max)));
  seek(recording.start_ns + Math.round(Number(timeline.value) * 1e9), true);
}, TICK_MS);

function drawTrack() {
  const L = window.L; // Leaflet, loaded by index.html before the modules run
  if (!L) return;
  if (!map) map = L.map(mapBox, { attributionControl: false, zoomControl: true });
  map.eachLayer((layer) => map.removeLayer(layer));
  const points = recording.track.map(([, lat, lon]) => [lat, lon]);
  if (points.length) {
    L.polyline(points, { color: "#1565c0", weight: 3 }).addTo(map);
    map.fitBounds(L.latLngBounds(points).pad(0.2));
    marker = L.circleMarker(points[0], { radius: 7, color: "#c62828" }).addTo(map);
  } else {
    map.setView([0, 0], 2);
    marker = null;
  }
}

/** Show the state at ``timeNs``; seeks that come while one is answered keep only the last. */
async function seek(timeNs, tick = false) {
  // A tick of play goes on from the previous one; a seek by hand starts over at a keyframe.
  if (inFlight) { pendingSeek = { timeNs, tick: tick && (pendingSeek?.tick ?? true) }; return; }
  inFlight = true;
  try {
    const params = { platform_id: recording.platform, name: recording.name, time_ns: timeNs };
    // Playing on: only the access units the decoder has not had.
    if (tick && playing && continuable()) params.frames_after_ns = video.lastFed;
    const state = await api.call("recording_state", params, 10000);
    show(state, tick);
  } catch (error) {
    message.textContent = `cannot seek: ${error.message}`;
  } finally {
    inFlight = false;
    if (pendingSeek !== null) { const next = pendingSeek; pendingSeek = null; seek(next.timeNs, next.tick); }
  }
}

function show(state, tick = false) {
  const seconds = (state.time_ns - recording.start_ns) / 1e9;
  clock.textContent = `${new Date(state.time_ns / 1e6).toISOString().slice(11, 23)} UTC (+${seconds.toFixed(1)} s)`;
  view.dataset.timeNs = String(state.time_ns);
  if (state.position) {
    const { lat, lon } = state.position;
    position.textContent = `position ${lat.toFixed(6)}, ${lon.toFixed(6)}`;
    position.dataset.lat = String(lat);
    position.dataset.lon = String(lon);
    position.dataset.timeNs = String(state.position.time_ns);
    if (marker) {
      marker.setLatLng([lat, lon]);
      const at = marker.getLatLng();
      mapBox.dataset.marker = `${at.lat},${at.lng}`;
    }
  } else {
    position.textContent = "position —";
  }
  const rows = [];
  const t = state.telemetry;
  const add = (label, value) => { if (value !== undefined && value !== null) rows.push(element("dt", {}, label), element("dd", {}, String(value))); };
  const number = (value, digits, unit) => (typeof value === "number" ? `${value.toFixed(digits)} ${unit}` : undefined);
  add("mode", t.override?.mode);
  add("speed", number(typeof t.pose?.speed === "number" ? t.pose.speed * KMH : null, 1, "km/h"));
  add("heading", number(t.pose?.heading, 0, "°"));
  add("battery", number(t.battery?.volts, 2, "V"));
  add("failsafe", t.failsafe?.step);
  add("patrol", t.autonomy?.state);
  if (t.motion) add("motor", `linear ${fixed(t.motion.linear, 2)}, angular ${fixed(t.motion.angular, 2)}`);
  instruments.replaceChildren(...rows);
  log.replaceChildren(...state.log.map((line) => {
    const text = readable(line.text);
    const item = element("li", { class: line.level >= 3 ? "warning" : "" }, `${new Date(line.time_ns / 1e6).toISOString().slice(11, 19)} ${text}`);
    if (text !== line.text) item.title = line.text; // the whole line on hover
    return item;
  }));
  drawPlots(state.time_ns);
  const pacing = tick && playing && previousNs !== null && state.time_ns > previousNs
    ? { wallMs: performance.now(), fromNs: previousNs, speed: Number(speed.value) }
    : null;
  previousNs = playing ? state.time_ns : null;
  decodeFrames(state.frames, pacing, state.frames_after_ns);
  markVideoTime();
}

/** Mark the picture when the frame up is not of the moment shown: seeking into a stretch
 * without recorded video used to leave the previous frame up, unmarked. While playing, frames
 * are drawn one tick late: that lag (at the speed) is not another time. */
function markVideoTime() {
  const momentNs = Number(view.dataset.timeNs ?? NaN);
  const frameNs = canvas.dataset.frameTimeNs ? Number(canvas.dataset.frameTimeNs) : null;
  const lagNs = playing ? 2 * TICK_MS * 1e6 * Number(speed.value) : 0;
  const behindNs = frameNs === null ? null : momentNs - frameNs;
  const other = !Number.isNaN(momentNs) && (behindNs === null || Math.abs(behindNs) > NO_VIDEO_AFTER_NS + lagNs);
  if (noVideo.hidden === other) noVideo.hidden = !other;
  videoBox.dataset.stale = String(other);
  if (!other) return;
  noVideoAge.textContent = "NO VIDEO at this time";
  noVideoText.textContent = frameNs === null
    ? "the NavCam recorded nothing in the seconds up to this moment."
    : `the picture is from ${new Date(frameNs / 1e6).toISOString().slice(11, 19)} UTC, ${(behindNs / 1e9).toFixed(1)} s ${behindNs > 0 ? "before" : "after"} this moment.`;
}

const LOG_LINE_CHARS = 120;

/** A log line for the eye: a JSON document in it (a load_map's whole map) is named by its
 * size, and a long line is cut. */
function readable(text) {
  const brace = text.search(/[[{]/);
  let shown = text;
  if (brace >= 0 && text.length - brace > 40) {
    try { JSON.parse(text.slice(brace)); shown = `${text.slice(0, brace)}(${text.length - brace} characters of JSON)`; } catch { /* not JSON */ }
  }
  return shown.length > LOG_LINE_CHARS ? `${shown.slice(0, LOG_LINE_CHARS)}…` : shown;
}

const PLOT_COLORS = ["#4fc3f7", "#81c784", "#ef9a9a", "#ce93d8"];

/** Each series scaled to its own range, along the recording's span; a cursor at ``timeNs``. */
function drawPlots(timeNs) {
  const context = plot.getContext("2d");
  const { width, height } = plot;
  context.clearRect(0, 0, width, height);
  const span = Math.max(1, recording.end_ns - recording.start_ns);
  const x = (t) => ((t - recording.start_ns) / span) * width;
  Object.entries(recording.plots ?? {}).forEach(([recorded, recordedPoints], i) => {
    // The live view's units: speed in km/h.
    const metres = recorded === "speed m/s";
    const label = metres ? "speed km/h" : recorded;
    const points = metres ? recordedPoints.map(([t, v]) => [t, v * KMH]) : recordedPoints;
    context.strokeStyle = context.fillStyle = PLOT_COLORS[i % PLOT_COLORS.length];
    context.fillText(label, 4 + 110 * i, 12);
    if (points.length < 2) return;
    let low = Infinity;
    let high = -Infinity;
    for (const [, v] of points) { low = Math.min(low, v); high = Math.max(high, v); }
    const y = (v) => height - 4 - ((v - low) / Math.max(1e-9, high - low)) * (height - 24);
    // Its scale: the highest and lowest value, at their heights, in the series' colour.
    context.fillText(String(Number(high.toFixed(2))), width - 40 - 44 * i, y(high) + 10);
    context.fillText(String(Number(low.toFixed(2))), width - 40 - 44 * i, y(low) - 2);
    context.beginPath();
    points.forEach(([t, v], j) => (j ? context.lineTo(x(t), y(v)) : context.moveTo(x(t), y(v))));
    context.stroke();
  });
  context.strokeStyle = "#ddd";
  context.beginPath();
  context.moveTo(x(timeNs), 0);
  context.lineTo(x(timeNs), height);
  context.stroke();
  plot.dataset.cursorNs = String(timeNs);
}

function bytesOf(base64) {
  const text = atob(base64);
  const out = new Uint8Array(text.length);
  for (let i = 0; i < text.length; i++) out[i] = text.charCodeAt(i);
  return out;
}

// Video. Paused (a seek): decode from the keyframe to the frame of that moment and draw that
// one. Playing: each tick's answer carries the access units up to the new moment; the decoder
// is kept, fed only the units it has not had, and every one of them is drawn at its recorded
// offset from the previous tick (divided by the speed), spread over the next tick: playback
// shows the recorded frame rate, one tick late.
let video = null; // {decoder, lastFed (ns), paced: timestamp → {pacing, timeNs}, queue: decoded frames to draw, in order, flushed}
let generation = 0;
let framesDrawn = 0;

function draw(frame, timeNs) {
  const context = canvas.getContext("2d");
  if (canvas.width !== frame.displayWidth) canvas.width = frame.displayWidth;
  if (canvas.height !== frame.displayHeight) canvas.height = frame.displayHeight;
  context.drawImage(frame, 0, 0);
  framesDrawn += 1;
  canvas.dataset.framesDrawn = String(framesDrawn);
  canvas.dataset.frameTimeNs = String(timeNs);
  markVideoTime();
}

function resetVideo() {
  generation += 1; // frames still waiting for their moment are dropped
  if (video && video.decoder.state !== "closed") video.decoder.close();
  for (const { frame } of video?.queue ?? []) frame.close();
  video = null;
}

/** Draw the chain's decoded frames one after another, each at its moment or, if that passed,
 * right after the one before: one timer per frame let a late tick's last frames come up after
 * the next tick's first ones (the picture stepped back, and a frame shown counted as later). */
function drawWhenDue(chain, mine) {
  const head = chain.queue[0];
  if (!head) return;
  setTimeout(() => {
    if (mine !== generation) return; // resetVideo closed the queue's frames
    chain.queue.shift();
    draw(head.frame, head.timeNs);
    head.frame.close();
    drawWhenDue(chain, mine);
  }, Math.max(0, head.dueMs - performance.now()));
}

/** Decode ``units`` on ``chain``; played, the units new since the previous tick show at their
 * moment, the others (the way from the keyframe to them) are decoded, not shown. */
function feed(chain, units, pacing, first) {
  units.forEach((unit, i) => {
    const timestamp = Math.round(unit.time / 1000);
    if (pacing && unit.time > pacing.fromNs) chain.paced.set(timestamp, { pacing, timeNs: unit.time });
    const type = (first && i === 0) || isKey(unit.data) ? "key" : "delta";
    chain.decoder.decode(new EncodedVideoChunk({ type, timestamp, data: unit.data }));
  });
  chain.lastFed = units[units.length - 1].time;
}

/** Whether an Annex B access unit holds an IDR slice (NAL type 5). */
function isKey(bytes) {
  for (let i = 0; i + 3 < bytes.length; i++) {
    if (bytes[i] === 0 && bytes[i + 1] === 0 && bytes[i + 2] === 1 && (bytes[i + 3] & 0x1f) === 5) return true;
  }
  return false;
}

function continuable() {
  return video !== null && !video.flushed && video.decoder.state === "configured";
}

/** Decode ``frames``: from a keyframe, or (``after`` the last unit fed) the units that follow;
 * ``pacing`` ({wallMs, fromNs, speed}) while playing. */
async function decodeFrames(frames, pacing, after) {
  if (pacing && after !== null && after !== undefined && continuable() && after === video.lastFed) {
    if (frames.length) feed(video, frames.map((f) => ({ time: f.time_ns, data: bytesOf(f.data) })), pacing, false);
    return;
  }
  if (!frames.length || typeof VideoDecoder === "undefined") {
    resetVideo();
    canvas.getContext("2d").clearRect(0, 0, canvas.width, canvas.height); // no picture from another time
    canvas.dataset.frameTimeNs = "";
    markVideoTime();
    return;
  }
  const units = frames.map((f) => ({ time: f.time_ns, data: bytesOf(f.data) }));
  const last = units[units.length - 1].time;
  const codec = codecFromSps(units[0].data);
  if (!codec) return;
  resetVideo();
  const mine = generation;
  const lastStamp = Math.round(last / 1000);
  const chain = { decoder: null, lastFed: last, paced: new Map(), queue: [], flushed: !pacing };
  chain.decoder = new VideoDecoder({
    output: (frame) => {
      const paced = chain.paced.get(frame.timestamp);
      chain.paced.delete(frame.timestamp);
      if (mine !== generation || (!paced && (pacing || frame.timestamp !== lastStamp))) {
        frame.close();
        return;
      }
      if (!paced) { // paused: the moment's frame
        draw(frame, last);
        frame.close();
        return;
      }
      const { pacing: at, timeNs } = paced;
      chain.queue.push({ frame, timeNs, dueMs: at.wallMs + (timeNs - at.fromNs) / 1e6 / at.speed });
      if (chain.queue.length === 1) drawWhenDue(chain, mine);
    },
    error: (error) => { message.textContent = `video: ${error.message}`; },
  });
  chain.decoder.configure({ codec, optimizeForLatency: true });
  feed(chain, units, pacing, true);
  video = chain;
  if (!pacing) {
    // Paused: flush to get the moment's frame out (after a flush the next chunk must be a key:
    // playing from here starts a new decoder).
    try { await chain.decoder.flush(); } catch { /* replaced by a newer seek */ }
  }
}
