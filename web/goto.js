// Click on the map to go there (a QGroundControl user's "go to location"): the controller
// presses *go to*, clicks the map, and pulls the slider to confirm; the platform drives there
// through its planner (around keep-outs) and stops, its route kept for *start patrol*. The
// point is marked on the map until the platform is told. Observers: disabled, saying who
// holds control.

import { sayOn } from "./answer.js";
import { $, element, observerReason } from "./common.js";
import { slideToConfirm } from "./confirm.js";
import { map } from "./patrol.js";
import { api } from "./station.js";
import { state, subscribe } from "./store.js";

const button = element("button", { id: "goto", type: "button", "aria-label": "go to a point", "aria-pressed": "false" }, "go to…");
let picking = null; // stop() of the map's pick while waiting for the click
let target = null; // [lat, lon] clicked, waiting for the slide

function answer(text, refused = false) {
  sayOn($("#patrol-answer"), text, { refused, keepMs: 15000 });
}

const slide = slideToConfirm("goto-slide", "slide to go there", () => go());
slide.box.hidden = true;

function reset() {
  picking?.();
  picking = null;
  target = null;
  map.flag("goto-target", null);
  slide.box.hidden = true;
  button.setAttribute("aria-pressed", "false");
}

function pick() {
  if (picking || target) { reset(); answer("Go to cancelled."); return; }
  button.setAttribute("aria-pressed", "true");
  answer("Go to: click the map where the platform should drive (Escape cancels).");
  picking = map.pickPoint((point) => {
    picking?.();
    picking = null;
    target = point;
    map.flag("goto-target", point, "go to here");
    slide.say(`slide to go to ${point[0].toFixed(6)}, ${point[1].toFixed(6)}`);
    slide.box.hidden = false;
  });
}

async function go() {
  const [platformId, point] = [state.current, target];
  reset();
  if (!platformId || !point) return;
  try {
    await api.call("goto", { platform_id: platformId, latitude: point[0], longitude: point[1] }, 8000);
    answer(`going to ${point[0].toFixed(6)}, ${point[1].toFixed(6)}: the planner's path is on the map; start patrol goes back to the route.`);
  } catch (error) {
    answer(`go to: ${error.message}`, true); // the platform's reason (a keep-out, not armed…)
  }
}

function render() {
  const why = observerReason();
  button.disabled = Boolean(why);
  button.title = why || "click the map, then slide to confirm: the platform drives there and stops";
  if (why && (picking || target)) reset();
}

export function startGoTo() {
  $("#route-edit").before(button, slide.box);
  button.onclick = pick;
  window.addEventListener("keydown", (event) => { if (event.key === "Escape" && (picking || target)) { reset(); answer("Go to cancelled."); } });
  subscribe("current", reset);
  subscribe("telemetry", (platformId) => { if (platformId === state.current) render(); });
  subscribe("connections", render);
  render();
}
