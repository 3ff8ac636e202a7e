// Warnings and notifications. The annunciator flashes each active warning until acknowledged
// (its wording follows the platform: "telemetry silent for 3.4 s" grows); the notification
// list, kept by the station so a reload shows it, colours by severity, collapses bursts of the
// same note ("×8"), gives 24-hour times and says when a warning cleared.

import { $, clockTime } from "./common.js";
import { state, subscribe } from "./store.js";

const warnings = new Map(); // "platform/name" → { note, acknowledged }
// One button per warning, kept while the warning lasts: telemetry re-renders five times a
// second, and a button replaced between the operator's mousedown and mouseup gets no click.
const warningButtons = new Map();
const SEVERE = /^(link_lost|control_taken|battery_critical|stream_failed|temperature)/;
const MAX_ITEMS = 30;
// Routine events are not warnings: a patrol planning its path after a start or a takeover.
// Listed as information, never flashed, and their clearing is not a note of its own.
// A video stream paused or resumed (the page's own note, from the streams section) likewise.
const ROUTINE = (note) => (note.name === "patrol_holding" && /planning/i.test(note.message ?? ""))
  || /^video_(paused|resumed)$/.test(note.name);
const streamStates = new Map(); // "platform/stream" → its last state

function noteWarning(note) {
  const key = `${note.platform_id}/${note.name}`;
  if (note.active && ROUTINE(note)) { warnings.delete(key); return; }
  if (!note.active) { warnings.delete(key); return; }
  const known = warnings.get(key);
  if (known) known.note = { ...known.note, message: note.message || known.note.message };
  else warnings.set(key, { note, acknowledged: false });
}

function renderAnnunciator() {
  const box = $("#annunciator");
  for (const [key, button] of warningButtons) {
    if (!warnings.has(key)) { button.remove(); warningButtons.delete(key); }
  }
  for (const [key, { note, acknowledged }] of warnings) {
    let button = warningButtons.get(key);
    if (!button) {
      button = document.createElement("button");
      button.type = "button";
      button.onclick = () => {
        const warning = warnings.get(key);
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

const routineShown = new Set(); // "platform/name" of routine notes listed, whose clearing is not

function severity(note) {
  if (!note.active) return "cleared";
  if (ROUTINE(note)) return "info";
  return SEVERE.test(note.name) ? "critical" : "warning";
}

function addNotification(note) {
  const list = $("#notifications");
  const key = `${note.platform_id}/${note.name}`;
  if (!note.active && routineShown.delete(key)) return;
  const kind = severity(note);
  if (kind === "info") routineShown.add(key);
  const mark = kind === "info" ? "ℹ" : note.active ? "⚠" : "✓ cleared:";
  const text = `${note.platform_id} ${mark} ${note.message || note.name}`;
  const first = list.firstElementChild;
  if (first && first.dataset.text === text) { // a burst: one line, counted
    const count = Number(first.dataset.count) + 1;
    first.dataset.count = String(count);
    first.querySelector(".count").textContent = ` ×${count}`;
    first.querySelector("time").textContent = clockTime(note.time);
    return;
  }
  const item = document.createElement("li");
  item.className = `note ${kind}`;
  item.dataset.text = text;
  item.dataset.count = "1";
  const time = document.createElement("time");
  time.textContent = clockTime(note.time);
  const count = document.createElement("span");
  count.className = "count";
  item.append(time, ` ${text}`, count);
  list.prepend(item);
  while (list.children.length > MAX_ITEMS) list.lastElementChild.remove();
}

/** A note when a video stream pauses (frozen on purpose, not lost) and when it plays again. */
function noteStreamPauses(platformId, report) {
  for (const [name, now] of Object.entries(report?.snapshot?.streams?.states ?? {})) {
    const key = `${platformId}/${name}`;
    const before = streamStates.get(key);
    streamStates.set(key, now);
    if (before === undefined || before === now || (now !== "paused" && before !== "paused")) continue;
    const paused = now === "paused";
    addNotification({
      platform_id: platformId,
      name: paused ? "video_paused" : "video_resumed",
      message: paused ? `${name} paused: the picture is held (start resumes it)` : `${name} ${now} again`,
      time: Date.now() / 1000,
      active: true,
    });
  }
}

export function startNotifications() {
  subscribe("telemetry", (platformId) => {
    // The report lists the warnings active now, with today's wording: one missing there has
    // cleared (a clearing notification can be missed while the socket reconnects).
    const report = state.telemetry.get(platformId)?.report;
    noteStreamPauses(platformId, report);
    const active = new Set((report?.warnings ?? []).map((warning) => warning.name));
    for (const [key, { note }] of warnings) {
      if (note.platform_id === platformId && !active.has(note.name)) warnings.delete(key);
    }
    for (const warning of report?.warnings ?? []) noteWarning({ ...warning, platform_id: platformId, active: true });
    renderAnnunciator();
  });
  subscribe("notification", (note) => {
    if (!note.replayed) noteWarning(note);
    addNotification(note);
    renderAnnunciator();
  });
}
