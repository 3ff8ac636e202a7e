// Brasidas browser console: the operator's station in one page. The station daemon's local
// API over one WebSocket (JSON-RPC 2.0): telemetry, platforms and warnings are pushed, the
// NavCam arrives as H.264 access units decoded in a Worker (WebCodecs), and the keyboard or a
// game controller drives the platform whose override this console engaged.

import { StationApi } from "./api.js";
import { PlatformAudio } from "./audio.js";
import { PlatformMap } from "./map.js";
import { Teleop } from "./teleop.js";

const $ = (selector, root = document) => root.querySelector(selector);
const STALE_MS = 2000;

// Telemetry is read by the schema's field names (/api/telemetry-schema.json, generated from
// brasidas/codecs/telemetry_schema.py); tests/test_web_console.py checks every name read here.
// A section is null (no such device), its fields, or {error} when its source failed.
let schema = null;
fetch("/api/telemetry-schema.json").then((answer) => answer.json()).then((document) => { schema = document; });

/** The section's value, or null when absent or failed (see ``failure``). */
function section(snapshot, name) {
  const value = snapshot?.[name];
  return value && failure(value) === null ? value : null;
}

function failure(value) {
  return value && Object.keys(value).length === 1 && typeof value.error === "string" ? value.error : null;
}

const state = {
  current: null,          // the platform shown, controlled and driven
  platforms: [],          // beacons heard (pushed)
  connections: new Map(), // platform id → connection summary (pushed)
  telemetry: new Map(),   // platform id → { report, at }
  warnings: new Map(),    // "platform/name" → { note, acknowledged }
  session: null,
  stationId: null,        // this station's id (console_subscribe)
  taken: new Map(),       // platform id → the 90.17 note: control taken from this station
  clockOffsetMs: 0,       // station clock − page clock
  override: "idle",       // idle | pending | engaged | error
  videoStats: null,
};

// ---------------------------------------------------------------- video

const canvas = $("#video");
const videoMessage = $("#video-message");
let worker = null;
if (!window.isSecureContext) {
  showVideoMessage("No video: this page is not a secure context. Open it as http://127.0.0.1 or localhost, or over HTTPS (console.tls_cert).");
} else if (typeof VideoDecoder === "undefined" || typeof OffscreenCanvas === "undefined") {
  showVideoMessage("No video: this browser has no WebCodecs VideoDecoder. Use a current Chromium or Firefox.");
} else {
  worker = new Worker("/static/video-worker.js");
  const offscreen = canvas.transferControlToOffscreen();
  worker.postMessage({ type: "init", canvas: offscreen }, [offscreen]);
  worker.onmessage = (event) => onWorkerMessage(event.data);
}
window.navcam = {
  stats: () => state.videoStats,
  marks: () => Object.fromEntries(performance.getEntriesByType("mark").map((m) => [m.name, m.startTime])),
  audio: () => ({ ...audio.stats }),
  apiStates: [],
  /** Drop the station connection (it reconnects by itself): for trying the reconnection. */
  dropStationConnection: () => api.ws?.close(),
  keepLatencies: (on) => worker?.postMessage({ type: "keep", on }),
  dump: () => new Promise((resolve) => { dumpWaiters.push(resolve); worker?.postMessage({ type: "dump" }); }),
  /** Where [lat, lon] is on the map, in pixels from its top-left corner: for clicking it. */
  mapPixel: (lat, lon) => map.pixel(lat, lon),
};
const dumpWaiters = [];

function showVideoMessage(text) {
  videoMessage.textContent = text;
  videoMessage.hidden = !text;
}

function onWorkerMessage(message) {
  if (message.type === "stats") {
    state.videoStats = message;
    canvas.dataset.framesDecoded = String(message.decoded);
    $("#latency").textContent = message.lastLatencyMs == null ? "—" : `${message.lastLatencyMs.toFixed(1)} ms`;
    $("#latency").dataset.ms = message.lastLatencyMs == null ? "" : message.lastLatencyMs.toFixed(2);
    $("#latency").title = message.lastLatencyMs == null ? "" :
      `capture → station ${message.lastNetworkMs.toFixed(1)} ms, station → drawn ${(message.lastLatencyMs - message.lastNetworkMs).toFixed(1)} ms; p50 ${message.p50?.toFixed(1)} ms, p95 ${message.p95?.toFixed(1)} ms`;
    $("#fps").textContent = `${message.fps} fps`;
    if (message.decoded > 0 && state.current) showVideoMessage("");
  } else if (message.type === "unsupported") {
    showVideoMessage("No video: WebCodecs VideoDecoder is missing in workers of this browser.");
  } else if (message.type === "error") {
    console.warn("decoder:", message.message);
  } else if (message.type === "dump") {
    for (const resolve of dumpWaiters.splice(0)) resolve(message);
  }
}

async function watch(platformId) {
  if (!worker) return;
  worker.postMessage({ type: "clear" });
  canvas.setAttribute("aria-label", `NavCam ${platformId}`);
  showVideoMessage(`Waiting for ${platformId}'s NavCam…`);
  try {
    performance.mark("watch");
    await api.call("video_watch", { platform_id: platformId }, 10000);
    performance.mark("watching");
  } catch (error) {
    showVideoMessage(`No video from ${platformId}: ${error.message}`);
  }
}

// ---------------------------------------------------------------- station connection

const api = new StationApi(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/api/rpc/ws`, {
  onState: (text) => (window.navcam.apiStates.push(text), setPill("#api-state", text === "connected" ? "station connected" : `station ${text}…`, text === "connected" ? "ok" : "bad")),
  onBinary: (buffer) => {
    const type = new Uint8Array(buffer, 0, 1)[0];
    if (type === 1) worker?.postMessage({ type: "frame", buffer }, [buffer]);
    else if (type === 2) audio.onPacket(buffer);
  },
  onOpen: () => { subscribe().catch((error) => console.warn("subscribe failed", error)); },
});

async function subscribe() {
  performance.mark("station-open");
  const hello = await api.call("console_subscribe");
  state.session = hello.session;
  state.stationId = hello.station_id;
  measureClock().catch((error) => console.warn("clock offset not measured", error));
  if (state.current) {
    await api.call("connect", { platform_id: state.current }, 8000).catch(() => {});
    await api.call("console_focus", { platform_id: state.current }).catch(() => {});
    loadArea(state.current);
    await watch(state.current);
    if (audio.listening) await audio.listen(audio.listening).catch(() => {});
  } else if (requestedPlatform) {
    await select(requestedPlatform);
  }
}
const requestedPlatform = new URLSearchParams(location.search).get("platform"); // ?platform=ID

async function measureClock() {
  // Station clock − page clock, from the fastest of ten round trips (its midpoint). An offset
  // within that round trip's half is measurement noise (one host: one clock), taken as 0.
  let best = null;
  for (let i = 0; i < 10; i++) {
    const sent = performance.timeOrigin + performance.now();
    const station = await api.call("station_time", {}, 2000);
    const back = performance.timeOrigin + performance.now();
    if (!best || back - sent < best.rtt) best = { rtt: back - sent, offset: station - (sent + back) / 2 };
  }
  const offset = Math.abs(best.offset) <= best.rtt / 2 ? 0 : best.offset;
  state.clockOffsetMs = offset;
  audio.clockOffsetMs = offset;
  worker?.postMessage({ type: "clock", offsetMs: offset });
}

api.on("platforms", (platforms) => { state.platforms = platforms; renderPlatforms(); });
api.on("connections", (connections) => {
  state.connections = new Map(connections.map((c) => [c.platform_id, c]));
  if (state.current && !state.connections.has(state.current) && state.override !== "pending") state.override = "idle";
  renderPlatforms();
  renderControls();
  renderPatrol();
});
api.on("telemetry", (report) => {
  state.telemetry.set(report.platform_id, { report, at: performance.now() });
  // The report lists the warnings active now: one missing there has cleared (a clearing
  // notification can be missed while the socket reconnects).
  const active = new Set((report.warnings ?? []).map((warning) => warning.name));
  for (const [key, { note }] of state.warnings) {
    if (note.platform_id === report.platform_id && !active.has(note.name)) state.warnings.delete(key);
  }
  for (const warning of report.warnings ?? []) noteWarning({ ...warning, platform_id: report.platform_id, active: true });
  renderAnnunciator();
  if (report.platform_id === state.current) { renderStatus(); renderControls(); renderPatrol(); }
  updateMap(report.platform_id);
});
api.on("notification", (note) => {
  noteWarning(note);
  addNotification(note);
  if (note.name === "control_taken" && note.active) {
    state.taken.set(note.platform_id, { note, at: performance.now() }); // said at once, until this station holds it again
    if (note.platform_id === state.current) { teleop.halt("control taken"); renderControls(); }
  }
});
api.on("video", () => {});

function setPill(selector, text, kind) {
  const pill = $(selector);
  pill.textContent = text;
  pill.className = `pill ${kind}`;
}

// ---------------------------------------------------------------- audio

const audio = new PlatformAudio(api, {
  onStats: (stats) => {
    const listen = $("#listen");
    listen.dataset.decoded = String(stats.decoded);
    $("#audio-latency").textContent = stats.latencyMs == null ? "" : `audio ${stats.latencyMs.toFixed(0)} ms`;
  },
});

$("#listen").onclick = async (event) => {
  const button = event.currentTarget;
  if (button.getAttribute("aria-pressed") === "true") {
    button.setAttribute("aria-pressed", "false");
    await audio.stopListening();
    return;
  }
  try {
    await audio.listen(state.current);
    button.setAttribute("aria-pressed", "true");
  } catch (error) { answer(`listen: ${error.message}`); }
};

async function talk(on) {
  const button = $("#talk");
  if (on === (button.getAttribute("aria-pressed") === "true")) return;
  button.setAttribute("aria-pressed", String(on));
  try {
    if (on) await audio.startTalking(state.current);
    else await audio.stopTalking(state.current);
  } catch (error) {
    button.setAttribute("aria-pressed", "false");
    answer(`push-to-talk: ${error.message}`);
    await audio.stopTalking(state.current);
  }
}
$("#talk").addEventListener("pointerdown", () => talk(true));
for (const name of ["pointerup", "pointerleave", "pointercancel"]) $("#talk").addEventListener(name, () => talk(false));
$("#talk").addEventListener("keydown", (event) => { if (event.key === "Enter" || event.key === " ") { event.preventDefault(); talk(true); } });
$("#talk").addEventListener("keyup", (event) => { if (event.key === "Enter" || event.key === " ") talk(false); });
window.addEventListener("blur", () => talk(false));

// ---------------------------------------------------------------- platforms and map

const map = new PlatformMap($("#map"), { onSelect: (id) => select(id) });

function renderPlatforms() {
  const body = $("#platforms tbody");
  body.replaceChildren(...state.platforms.map((entry) => {
    const row = document.createElement("tr");
    row.dataset.platform = entry.id;
    if (entry.id === state.current) row.classList.add("current");
    const flags = Object.entries(entry.status ?? {}).filter(([, on]) => on === true).map(([name]) => name).join(" ");
    for (const text of [entry.id, flags || "—", `${entry.age_s.toFixed(1)} s ago`]) {
      const cell = document.createElement("td");
      cell.textContent = text;
      row.append(cell);
    }
    const action = document.createElement("td");
    const button = document.createElement("button");
    button.type = "button";
    button.className = "connect";
    const connected = state.connections.has(entry.id);
    button.textContent = entry.id === state.current ? "shown" : connected ? "show" : "connect";
    button.disabled = entry.id === state.current;
    button.setAttribute("aria-label", `${connected ? "show" : "connect to"} ${entry.id}`);
    button.onclick = () => select(entry.id);
    action.append(button);
    row.append(action);
    map.update(entry.id, entry.position, heading(entry.id), { current: entry.id === state.current, connected });
    return row;
  }));
  const heard = new Set(state.platforms.map((p) => p.id));
  for (const id of map.ids()) if (!heard.has(id)) map.remove(id);
  $("#no-platforms").hidden = state.platforms.length > 0;
}

function heading(platformId) {
  const snapshot = state.telemetry.get(platformId)?.report.snapshot;
  const attitude = section(snapshot, "attitude");
  return section(snapshot, "gps")?.course ?? (attitude?.yaw != null ? 90 - attitude.yaw : null);
}

function updateMap(platformId) {
  // Where the platform's localization puts it (what its patrol steers by), else its GPS fix.
  const snapshot = state.telemetry.get(platformId)?.report.snapshot;
  const pose = section(snapshot, "pose");
  const gps = section(snapshot, "gps");
  const position = pose?.lat != null ? [pose.lat, pose.lon] : gps?.fix && gps.lat != null ? [gps.lat, gps.lon] : null;
  if (position) {
    map.update(platformId, position, heading(platformId), {
      current: platformId === state.current, connected: true,
    });
  }
}

/** Show, control and drive ``platformId``; connects first. Others stay connected. */
async function select(platformId) {
  if (platformId === state.current) return;
  teleop.halt("switched platform");
  await talk(false);
  if (audio.listening) { $("#listen").setAttribute("aria-pressed", "false"); await audio.stopListening(); }
  const previous = state.current;
  state.current = platformId;
  state.override = "idle";
  if (previous) clearArea(previous);
  setPill("#current", platformId, "ok");
  renderPlatforms();
  renderStatus();
  renderControls();
  try {
    await api.call("connect", { platform_id: platformId }, 8000);
    await api.call("console_focus", { platform_id: platformId });
  } catch (error) {
    answer(`connect to ${platformId} failed: ${error.message}`);
    return;
  }
  if (state.current !== platformId) return;
  loadArea(platformId);
  await watch(platformId);
}

// ---------------------------------------------------------------- controls

const teleop = new Teleop({
  send: (linear, angular) => api.call("console_drive", { platform_id: state.current, linear, angular }, 1000),
  onOverrideButton: () => $("#override").click(),
  onLightsButton: () => $("#lights-main").click(),
});

function answer(text) { $("#answer").textContent = text; }

function describe(result) {
  if (result && result.accepted === false) return `rejected: ${result.reason}`;
  return `acknowledged ${JSON.stringify(result?.result ?? result)}`;
}

async function command(label, method, params, timeoutMs = 5000) {
  if (!state.current) return null;
  try {
    const result = await api.call(method, { platform_id: state.current, ...params }, timeoutMs);
    answer(`${label}: ${describe(result)}`);
    return result;
  } catch (error) {
    answer(`${label}: ${error.message}`);
    return null;
  }
}

$("#override").onclick = async () => {
  if (!state.current || state.override === "pending") return;
  // During the platform's hold, pressing the switch re-engages (the deliberate act it waits for).
  const engage = !engagedHere() || holding();
  state.override = "pending";
  renderControls();
  const result = await command("manual override", "console_override", { engaged: engage }, 6000);
  if (result && result.accepted) state.override = engage ? "engaged" : "idle";
  else { state.override = "error"; state.overrideError = result ? result.reason : $("#answer").textContent; }
  renderControls();
};

for (const [selector, which, field] of [["#lights-main", "main", "main"], ["#lights-pos", "pos", "positional"]]) {
  $(selector).onclick = async (event) => {
    const on = event.currentTarget.getAttribute("aria-pressed") !== "true";
    const result = await command(`${which} lights`, "lights", { which, on });
    if (result && result.accepted !== false) $(selector).setAttribute("aria-pressed", String(on));
    void field;
  };
}
$("#set-framerate").onclick = () => command("NavCam framerate", "command", { group: 10, command: 5, payload: `navcam=${$("#framerate").value}` });
for (const [selector, label, code] of [["#diagnostics", "diagnostics", 0], ["#battery-monitor", "battery monitor", 4]]) {
  $(selector).onclick = async (event) => {
    const on = event.currentTarget.getAttribute("aria-pressed") !== "true";
    const result = await command(label, "command", { group: 20, command: code, payload: on ? "ON" : "OFF" });
    if (result && result.accepted !== false) $(selector).setAttribute("aria-pressed", String(on));
  };
}
$("#disconnect").onclick = async () => {
  const platformId = state.current;
  if (!platformId) return;
  teleop.halt("disconnect");
  await command("disconnect", "disconnect", {});
  worker?.postMessage({ type: "clear" });
  clearArea(platformId);
  state.current = null;
  state.override = "idle";
  setPill("#current", "no platform", "");
  showVideoMessage("Select a platform to see its NavCam.");
  renderPlatforms();
  renderControls();
  renderStatus();
  renderPatrol();
};

/** The shown platform holds (failsafe) for this station: driving needs a re-engage. */
function holding() {
  const failsafe = section(state.telemetry.get(state.current)?.report.snapshot, "failsafe");
  return Boolean(failsafe && failsafe.step === "hold" && failsafe.controller === state.stationId);
}

function engagedHere() {
  const connection = state.connections.get(state.current);
  const holder = controlHolder();
  return Boolean(connection && connection.this_console_drives && connection.manual_override
    && (holder === undefined || holder === state.stationId));
}

/** The station holding control of the shown platform: its telemetry (fresher than the
 * heartbeat's answer), else the connection's; null when nobody does, undefined unknown. */
function controlHolder() {
  const failsafe = section(state.telemetry.get(state.current)?.report.snapshot, "failsafe");
  if (failsafe) return failsafe.controller ?? null;
  const connection = state.connections.get(state.current);
  return connection ? connection.controller ?? null : undefined;
}

function renderAuthority(drives) {
  const holder = controlHolder();
  const box = $("#authority");
  const taken = state.taken.get(state.current);
  // The telemetry can still name this station for a moment after the 90.17 note came.
  if (taken && (drives || (holder === state.stationId && performance.now() - taken.at > 3000))) state.taken.delete(state.current);
  const other = holder != null && holder !== state.stationId;
  const [kind, text] = drives ? ["driving", "this console is driving"]
    : holder === state.stationId ? ["station", "this station holds control (not driven from this console)"]
    : other && state.taken.has(state.current) ? ["taken", `CONTROL TAKEN by station ${holder}: observing`]
    : other ? ["observing", `observing — control held by station ${holder}`]
    : ["free", "control free: engage the override to drive"];
  box.dataset.state = kind;
  box.dataset.holder = holder ?? "";
  $("#control-state").textContent = text;
  $("#takeover").hidden = !other || !$("#takeover-confirm").hidden;
  $("#takeover-holder").textContent = `station ${holder}`;
  if (!other) $("#takeover-confirm").hidden = true;
}

$("#takeover").onclick = () => {
  $("#takeover").hidden = true;
  $("#takeover-confirm").hidden = false;
  $("#takeover-yes").focus();
};
$("#takeover-no").onclick = () => { $("#takeover-confirm").hidden = true; renderControls(); };
$("#takeover-yes").onclick = async () => {
  $("#takeover-confirm").hidden = true;
  if (!state.current || state.override === "pending") return;
  state.override = "pending";
  renderControls();
  // movrd --force: the platform moves control to this station and engages its override.
  const result = await command("take control", "console_override", { engaged: true, force: true }, 6000);
  if (result && result.accepted) { state.override = "engaged"; state.taken.delete(state.current); }
  else { state.override = "error"; state.overrideError = result ? result.reason : $("#answer").textContent; }
  renderControls();
};

function renderFailsafe(entry, connection) {
  // The platform's failsafe ladder (hold, released) and this page's own view of the link.
  const banner = $("#failsafe");
  const failsafe = section(entry?.report.snapshot, "failsafe");
  const stale = entry && (performance.now() - entry.at > STALE_MS || (entry.report.link?.silence_s ?? 0) > STALE_MS / 1000);
  let step = "normal";
  let text = "";
  if (connection && connection.connected === false) {
    [step, text] = ["lost", `LINK LOST: ${connection.close_reason || "connection to the platform closed"}`];
  } else if (failsafe && failsafe.step !== "normal") {
    // This station's link is back (fresh telemetry, connected) while the platform still holds
    // for it: driving resumes only when the operator re-engages, deliberately.
    const back = !stale && connection && connection.connected !== false && failsafe.controller === state.stationId;
    step = back && failsafe.step === "hold" ? "rejoin" : failsafe.step;
    text = failsafe.step === "hold"
      ? `LINK LOST — platform on HOLD (${failsafe.reason})${back ? ". Link back: re-engage the override to drive" : ""}`
      : `LINK LOST — override released, autonomy resumed (${failsafe.reason})`;
  } else if (stale && state.override === "engaged") {
    [step, text] = ["lost", "LINK LOST: no telemetry from the platform"];
  }
  banner.dataset.step = step;
  banner.textContent = text;
  banner.hidden = !text;
}

function renderSpeedCap(snapshot) {
  const cap = section(snapshot, "speed_cap");
  const readout = $("#speed-cap");
  if (!cap) { readout.textContent = "cap —"; readout.dataset.kmh = ""; readout.title = ""; return; }
  const ms = (value) => (value == null ? "—" : `${value.toFixed(0)} ms`);
  readout.textContent = `cap ${fixed(cap.cap_kmh, 1)} km/h (video ${ms(cap.video_ms)}, command ${ms(cap.command_ms)})`;
  readout.dataset.kmh = String(cap.cap_kmh);
  readout.title = cap.reason;
}

function renderTurret(snapshot) {
  const turret = section(snapshot, "turret");
  const readout = $("#turret");
  readout.hidden = !turret;
  if (!turret) return;
  readout.dataset.trigger = turret.trigger ? "armed" : "safe";
  readout.dataset.line = turret.connected ? "up" : "down";
  // As brasidas-station status words it: why the serial line is down, else where it points;
  // then its sight (the thermal camera registered as its stream) and that stream's state.
  const streams = Object.entries(turret.streams).map(([name, stream]) => `${name} ${stream}`);
  readout.textContent = [
    "turret:",
    ...(turret.connected
      ? [turret.trigger ? "trigger ARMED" : "trigger safe", `azimuth ${fixed(turret.azimuth, 1)}°`, `elevation ${fixed(turret.elevation, 1)}°`]
      : [turret.error ? `LINE DOWN: ${turret.error}` : "LINE DOWN"]),
    streams.length ? `sight ${streams.join("  ")}` : null,
  ].filter(Boolean).join("  ");
}

function renderLights(lights) {
  // A light that cannot be switched (its GPIO chip missing, its line busy) says so and why, next
  // to its button; pressing it asks again (the platform retries the line at each switch).
  const errors = lights ? Object.entries(lights.errors) : [];
  for (const [selector, which] of [["#lights-main", "main"], ["#lights-pos", "positional"]]) {
    const error = lights ? lights.errors[which] : undefined;
    $(selector).dataset.error = error ? "true" : "";
  }
  const readout = $("#lights-error");
  readout.textContent = errors.length
    ? `lights cannot be switched: ${errors.sort().map(([which, error]) => `${which}: ${error}`).join("; ")}`
    : "";
  readout.hidden = !errors.length;
}

function renderControls() {
  const connection = state.current ? state.connections.get(state.current) : null;
  $("#controls").hidden = !connection;
  const drives = engagedHere();
  renderFailsafe(state.current ? state.telemetry.get(state.current) : null, connection);
  renderAuthority(drives);
  if (state.override !== "pending" && state.override !== "error") state.override = drives ? "engaged" : "idle";
  const button = $("#override");
  button.setAttribute("aria-pressed", String(drives));
  button.dataset.state = state.override;
  const holder = section(state.telemetry.get(state.current)?.report.snapshot, "override");
  button.textContent = {
    idle: holder?.engaged ? `override: held by ${holder.station ?? "another station"}` : "override: autonomous",
    pending: "override: pending…",
    engaged: holding() ? "override: HOLD — press to re-engage" : "override: ENGAGED",
    error: `override: error (${state.overrideError ?? "no answer"})`,
  }[state.override];
  teleop.setActive(drives);
  setPill("#driving", drives ? `this console is driving ${state.current}` : "not driving", drives ? "teleop" : "");
  const lights = section(state.telemetry.get(state.current)?.report.snapshot, "lights");
  if (lights) {
    $("#lights-main").setAttribute("aria-pressed", String(Boolean(lights.main)));
    $("#lights-pos").setAttribute("aria-pressed", String(Boolean(lights.positional)));
  }
  renderLights(lights);
  const snapshot = state.telemetry.get(state.current)?.report.snapshot;
  renderSpeedCap(snapshot);
  renderTurret(snapshot);
  if (snapshot) {
    $("#diagnostics").setAttribute("aria-pressed", String(section(snapshot, "diagnostics") != null));
    const battery = section(snapshot, "battery");
    if (battery) $("#battery-monitor").setAttribute("aria-pressed", String(Boolean(battery.monitor)));
  }
  renderStreams();
}

function renderStreams() {
  const streams = Object.entries(section(state.telemetry.get(state.current)?.report.snapshot, "streams")?.states ?? {});
  const body = $("#streams tbody");
  const wanted = streams.map(([name, stream]) => `${name}:${stream}`).join(",");
  if (body.dataset.shown === wanted) return;
  body.dataset.shown = wanted;
  body.replaceChildren(...streams.map(([name, stream]) => {
    const row = document.createElement("tr");
    row.dataset.stream = name;
    const label = document.createElement("td");
    label.textContent = `${name}: ${stream}`;
    row.append(label);
    for (const action of ["start", "pause", "stop"]) {
      const cell = document.createElement("td");
      const button = document.createElement("button");
      button.type = "button";
      button.textContent = action;
      button.setAttribute("aria-label", `${action} ${name}`);
      button.onclick = () => command(`${action} ${name}`, "console_stream", { name, action });
      cell.append(button);
      row.append(cell);
    }
    return row;
  }));
}

// ---------------------------------------------------------------- status and annunciator

const fixed = (value, digits) => (typeof value === "number" ? value.toFixed(digits) : "—");

function telemetryRows(snapshot, link) {
  const rows = [];
  const add = (name, show) => {
    const value = snapshot[name];
    if (value === null || value === undefined) return;
    const error = failure(value);
    if (error !== null) { rows.push([name, `ERROR ${error}`]); return; }
    const stale = "stale" in schema.sections[name].fields && value.stale;
    rows.push([name, show(value) + (stale ? `  STALE (${fixed(value.age_ms / 1000, 1)} s old)` : "")]);
  };
  add("override", (o) => `${o.mode}${o.engaged ? ` (override: ${o.station ?? "—"})` : ""}`);
  add("battery", (b) => `${fixed(b.volts, 1)} V ${b.level ?? (b.monitor ? "" : "monitor off")}`);
  add("controller", (c) => `${c.connected ? "connected" : "LOST"}  heatsinks ${(c.temps_c ?? []).join("/")} °C  motors ${(c.amps ?? []).join("/")} A`);
  add("gps", (g) => (g.fix
    ? `${fixed(g.lat, 6)}, ${fixed(g.lon, 6)}  ${g.sats ?? "—"} sats  hdop ${g.hdop ?? "—"}`
    : `no fix${g.lost_for_s == null ? "" : ` (${fixed(g.lost_for_s, 0)} s)`}`));
  add("attitude", (a) => `roll ${fixed(a.roll, 1)}°  pitch ${fixed(a.pitch, 1)}°  yaw ${fixed(a.yaw, 1)}°`);
  add("streams", (s) => Object.entries(s.states).map(([name, stream]) => `${name} ${stream}`).join("  ") || "none");
  add("computer", (c) => [
    c.cpu_temp_c == null ? null : `cpu ${c.cpu_temp_c} °C`,
    `load ${(c.load ?? []).map((v) => v.toFixed(2)).join(" ")}`,
    `free ${Math.round(c.mem_free_mb ?? 0)} MB`,
  ].filter(Boolean).join("  "));
  if (link) rows.push(["link", `loss ${link.loss_pct ?? "—"}%  rtt ${link.round_trip_ms ?? "—"} ms  silence ${link.silence_s ?? "—"} s${link.error ? `  ${link.error}` : ""}`]);
  return rows;
}

function reportRows(report) {
  if (!schema) return [["telemetry", "loading the telemetry schema…"]];
  if (report.schema !== schema.version) {
    return [["telemetry", `the station reports telemetry schema v${report.schema}; this page reads v${schema.version} (reload the page)`]];
  }
  return report.snapshot ? telemetryRows(report.snapshot, report.link) : [];
}

function renderStatus() {
  const list = $("#status");
  const entry = state.current ? state.telemetry.get(state.current) : null;
  renderFailsafe(entry, state.current ? state.connections.get(state.current) : null);
  if (!entry) { list.replaceChildren(); return; }
  const { report, at } = entry;
  const stale = performance.now() - at > STALE_MS || (report.link?.silence_s ?? 0) > STALE_MS / 1000;
  list.classList.toggle("stale", stale);
  const rows = reportRows(report);
  if (stale) rows.unshift(["data", `STALE (nothing new for ${((performance.now() - at) / 1000).toFixed(1)} s)`]);
  list.replaceChildren(...rows.flatMap(([name, value]) => {
    const term = document.createElement("dt");
    term.textContent = name;
    const detail = document.createElement("dd");
    detail.textContent = value;
    return [term, detail];
  }));
}
setInterval(renderStatus, 500);

function noteWarning(note) {
  const key = `${note.platform_id}/${note.name}`;
  const known = state.warnings.get(key);
  if (!note.active) { state.warnings.delete(key); renderAnnunciator(); return; }
  if (known) return;
  state.warnings.set(key, { note, acknowledged: false });
  renderAnnunciator();
}

// One button per warning, kept while the warning lasts: telemetry re-renders five times a
// second, and a button replaced between the operator's mousedown and mouseup gets no click.
const warningButtons = new Map(); // "platform/name" → its button

function renderAnnunciator() {
  const box = $("#annunciator");
  for (const [key, button] of warningButtons) {
    if (!state.warnings.has(key)) { button.remove(); warningButtons.delete(key); }
  }
  for (const [key, { note, acknowledged }] of state.warnings) {
    let button = warningButtons.get(key);
    if (!button) {
      button = document.createElement("button");
      button.type = "button";
      button.onclick = () => {
        const warning = state.warnings.get(key);
        if (warning) warning.acknowledged = true;
        renderAnnunciator();
      };
      warningButtons.set(key, button);
      box.append(button);
    }
    const text = `⚠ ${note.platform_id}: ${note.message || note.name}`;
    if (button.textContent !== text) button.textContent = text;
    button.className = `warning${acknowledged ? "" : " unacknowledged"}`;
    button.setAttribute("aria-pressed", String(acknowledged));
    button.setAttribute("aria-label", `warning ${note.platform_id} ${note.message || note.name}: ${acknowledged ? "acknowledged" : "acknowledge"}`);
  }
}

function addNotification(note) {
  const item = document.createElement("li");
  item.textContent = `${new Date(note.time * 1000).toLocaleTimeString()} ${note.platform_id} ${note.active ? "⚠" : "✓"} ${note.message}`;
  const list = $("#notifications");
  list.prepend(item);
  while (list.children.length > 20) list.lastElementChild.remove();
}

// ---------------------------------------------------------------- map backgrounds

$("#map-image").onchange = (event) => {
  const file = event.target.files[0];
  const corners = $("#map-bounds").value.split(",").map(Number);
  if (!file || corners.length !== 4 || corners.some(Number.isNaN)) {
    answer("area image: give the corners as south,west,north,east first");
    return;
  }
  map.setImage(URL.createObjectURL(file), ...corners);
};
$("#map-geojson").onchange = async (event) => {
  const file = event.target.files[0];
  if (!file) return;
  try { map.setGeoJson(JSON.parse(await file.text())); } catch (error) { answer(`GeoJSON: ${error.message}`); }
};
$("#map-clear").onclick = () => map.clearBackground();

// ---------------------------------------------------------------- patrol

// The shown platform's area map (boundary, keep-outs, named points) and waypoint route, from
// the platform (map_get through the station); its planned path and patrol state from telemetry.
// The route is edited on the map and sent as a whole (route_set); a refusal shows the
// platform's reason (a point outside the boundary, another station holding control).

const patrol = { routes: new Map(), keepouts: new Map(), editing: null, drawing: null, loading: null };

async function loadArea(platformId) {
  const asked = (patrol.loading = Symbol(platformId));
  let area;
  try {
    area = await api.call("map_get", { platform_id: platformId }, 8000);
  } catch (error) {
    patrolAnswer(`map of ${platformId}: ${error.message}`, true);
    return;
  }
  if (patrol.loading !== asked || state.current !== platformId) return;
  if (area.map) map.setGeoJson(area.map, { fit: !patrol.routes.has(platformId) }); // zoomed once
  else map.clearBackground();
  const features = area.map?.features ?? [];
  patrol.keepouts.set(platformId, features.filter((f) => f?.properties?.role === "keepout").map((f) => String(f.id)));
  renderKeepouts();
  const points = (area.route ?? []).map((waypoint) => [waypoint.lat, waypoint.lon]);
  patrol.routes.set(platformId, { points, names: (area.route ?? []).map((waypoint) => waypoint.name ?? ""), mapRev: area.map_rev });
  map.setRoute(platformId, points);
  renderPatrol();
}

window.addEventListener("brasidas:area-changed", (event) => { if (event.detail === state.current) loadArea(state.current); }); // web/mapfiles.js imported a file

function clearArea(platformId) {
  stopEditing();
  stopDrawing();
  patrol.routes.delete(platformId);
  patrol.keepouts.delete(platformId);
  renderKeepouts();
  map.setRoute(platformId, []);
  map.setPlannedPath(platformId, []);
  map.clearBackground();
}

function patrolAnswer(text, refused = false) {
  const line = $("#patrol-answer");
  line.textContent = text;
  line.classList.toggle("refused", refused);
}

function renderPatrol() {
  const panel = $("#patrol");
  const autonomy = state.current ? section(state.telemetry.get(state.current)?.report.snapshot, "autonomy") : null;
  panel.hidden = !state.current || !state.connections.has(state.current);
  if (!autonomy) { $("#patrol-state").textContent = "patrol: no report"; return; }
  const route = patrol.routes.get(state.current);
  const target = autonomy.waypoint == null ? null
    : `waypoint ${autonomy.waypoint + 1}/${autonomy.waypoints}${route?.names[autonomy.waypoint] ? ` (${route.names[autonomy.waypoint]})` : ""}`;
  const parts = [
    autonomy.enabled === false ? `${autonomy.state} (switched off)` : autonomy.state,
    target && `→ ${target}`,
    autonomy.distance_m == null ? null : `${autonomy.distance_m.toFixed(1)} m`,
    `lap ${autonomy.lap}`,
    autonomy.reason && `— ${autonomy.reason}`,
  ];
  renderKeepouts();
  const line = $("#patrol-state");
  line.textContent = `patrol: ${parts.filter(Boolean).join("  ")}`;
  line.dataset.state = autonomy.state;
  map.setPlannedPath(state.current, autonomy.path ?? []);
  // The route or the map changed elsewhere (the CLI, another station): fetch them again.
  if (route) {
    const routeMoved = route.count !== undefined && route.count !== autonomy.waypoints;
    const mapMoved = route.mapRev != null && route.mapRev !== autonomy.map_rev;
    route.count = autonomy.waypoints;
    if ((routeMoved || mapMoved) && !patrol.editing) {
      route.mapRev = autonomy.map_rev; // asked once
      loadArea(state.current);
    }
  }
}

async function patrolCall(label, method, params = {}) {
  const platformId = state.current;
  if (!platformId) return null;
  try {
    const result = await api.call(method, { platform_id: platformId, ...params }, 8000);
    patrolAnswer(`${label}: done`);
    return result;
  } catch (error) {
    patrolAnswer(`${label}: ${error.message}`, true); // the platform's reason
    return null;
  }
}

$("#patrol-start").onclick = () => patrolCall("start patrol", "patrol_start");
$("#patrol-stop").onclick = () => patrolCall("stop patrol", "patrol_stop");

function stopEditing() {
  if (!patrol.editing) return;
  patrol.editing.stop();
  patrol.editing = null;
  $("#route-edit").setAttribute("aria-pressed", "false");
  $("#route-send").hidden = true;
  $("#route-cancel").hidden = true;
}

$("#route-edit").onclick = () => {
  if (!state.current || patrol.editing) return;
  stopDrawing();
  const points = patrol.routes.get(state.current)?.points ?? [];
  const editing = { points, stop: null };
  editing.stop = map.editWaypoints(points, (changed) => { editing.points = changed; }).stop;
  patrol.editing = editing;
  $("#route-edit").setAttribute("aria-pressed", "true");
  $("#route-send").hidden = false;
  $("#route-cancel").hidden = false;
  patrolAnswer("editing the route: click the map to add a waypoint, drag one to move it, right-click one to delete it");
};

$("#route-send").onclick = async () => {
  const editing = patrol.editing;
  const platformId = state.current;
  if (!editing || !platformId) return;
  const result = await patrolCall("send route", "route_set", { waypoints: editing.points });
  if (!result || patrol.editing !== editing) return; // refused: keep editing
  stopEditing();
  patrolAnswer(`route sent: ${result.waypoints.length} waypoints${result.closed ? ", closed" : ""}`);
  await loadArea(platformId);
};

$("#route-cancel").onclick = () => { stopEditing(); patrolAnswer("route edit cancelled"); };

// ---------------------------------------------------------------- keep-out zones

// Keep-outs are added (a polygon drawn on the map) and removed (by id) without reloading the
// map (update_map, R-5.3.3.4), by the station holding control; an observer sees them read-only.
// The drawn polygon is a draft: the map shows a zone only once the platform has it (its answer,
// then map_get); a refusal (self-intersecting, the robot inside, ...) shows the platform's reason
// and leaves the draft open to correct.

/** This station may change the shown platform's map: it holds control, or nobody does. */
function mayChangeMap() {
  const holder = controlHolder();
  return Boolean(state.current && state.connections.has(state.current)) && (holder == null || holder === state.stationId);
}

const keepoutButtons = new Map(); // id → its list item (kept: see warningButtons)

function renderKeepouts() {
  const ids = patrol.keepouts.get(state.current) ?? [];
  const list = $("#keepouts");
  const allowed = mayChangeMap();
  const why = allowed ? "" : `control held by station ${controlHolder()}: read-only`;
  for (const [id, item] of keepoutButtons) if (!ids.includes(id)) { item.remove(); keepoutButtons.delete(id); }
  for (const id of ids) {
    let item = keepoutButtons.get(id);
    if (!item) {
      item = document.createElement("li");
      item.dataset.keepout = id;
      const button = document.createElement("button");
      button.type = "button";
      button.textContent = "remove";
      button.setAttribute("aria-label", `remove keep-out ${id}`);
      button.onclick = () => removeKeepout(id);
      item.append(`keep-out ${id}`, button);
      keepoutButtons.set(id, item);
      list.append(item);
    }
    const button = item.querySelector("button");
    button.disabled = !allowed;
    button.title = why;
  }
  const draw = $("#keepout-draw");
  draw.disabled = !allowed && !patrol.drawing;
  draw.title = why;
  $("#keepout-send").disabled = !allowed || !patrol.drawing || patrol.drawing.points.length < 3;
}

function stopDrawing() {
  if (!patrol.drawing) return;
  patrol.drawing.handle.stop();
  patrol.drawing = null;
  $("#keepout-draw").setAttribute("aria-pressed", "false");
  $("#keepout-drafting").hidden = true;
  renderKeepouts();
}

$("#keepout-draw").onclick = () => {
  if (patrol.drawing) { stopDrawing(); patrolAnswer("keep-out cancelled"); return; }
  if (!state.current || !mayChangeMap()) return;
  stopEditing();
  const drawing = { points: [], handle: null };
  drawing.handle = map.drawPolygon((points) => { drawing.points = points; renderKeepouts(); });
  patrol.drawing = drawing;
  $("#keepout-name").value = "";
  $("#keepout-draw").setAttribute("aria-pressed", "true");
  $("#keepout-drafting").hidden = false;
  renderKeepouts();
  patrolAnswer("drawing a keep-out: click the map for each corner (or pan the map with the arrows and add one at the centre), drag one to move it, right-click one to delete it; then send (Escape cancels)");
};

$("#keepout-corner").onclick = () => patrol.drawing?.handle.addAtCentre();
$("#keepout-cancel").onclick = () => { stopDrawing(); patrolAnswer("keep-out cancelled"); };
window.addEventListener("keydown", (event) => {
  if (event.key === "Escape" && patrol.drawing) { stopDrawing(); patrolAnswer("keep-out cancelled"); }
});

$("#keepout-send").onclick = async () => {
  const drawing = patrol.drawing;
  const platformId = state.current;
  if (!drawing || !platformId || drawing.points.length < 3) return;
  const ring = [...drawing.points, drawing.points[0]].map(([lat, lon]) => [lon, lat]); // GeoJSON: closed, lon first
  const feature = { type: "Feature", properties: { role: "keepout" }, geometry: { type: "Polygon", coordinates: [ring] } };
  const name = $("#keepout-name").value.trim();
  if (name) feature.id = name;
  const result = await patrolCall("send keep-out", "map_update", { add: [feature] });
  if (!result || patrol.drawing !== drawing) return; // refused: the draft stays, the map as it was
  stopDrawing();
  patrolAnswer(`keep-out sent: the platform's keep-outs are ${result.map.keepouts.join(", ")}`);
  if (state.current === platformId) await loadArea(platformId); // at once, not at the next push
};

async function removeKeepout(id) {
  const platformId = state.current;
  if (!platformId || !mayChangeMap()) return;
  const result = await patrolCall(`remove keep-out ${id}`, "map_update", { remove: [id] });
  if (!result) return;
  patrolAnswer(`keep-out ${id} removed: the platform's keep-outs are ${result.map.keepouts.join(", ") || "none"}`);
  if (state.current === platformId) await loadArea(platformId);
}
