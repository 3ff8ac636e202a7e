// The instrument panel and the status list of the shown platform: ground and commanded speed,
// heading on a compass (degrees clockwise from north, as the CLI's course), roll and pitch,
// battery with an estimate of the charge and time left, link quality (loss, round trip, video
// age), the speed cap with its reason in plain sight, the command being sent (a small stick),
// a driving hint. Telemetry older than 2 s is STALE, counted from its last report.

import { $, attr, compassHeading, engagedHere, failure, fixed, put, section, snapshotOf, telemetryAgeMs } from "./common.js";
import { drivingHint, teleop } from "./controls.js";
import { state, subscribe } from "./store.js";
import { videoAgeMs } from "./video.js";

const STALE_MS = 2000;
const KMH = 3.6;
// A 7-cell lithium-ion pack (the platform's 24 V battery): empty 21.0 V, full 29.4 V, linear
// between — an estimate for the panel, the platform's own level word is shown beside it.
const CELL_EMPTY_V = 3.0, CELL_FULL_V = 4.2, CELLS = 7;
let schema = null;
const voltages = []; // [page ms, volts] of the last 10 minutes: the discharge rate

function batteryEstimate(volts) {
  if (typeof volts !== "number") return { percent: null, minutes: null };
  const percent = Math.max(0, Math.min(100, ((volts / CELLS - CELL_EMPTY_V) / (CELL_FULL_V - CELL_EMPTY_V)) * 100));
  const now = performance.now();
  if (!voltages.length || now - voltages[voltages.length - 1][0] > 5000) voltages.push([now, volts]);
  while (voltages.length && now - voltages[0][0] > 600_000) voltages.shift();
  let minutes = null;
  if (voltages.length > 6) {
    const [t0, v0] = voltages[0];
    const perMinute = (v0 - volts) / ((now - t0) / 60000);
    if (perMinute > 0.001) minutes = (volts - CELLS * CELL_EMPTY_V) / perMinute;
  }
  return { percent, minutes };
}

const PITCH_PX_PER_DEGREE = 1.5; // ±30° of pitch fills the dial

/** The artificial horizon: the world turns against the roll and slides with the pitch; with
 * no attitude reported the dial says so (a level horizon would be a guess). */
function renderHorizon(attitude) {
  const world = $("#horizon-world");
  const known = typeof attitude?.roll === "number" && typeof attitude?.pitch === "number";
  attr($("#horizon-unknown"), "visibility", known ? "hidden" : "visible");
  attr(world, "visibility", known ? "visible" : "hidden");
  if (!known) return;
  const pitch = Math.max(-30, Math.min(30, attitude.pitch));
  attr(world, "transform", `rotate(${(-attitude.roll).toFixed(1)} 50 50) translate(0 ${(pitch * PITCH_PX_PER_DEGREE).toFixed(1)})`);
  world.dataset.roll = attitude.roll.toFixed(1);
  world.dataset.pitch = attitude.pitch.toFixed(1);
}

function renderCompass(heading) {
  // No heading: no needle (a needle at north read as "heading north").
  const needle = $("#compass-needle");
  if (heading != null) attr(needle, "transform", `rotate(${heading} 50 50)`);
  attr(needle, "visibility", heading == null ? "hidden" : "visible");
  put($("#heading"), heading == null ? "unknown" : `${String(Math.round(heading) % 360).padStart(3, "0")}°`);
}

function renderStick() {
  const [linear, angular] = teleop.commanded;
  attr($("#stick-dot"), "cx", String(20 - angular * 16));
  attr($("#stick-dot"), "cy", String(20 - linear * 16));
  $("#stick").dataset.active = String(linear !== 0 || angular !== 0);
}

function renderPanel() {
  const snapshot = snapshotOf();
  const panel = $("#instruments");
  panel.hidden = !state.current;
  if (!state.current) return;
  const pose = section(snapshot, "pose");
  const gps = section(snapshot, "gps");
  const motion = section(snapshot, "motion");
  const attitude = section(snapshot, "attitude");
  const battery = section(snapshot, "battery");
  const cap = section(snapshot, "speed_cap");
  const ground = pose?.speed ?? gps?.speed ?? null;
  put($("#ground-speed"), ground == null ? "—" : `${(ground * KMH).toFixed(1)} km/h`);
  put($("#commanded-speed"), motion ? `${fixed(motion.linear, 2)} / ${fixed(motion.angular, 2)}` : "—");
  renderCompass(compassHeading(snapshot));
  renderHorizon(attitude);
  put($("#attitude"), attitude ? `roll ${fixed(attitude.roll, 1)}°  pitch ${fixed(attitude.pitch, 1)}°` : "—");
  const { percent, minutes } = batteryEstimate(battery?.volts);
  put($("#battery"), battery
    ? `${fixed(battery.volts, 1)} V  ≈${percent == null ? "—" : percent.toFixed(0)} %  ${minutes == null ? "time left —" : `≈${minutes.toFixed(0)} min left`}${battery.level ? `  (${battery.level})` : ""}`
    : "—");
  const link = state.telemetry.get(state.current)?.report.link;
  const videoAge = videoAgeMs();
  put($("#link-quality"), `loss ${link?.loss_pct ?? "—"} %  rtt ${link?.round_trip_ms ?? "—"} ms  video ${videoAge == null ? "—" : `${(videoAge / 1000).toFixed(1)} s old`}`);
  const readout = $("#speed-cap");
  if (!cap) { put(readout, "cap —"); readout.dataset.kmh = ""; put($("#speed-cap-reason"), ""); }
  else {
    const ms = (value) => (value == null ? "—" : `${value.toFixed(0)} ms`);
    put(readout, `cap ${fixed(cap.cap_kmh, 1)} km/h (video ${ms(cap.video_ms)}, command ${ms(cap.command_ms)})`);
    readout.dataset.assumed = String(cap.video_ms == null);
    readout.dataset.kmh = String(cap.cap_kmh);
    // The cap limits driving by hand; a patrol keeps its own speed: greyed, and said, then.
    const applies = engagedHere();
    readout.dataset.applies = String(applies);
    put($("#speed-cap-reason"), applies ? cap.reason : `for driving by hand (a patrol keeps its own speed): ${cap.reason}`);
  }
  put($("#drive-hint"), drivingHint());
}

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
  if (!entry) { list.replaceChildren(); list.dataset.shown = ""; list.dataset.names = ""; return; }
  const age = telemetryAgeMs(entry);
  const stale = age > STALE_MS;
  list.classList.toggle("stale", stale);
  const rows = reportRows(entry.report);
  if (stale) rows.unshift(["data", `STALE (nothing new for ${(age / 1000).toFixed(1)} s)`]);
  const shown = rows.map((row) => row.join("\t")).join("\n");
  if (list.dataset.shown === shown) return;
  list.dataset.shown = shown;
  // The same sections as drawn (each report, mostly): their values written in place.
  const names = rows.map(([name]) => name).join("\n");
  if (list.dataset.names === names) {
    rows.forEach(([, value], index) => put(list.children[2 * index + 1], value));
    return;
  }
  list.dataset.names = names;
  list.replaceChildren(...rows.flatMap(([name, value]) => {
    const term = document.createElement("dt");
    term.textContent = name;
    const detail = document.createElement("dd");
    detail.textContent = value;
    return [term, detail];
  }));
}

export function startInstruments() {
  fetch("/api/telemetry-schema.json").then((answer) => answer.json()).then((document) => { schema = document; renderStatus(); });
  subscribe("telemetry", (platformId) => { if (platformId === state.current) { renderStatus(); renderPanel(); } });
  subscribe("current", () => { voltages.length = 0; renderStatus(); renderPanel(); });
  subscribe("connections", renderPanel);
  setInterval(() => { renderStatus(); renderPanel(); }, 500);
  setInterval(renderStick, 100);
  renderPanel();
}
