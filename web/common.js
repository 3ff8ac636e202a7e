// Small helpers every view uses: element lookup, telemetry sections, number formatting, and
// who holds control of the shown platform.

import { state } from "./store.js";

export const $ = (selector, root = document) => root.querySelector(selector);

/** A new element with ``attributes`` and ``children`` (nodes or text), for views that build
 * their own part of the page (map files, recordings). */
export function element(tag, attributes = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attributes)) node.setAttribute(name, value);
  for (const child of children) if (child !== "") node.append(child);
  return node;
}

/** Set an element's text only when it changed (a write forces layout work). */
export function put(element, text) {
  if (element.textContent !== text) element.textContent = text;
}

/** Set an attribute only when it changed: an SVG attribute (a dial's needle, the stick's dot)
 * set to the value it has still costs the page a style recalc and a layout. */
export function attr(element, name, value) {
  if (element.getAttribute(name) !== value) element.setAttribute(name, value);
}

export const fixed = (value, digits) => (typeof value === "number" ? value.toFixed(digits) : "—");

/** A section's error text when its source failed, else null. */
export function failure(value) {
  return value && Object.keys(value).length === 1 && typeof value.error === "string" ? value.error : null;
}

/** The section's value, or null when absent or failed. Telemetry is read by the schema's
 * field names (/api/telemetry-schema.json); tests/test_web_console.py checks each name read. */
export function section(snapshot, name) {
  const value = snapshot?.[name];
  return value && failure(value) === null ? value : null;
}

/** The shown platform's latest snapshot, or null. */
export function snapshotOf(platformId = state.current) {
  return platformId ? state.telemetry.get(platformId)?.report.snapshot ?? null : null;
}

export function setPill(selector, text, kind) {
  const pill = $(selector);
  put(pill, text);
  if (pill.className !== `pill ${kind}`) pill.className = `pill ${kind}`;
}

/** Compass heading (degrees clockwise from north, 0–360) of a platform: its localization's,
 * else its GPS course; null when neither knows (as `brasidas-station status` says "heading
 * unknown"). Never the IMU's yaw: counted from where the platform was powered up, not north. */
export function compassHeading(snapshot) {
  const degrees = section(snapshot, "pose")?.heading ?? section(snapshot, "gps")?.course ?? null;
  return degrees == null ? null : ((degrees % 360) + 360) % 360;
}

/** 24-hour clock time of a Unix time in seconds, as the video clock shows it. */
export function clockTime(seconds) {
  return new Date(seconds * 1000).toLocaleTimeString("en-GB", { hour12: false });
}

/** The station holding control of the shown platform: its telemetry (fresher than the
 * heartbeat's answer), else the connection's; null when nobody does, undefined unknown. */
export function controlHolder() {
  const failsafe = section(snapshotOf(), "failsafe");
  if (failsafe) return failsafe.controller ?? null;
  const connection = state.connections.get(state.current);
  return connection ? connection.controller ?? null : undefined;
}

/** Another station holds control: this console observes (its controls are disabled). */
export function observing() {
  const holder = controlHolder();
  return holder != null && holder !== state.stationId;
}

/** Why a control is disabled for an observer ("" when it is not). */
export function observerReason() {
  return observing() ? `${controlHolder()} holds control of ${state.current}: take control to use this` : "";
}

const HELD_REFUSAL = /[\w.]+ refused: control held by station ([\w.-]+?)(?=\.?$|[;)\s])/;

/** A refusal in words: the platform's "set_waypoints refused: control held by station X"
 * (a method name, and "station" twice with ids like station-1) becomes "X holds control of
 * P: take control first" wherever it is quoted. Other text passes unchanged. */
export function plainReason(reason) {
  const text = String(reason ?? "");
  return text.replace(HELD_REFUSAL, (_, holder) => `${holder} holds control of ${state.current ?? "the platform"}: take control first`);
}

/** This console engaged the shown platform's override and this station holds control. */
export function engagedHere() {
  const connection = state.connections.get(state.current);
  const holder = controlHolder();
  return Boolean(connection && connection.this_console_drives && connection.manual_override
    && (holder === undefined || holder === state.stationId));
}

/** The shown platform holds (failsafe) for this station: driving needs a re-engage. */
export function holding() {
  const failsafe = section(snapshotOf(), "failsafe");
  return Boolean(failsafe && failsafe.step === "hold" && failsafe.controller === state.stationId);
}

/** Telemetry is stale: nothing new from the platform for ``limitMs``. Counted from its last
 * report: the station's silence when the page got it plus the time since (a report pushed
 * again unchanged is no news). */
export function telemetryAgeMs(entry) {
  if (!entry) return null;
  return (entry.report.link?.silence_s ?? 0) * 1000 + (performance.now() - entry.at);
}

const TEXT_INPUTS = new Set(["text", "search", "email", "password", "url", "tel"]);
const NUMBER_KEYS = /^(Digit|Numpad|Minus|Period|Comma|Backspace|Delete|Arrow(Up|Down)$|Home|End|Enter|Tab)/;

/** Whether a key belongs to the element that has focus (a letter typed into a text box, a digit
 * or ↑/↓ in a number box) rather than to the console's keys (drive, M). A ticked checkbox, a
 * button or a number box keep no letters: focus there used to swallow W, the arrows and M. */
export function keyForFocusedField(event) {
  const target = event.target;
  if (target instanceof HTMLTextAreaElement || target instanceof HTMLSelectElement) return true;
  if (target instanceof HTMLElement && target.isContentEditable) return true;
  if (!(target instanceof HTMLInputElement)) return false;
  if (TEXT_INPUTS.has(target.type)) return true;
  if (target.type === "number" || target.type === "range") return NUMBER_KEYS.test(event.code);
  return false;
}
