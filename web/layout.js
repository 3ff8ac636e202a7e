// The map and the video swap places: the map takes the main area with the NavCam as a
// picture-in-picture in its corner, and back (the button, or the M key outside inputs).

import { $, keyForFocusedField } from "./common.js";

function swap() {
  const mapMain = document.body.classList.toggle("map-main");
  const map = $("#map");
  if (mapMain) $("#video-pane").prepend(map);
  else $("#side").prepend(map);
  $("#swap-view").setAttribute("aria-pressed", String(mapMain));
  $("#swap-view").textContent = mapMain ? "video main" : "map main";
}

export function startLayout() {
  $("#swap-view").onclick = swap;
  window.addEventListener("keydown", (event) => {
    if (event.code === "KeyM" && !keyForFocusedField(event) && !event.repeat) swap();
  });
}
