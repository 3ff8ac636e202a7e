// The map and the video swap places: the map takes the main area with the NavCam as a
// picture-in-picture in its corner, and back (the button, or the M key outside inputs).
//
// Full view (the button, or F): the main view (video or map) fills everything under the
// header, with the other one as a picture-in-picture in its lower left, the instruments and
// the notifications over its upper right, and the values bar over it (values.js). The
// driving controls and the side panels (patrol, plots, platforms) fold into a drawer at the
// right ("panels"), so nothing is below the fold. The choice is kept for the next visit. Its
// buttons sit on the values bar, over the main view (the header has no room at 1366 px).

import { $, element, keyForFocusedField } from "./common.js";
import { addToValuesBar } from "./values.js";

const STORAGE_KEY = "brasidas.layout";

const fullButton = element("button", { id: "full-view", type: "button", "aria-pressed": "false", title: "the main view fills the screen, the instruments over it (F)" }, "full view");
const panelsButton = element("button", { id: "panels", type: "button", "aria-pressed": "false", "aria-controls": "side", title: "the controls, patrol, plots and platforms" }, "panels");
panelsButton.hidden = true;

/** Where the map and the controls belong in the current layout. */
function arrange() {
  const mapMain = document.body.classList.contains("map-main");
  const full = document.body.classList.contains("full-bleed");
  const map = $("#map");
  // In full view the map is in the main area either way: filling it, or as the inset.
  if (mapMain || full) { if (map.parentElement !== $("#video-pane")) $("#video-pane").prepend(map); }
  else if (map.parentElement !== $("#side")) $("#side").prepend(map);
  const controls = $("#controls");
  if (full) { if (controls.parentElement !== $("#side")) $("#side").prepend(controls); }
  else if (controls.parentElement !== $("#video-pane")) $("#failsafe").after(controls);
  $("#swap-view").setAttribute("aria-pressed", String(mapMain));
  $("#swap-view").textContent = mapMain ? "video main" : "map main";
  fullButton.setAttribute("aria-pressed", String(full));
  panelsButton.hidden = !full;
  panelsButton.setAttribute("aria-pressed", String(document.body.classList.contains("panels-open")));
}

function swap() {
  document.body.classList.toggle("map-main");
  arrange();
}

function remember() {
  try {
    localStorage.setItem(STORAGE_KEY, JSON.stringify({ full: document.body.classList.contains("full-bleed"), panels: document.body.classList.contains("panels-open") }));
  } catch { /* private mode: this visit only */ }
}

function toggleFull() {
  document.body.classList.toggle("full-bleed");
  arrange();
  remember();
}

function togglePanels() {
  document.body.classList.toggle("panels-open");
  arrange();
  remember();
}

export function startLayout() {
  addToValuesBar(fullButton, panelsButton); // the picture's own corner, as a video player's
  $("#swap-view").onclick = swap;
  fullButton.onclick = toggleFull;
  panelsButton.onclick = togglePanels;
  try {
    const stored = JSON.parse(localStorage.getItem(STORAGE_KEY) ?? "{}");
    document.body.classList.toggle("full-bleed", stored?.full === true);
    document.body.classList.toggle("panels-open", stored?.panels === true);
  } catch { /* a damaged entry: the default layout */ }
  arrange();
  window.addEventListener("keydown", (event) => {
    if (event.repeat || keyForFocusedField(event)) return;
    if (event.code === "KeyM") swap();
    else if (event.code === "KeyF" && !event.ctrlKey && !event.metaKey && !event.altKey) toggleFull();
  });
}
