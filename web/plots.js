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

function makeChart(quantity) {
  const box = document.createElement("div");
  box.className = "plot";
  box.dataset.quantity = quantity.key;
  box.setAttribute("aria-label", `plot ${quantity.label}`);
  $("#plots").append(box);
  const width = Math.max(200, $("#plots").clientWidth - 4);
  const plot = new window.uPlot({
    width, height: window.innerHeight < 900 ? 56 : 70, // 1366x768: the column must fit legend: { show: false }, cursor: { show: false },
    title: quantity.label,
    // Seconds before now, the last minute always (ticks at -60 … 0 s from the first sample).
    scales: { x: { time: false, range: () => [-WINDOW_S, 0] } },
    axes: [{ stroke: "#889", grid: { stroke: "#223" }, size: 20, font: "10px sans-serif",
      values: (u, ticks) => ticks.map((t) => `${Math.round(t)} s`) },
      { stroke: "#889", grid: { stroke: "#223" }, size: 36, font: "10px sans-serif" }],
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
  const ago = times.map((t) => t - now);
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
    chart.plot.setData([ago, ...chart.data]);
  }
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
    for (const chart of charts.values()) { chart.plot.destroy(); chart.box.remove(); }
    charts.clear();
  });
  setInterval(sample, SAMPLE_MS);
}
