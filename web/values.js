// The values bar (a QGroundControl user's values widget): the figures the operator chose, over
// the main view. "values…" opens the list to pick from; the choice is kept in the browser
// (localStorage) for the next visit. A value the platform does not report reads "—", never 0.
// It sits on the picture's lower edge when the video is the main view, and along the map's top
// when the map is (layout.js swaps them).

import { $, compassHeading, element, put, section, snapshotOf } from "./common.js";
import { distanceAndBearing } from "./home.js";
import { state, subscribe } from "./store.js";

const STORAGE_KEY = "brasidas.values";
const KMH = 3.6;

const number = (value, digits, unit) => (typeof value === "number" && Number.isFinite(value) ? `${value.toFixed(digits)}${unit}` : "—");
const here = (snapshot) => {
  const pose = section(snapshot, "pose");
  const gps = section(snapshot, "gps");
  if (pose?.lat != null) return [pose.lat, pose.lon];
  return gps?.fix && gps.lat != null ? [gps.lat, gps.lon] : null;
};

/** Every value that may be shown: key, its label, and how it reads from a snapshot. */
export const VALUES = [
  { key: "speed", label: "speed", read: (s) => number((section(s, "pose")?.speed ?? section(s, "gps")?.speed) * KMH, 1, " km/h") },
  { key: "heading", label: "heading", read: (s) => { const h = compassHeading(s); return h == null ? "—" : `${String(Math.round(h) % 360).padStart(3, "0")}°`; } },
  { key: "home", label: "to home", read: (s) => {
    const home = section(s, "autonomy")?.home;
    const from = here(s);
    if (!Array.isArray(home) || home.length !== 2 || !from) return "—";
    const { metres } = distanceAndBearing(from, home);
    return metres < 1000 ? `${Math.round(metres)} m` : `${(metres / 1000).toFixed(2)} km`;
  } },
  { key: "sats", label: "GPS sats", read: (s) => { const gps = section(s, "gps"); return gps ? (gps.fix ? String(gps.sats ?? "—") : "no fix") : "—"; } },
  { key: "hdop", label: "HDOP", read: (s) => number(section(s, "gps")?.hdop, 1, "") },
  { key: "volts", label: "battery", read: (s) => number(section(s, "battery")?.volts, 1, " V") },
  { key: "rtt", label: "link RTT", read: () => number(state.telemetry.get(state.current)?.report.link?.round_trip_ms, 0, " ms") },
  { key: "loss", label: "link loss", read: () => number(state.telemetry.get(state.current)?.report.link?.loss_pct, 0, " %") },
  { key: "latency", label: "glass-to-glass", read: () => number(state.video?.lastLatencyMs, 0, " ms") },
  { key: "fps", label: "video fps", read: () => (state.video ? String(state.video.fps ?? "—") : "—") },
  { key: "roll", label: "roll", read: (s) => number(section(s, "attitude")?.roll, 1, "°") },
  { key: "pitch", label: "pitch", read: (s) => number(section(s, "attitude")?.pitch, 1, "°") },
  { key: "cap", label: "hand cap", read: (s) => number(section(s, "speed_cap")?.cap_kmh, 1, " km/h") },
  { key: "cpu", label: "CPU temp", read: (s) => number(section(s, "computer")?.cpu_temp_c, 0, " °C") },
];
const DEFAULT = ["speed", "heading", "home", "sats", "hdop", "volts", "rtt", "latency"];

const bar = element("div", { id: "values-bar", class: "values-bar", role: "group", "aria-label": "values" });
const cells = element("span", { class: "values-cells" });
const choose = element("button", { id: "values-choose", type: "button", "aria-expanded": "false", "aria-controls": "values-choices", title: "choose the values shown" }, "values…");
const choices = element("div", { id: "values-choices", class: "values-choices", role: "dialog", "aria-label": "choose values", hidden: "" });
bar.append(cells, choose, choices);

/** Put ``nodes`` (the layout's buttons) on the bar, before "values…": always over the main view. */
export function addToValuesBar(...nodes) { choose.before(...nodes); }

// A cell reads "speed 0.2 km/h" as it is: no aria-label of its own (the instruments' labels,
// "heading", "battery", are the panel's).

/** The keys chosen (stored), in the list's order; the default on a first visit or a bad entry. */
export function chosenValues() {
  try {
    const stored = JSON.parse(localStorage.getItem(STORAGE_KEY) ?? "null");
    if (Array.isArray(stored)) return VALUES.map((v) => v.key).filter((key) => stored.includes(key));
  } catch { /* a damaged entry: the default */ }
  return [...DEFAULT];
}

function store(keys) {
  try { localStorage.setItem(STORAGE_KEY, JSON.stringify(keys)); } catch { /* private mode: this visit only */ }
}

function build() {
  const keys = chosenValues();
  cells.replaceChildren(...VALUES.filter((v) => keys.includes(v.key)).map((v) => element("span", { class: "value", "data-key": v.key },
    element("span", { class: "value-label" }, v.label), element("span", { class: "value-figure" }, "—"))));
  render();
}

function render() {
  const snapshot = snapshotOf();
  for (const cell of cells.children) {
    const value = VALUES.find((v) => v.key === cell.dataset.key);
    put(cell.lastChild, state.current ? value.read(snapshot) : "—");
  }
}

function buildChoices() {
  const keys = chosenValues();
  choices.replaceChildren(...VALUES.map((v) => {
    const box = element("input", { type: "checkbox", value: v.key });
    box.checked = keys.includes(v.key);
    box.onchange = () => {
      const now = [...choices.querySelectorAll("input:checked")].map((input) => input.value);
      store(now);
      build();
    };
    return element("label", {}, box, ` ${v.label}`);
  }));
}

/** On the picture's lower edge (video main) or along the map's top (map main). */
function place() {
  const host = document.body.classList.contains("map-main") ? $("#map") : $("#video-box");
  if (bar.parentElement !== host) host.append(bar);
  bar.classList.toggle("on-map", host.id === "map");
}

export function startValues() {
  choose.onclick = () => {
    const open = choices.hidden;
    if (open) buildChoices();
    choices.hidden = !open;
    choose.setAttribute("aria-expanded", String(open));
  };
  window.addEventListener("keydown", (event) => {
    if (event.key === "Escape" && !choices.hidden) { choices.hidden = true; choose.setAttribute("aria-expanded", "false"); }
  });
  // Clicks and wheel turns on the bar are the bar's, not the map's (under it in map main).
  for (const name of ["click", "dblclick", "mousedown", "wheel", "pointerdown"]) bar.addEventListener(name, (event) => event.stopPropagation());
  build();
  place();
  new MutationObserver(place).observe(document.body, { attributes: true, attributeFilter: ["class"] });
  subscribe("telemetry", (platformId) => { if (platformId === state.current) render(); });
  subscribe("current", render);
  // The decoder's figures come 10 times a second (and stop with the picture): 4 redraws a
  // second are readable, cheap, and never leave a figure of a picture that has gone.
  setInterval(render, 250);
}
