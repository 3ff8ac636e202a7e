// Rolling 60 s plots of the shown platform's telemetry, one small chart per quantity the
// operator ticks: battery voltage, motor currents, ground speed, glass-to-glass latency and
// telemetry loss. uPlot (npm, served by the station at /static/uplot) draws them; sampled
// twice a second, so a page with every plot on stays cheap.

import { $, section, snapshotOf } from "./common.js";
import { state, subscribe } from "./store.js";

const WINDOW_S = 60;
const SAMPLE_MS = 500;
const QUANTITIES = [
  { key: "volts", label: "battery V", series: ["V"], read: (s) => [section(s, "battery")?.volts] },
  { key: "amps", label: "motor A", series: ["left A", "right A"], read: (s) => { const a = section(s, "controller")?.amps ?? []; return [a[0], a[1]]; } },
  { key: "speed", label: "speed km/h", series: ["km/h"], read: (s) => { const v = section(s, "pose")?.speed ?? section(s, "gps")?.speed; return [v == null ? null : v * 3.6]; } },
  { key: "latency", label: "glass-to-glass ms", series: ["p95 ms"], read: () => [state.video?.p95Second ?? null] },
  { key: "loss", label: "telemetry loss %", series: ["%"], read: () => [state.telemetry.get(state.current)?.report.link?.loss_pct ?? null] },
];
const COLOURS = ["#fa3", "#5fd0a0", "#7aa2d6"];
const chosen = new Set(["volts", "latency"]);
const charts = new Map(); // key → { plot, data }
let times = [];
let ago = []; // each sample's time, in seconds before the last one

/** The plots can be seen: their panel open, and not folded into the full view's closed drawer.
 * Hidden, they go on sampling (the last minute is there when opened) without drawing. */
function shown() {
  const body = document.body.classList;
  return $("#plots-panel").open && !(body.contains("full-bleed") && !body.contains("panels-open"));
}

function draw() {
  for (const chart of charts.values()) chart.plot.setData([ago, ...chart.data]);
}

/** Each plot's height: what the screen leaves for the ticked plots (their panel scrolls past
 * the third), 90 to 160 px: ~35 px was unreadable, and 1920x1080 was left 40 % empty. */
function plotHeight() {
  const share = (window.innerHeight - 540) / Math.min(3, Math.max(1, chosen.size));
  return Math.round(Math.max(90, Math.min(160, share)));
}

/** A y range around the values with a margin; 0–1 before any value. */
function aroundValues(u, min, max) {
  if (min == null || max == null) return [0, 1];
  const margin = Math.max((max - min) * 0.15, Math.abs(max) * 0.02, 0.1);
  return [min - margin, max + margin];
}

function makeChart(quantity) {
  const box = document.createElement("div");
  box.className = "plot";
  box.dataset.quantity = quantity.key;
  box.setAttribute("aria-label", `plot ${quantity.label}`);
  $("#plots").append(box);
  const width = Math.max(200, $("#plots").clientWidth - 4);
  const plot = new window.uPlot({
    width, height: plotHeight(), legend: { show: false }, cursor: { show: false },
    title: quantity.label,
    // Seconds before now, the last minute always (ticks at -60 … 0 s from the first sample);
    // y around the values (a battery at 24.7 V on a 0-based axis was a flat line).
    scales: { x: { time: false, range: () => [-WINDOW_S, 0] }, y: { range: aroundValues } },
    axes: [{ stroke: "#aab", grid: { stroke: "#223" }, size: 30, font: "11px sans-serif",
      values: (u, ticks) => ticks.map((t) => `${Math.round(t)} s`) },
      { stroke: "#aab", grid: { stroke: "#223" }, size: 48, font: "11px sans-serif", label: quantity.series[0], labelSize: 14, labelFont: "11px sans-serif" }],
    series: [{}, ...quantity.series.map((label, i) => ({ label, stroke: COLOURS[i], width: 1.5, spanGaps: false }))],
  }, [[], ...quantity.series.map(() => [])], box);
  return { plot, data: quantity.series.map(() => []), box };
}

function sample() {
  if (!window.uPlot || !state.current) return;
  const snapshot = snapshotOf();
  const now = Date.now() / 1000;
  times.push(now);
  const drop = times.findIndex((t) => now - t <= WINDOW_S);
  if (drop > 0) times = times.slice(drop);
  ago = times.map((t) => t - now);
  for (const quantity of QUANTITIES) {
    let chart = charts.get(quantity.key);
    if (!chosen.has(quantity.key)) {
      if (chart) { chart.plot.destroy(); chart.box.remove(); charts.delete(quantity.key); }
      continue;
    }
    if (!chart) { chart = makeChart(quantity); chart.data = chart.data.map(() => times.map(() => null)); charts.set(quantity.key, chart); }
    const values = quantity.read(snapshot);
    chart.data.forEach((series, i) => {
      series.push(typeof values[i] === "number" ? values[i] : null);
      if (drop > 0) series.splice(0, drop);
      while (series.length > times.length) series.shift();
      while (series.length < times.length) series.unshift(null);
    });
  }
  if (shown()) draw();
}

/** How many points each shown plot holds, per series (numbers, not gaps): for tests. */
export function plotPoints() {
  return Object.fromEntries([...charts].map(([key, chart]) => [key, chart.data.map((series) => series.filter((v) => v != null).length)]));
}

export function startPlots() {
  // Its stylesheet loaded from here, not the page's head: it must not hold up the first frame.
  const style = document.createElement("link");
  style.rel = "stylesheet";
  style.href = "/static/uplot/uPlot.min.css";
  document.head.append(style);
  const choices = $("#plot-choices");
  for (const quantity of QUANTITIES) {
    const label = document.createElement("label");
    const box = document.createElement("input");
    box.type = "checkbox";
    box.checked = chosen.has(quantity.key);
    box.onchange = () => { if (box.checked) chosen.add(quantity.key); else chosen.delete(quantity.key); };
    label.append(box, ` ${quantity.label}`);
    choices.append(label);
  }
  subscribe("current", () => {
    times = [];
    ago = [];
    for (const chart of charts.values()) { chart.plot.destroy(); chart.box.remove(); }
    charts.clear();
  });
  // The screen or the ticked set changed: every plot takes its new share.
  const resize = () => {
    const width = Math.max(200, $("#plots").clientWidth - 4);
    for (const chart of charts.values()) chart.plot.setSize({ width, height: plotHeight() });
  };
  window.addEventListener("resize", resize);
  // Shown again (the panel opened, the drawer opened, the full view left): drawn at once.
  let wasShown = shown();
  const showing = () => { const now = shown(); if (now && !wasShown) draw(); wasShown = now; };
  $("#plots-panel").addEventListener("toggle", showing);
  new MutationObserver(showing).observe(document.body, { attributes: true, attributeFilter: ["class"] });
  choices.addEventListener("change", () => setTimeout(() => { sample(); resize(); }, 0));
  setInterval(sample, SAMPLE_MS);
}
