// The map and the patrol: the platforms heard (list and markers), the shown platform's area
// map (boundary, keep-outs, named points) and waypoint route from the platform (map_get), its
// planned path and patrol state from telemetry, route editing (sent whole: route_set) and
// keep-out zones (map_update), and the operator's offline backgrounds. An observer's patrol
// and map tools are disabled, saying who holds control. Waypoints count from 1, with names.

import { sayOn } from "./answer.js";
import { $, compassHeading, controlHolder, observerReason, put, section, snapshotOf } from "./common.js";
import { slideToConfirm } from "./confirm.js";
import { PlatformMap } from "./map.js";
import { api, select } from "./station.js";
import { state, subscribe } from "./store.js";

export const map = new PlatformMap($("#map"), { onSelect: (id) => select(id) });
const patrol = { routes: new Map(), keepouts: new Map(), editing: null, drawing: null, loading: null };
const keepoutButtons = new Map(); // id → its list item (kept: a replaced button loses its click)

const platformRows = new Map(); // id → its row in the platforms table, kept between pushes

/** The row of platform ``id``, made once: each beacon push writes what changed into it (the
 * table was rebuilt at every push, a few times a second). */
function platformRow(id) {
  let known = platformRows.get(id);
  if (known) return known;
  const row = document.createElement("tr");
  row.dataset.platform = id;
  const cells = [0, 1, 2].map(() => document.createElement("td"));
  const action = document.createElement("td");
  const button = document.createElement("button");
  button.type = "button";
  button.className = "connect";
  button.onclick = () => select(id);
  action.append(button);
  row.append(...cells, action);
  known = { row, cells, button };
  platformRows.set(id, known);
  return known;
}

function renderPlatforms() {
  const body = $("#platforms tbody");
  const rows = state.platforms.map((entry) => {
    const { row, cells, button } = platformRow(entry.id);
    row.classList.toggle("current", entry.id === state.current);
    const flags = Object.entries(entry.status ?? {}).filter(([, on]) => on === true).map(([name]) => name).join(" ");
    [entry.id, flags || "—", `${entry.age_s.toFixed(1)} s ago`].forEach((text, index) => put(cells[index], text));
    const connected = state.connections.has(entry.id);
    put(button, entry.id === state.current ? "shown" : connected ? "show" : "connect");
    button.disabled = entry.id === state.current;
    button.setAttribute("aria-label", `${connected ? "show" : "connect to"} ${entry.id}`);
    map.update(entry.id, entry.position, compassHeading(snapshotOf(entry.id)), { current: entry.id === state.current, connected });
    return row;
  });
  if (rows.length !== body.children.length || rows.some((row, index) => body.children[index] !== row)) body.replaceChildren(...rows);
  const heard = new Set(state.platforms.map((p) => p.id));
  for (const id of platformRows.keys()) if (!heard.has(id)) platformRows.delete(id);
  for (const id of map.ids()) if (!heard.has(id)) map.remove(id);
  $("#no-platforms").hidden = state.platforms.length > 0;
}

function updateMarker(platformId) {
  // Where the platform's localization puts it (what its patrol steers by), else its GPS fix.
  const snapshot = snapshotOf(platformId);
  const pose = section(snapshot, "pose");
  const gps = section(snapshot, "gps");
  const position = pose?.lat != null ? [pose.lat, pose.lon] : gps?.fix && gps.lat != null ? [gps.lat, gps.lon] : null;
  if (position) map.update(platformId, position, compassHeading(snapshot), { current: platformId === state.current, connected: true });
}

async function loadArea(platformId, { refit = false } = {}) {
  const asked = (patrol.loading = Symbol(platformId));
  let area;
  try {
    area = await api.call("map_get", { platform_id: platformId }, 8000);
  } catch (error) {
    patrolAnswer(`The map of ${platformId} could not be read: ${error.message}.`, true);
    return;
  }
  if (patrol.loading !== asked || state.current !== platformId) return;
  // Zoomed once, and again after a map file is imported (its named points were off screen).
  if (area.map) map.setArea(area.map, { fit: refit || !patrol.routes.has(platformId) });
  else map.clearArea();
  const features = area.map?.features ?? [];
  patrol.keepouts.set(platformId, features.filter((f) => f?.properties?.role === "keepout").map((f) => String(f.id)));
  const points = (area.route ?? []).map((waypoint) => [waypoint.lat, waypoint.lon]);
  patrol.routes.set(platformId, { points, names: (area.route ?? []).map((waypoint) => waypoint.name ?? ""), mapRev: area.map_rev });
  map.setRoute(platformId, points);
  renderPatrol();
}

function clearArea(platformId) {
  stopEditing();
  stopDrawing();
  patrol.routes.delete(platformId);
  patrol.keepouts.delete(platformId);
  map.setRoute(platformId, []);
  map.setPlannedPath(platformId, []);
  map.clearArea();
  renderKeepouts();
}

function patrolAnswer(text, refused = false) {
  sayOn($("#patrol-answer"), text, { refused, keepMs: 15000 });
}

function renderPatrol() {
  const panel = $("#patrol");
  panel.hidden = !state.current || !state.connections.has(state.current);
  renderTools();
  const autonomy = section(snapshotOf(), "autonomy");
  if (!autonomy) { put($("#patrol-state"), "patrol: no report"); return; }
  const route = patrol.routes.get(state.current);
  const name = autonomy.waypoint == null ? "" : route?.names[autonomy.waypoint];
  const target = autonomy.waypoint == null ? null
    : `waypoint ${autonomy.waypoint + 1}/${autonomy.waypoints}${name ? ` (${name})` : ""}`;
  const parts = [
    autonomy.enabled === false ? `${autonomy.state} (switched off)` : autonomy.state,
    target && `→ ${target}`,
    autonomy.distance_m == null ? null : `${autonomy.distance_m.toFixed(1)} m`,
    `lap ${autonomy.lap}`,
    autonomy.reason && `— ${autonomy.reason}`,
  ];
  const line = $("#patrol-state");
  put(line, `patrol: ${parts.filter(Boolean).join("  ")}`);
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

/** Patrol and map tools: disabled for an observer, saying who holds control. */
function renderTools() {
  const why = observerReason();
  for (const selector of ["#patrol-start", "#patrol-stop", "#route-edit", "#route-send"]) {
    $(selector).disabled = Boolean(why);
    $(selector).title = why;
  }
  renderKeepouts();
}

async function patrolCall(label, method, params = {}) {
  const platformId = state.current;
  if (!platformId) return null;
  try {
    const result = await api.call(method, { platform_id: platformId, ...params }, 8000);
    patrolAnswer(`${label}: done.`);
    return result;
  } catch (error) {
    patrolAnswer(`${label}: ${error.message}`, true); // the platform's reason
    return null;
  }
}

function stopEditing() {
  if (!patrol.editing) return;
  patrol.editing.stop();
  patrol.editing = null;
  $("#route-edit").setAttribute("aria-pressed", "false");
  $("#route-send").hidden = true;
  $("#route-cancel").hidden = true;
}

function editRoute() {
  if (!state.current || patrol.editing) return;
  stopDrawing();
  const points = patrol.routes.get(state.current)?.points ?? [];
  const editing = { points, stop: null };
  editing.stop = map.editWaypoints(points, (changed) => { editing.points = changed; }).stop;
  patrol.editing = editing;
  $("#route-edit").setAttribute("aria-pressed", "true");
  $("#route-send").hidden = false;
  $("#route-cancel").hidden = false;
  patrolAnswer("Editing the route: click the map to add a waypoint (a loop stays closed), drag one to move it, right-click one to delete it.");
}

async function sendRoute() {
  const editing = patrol.editing;
  const platformId = state.current;
  if (!editing || !platformId) return;
  const result = await patrolCall("send route", "route_set", { waypoints: editing.points });
  if (!result || patrol.editing !== editing) return; // refused: keep editing
  stopEditing();
  patrolAnswer(`route sent: ${result.waypoints.length} waypoints${result.closed ? ", closed" : ""}.`);
  await loadArea(platformId);
}

// Keep-outs are added (a polygon drawn on the map) and removed (by id) without reloading the
// map (update_map, R-5.3.3.4), by the station holding control; an observer sees them read-only.
// The drawn polygon is a draft: the map shows a zone only once the platform has it.

/** This station may change the shown platform's map: it holds control, or nobody does. */
function mayChangeMap() {
  const holder = controlHolder();
  return Boolean(state.current && state.connections.has(state.current)) && (holder == null || holder === state.stationId);
}

function renderKeepouts() {
  const ids = patrol.keepouts.get(state.current) ?? [];
  const list = $("#keepouts");
  const allowed = mayChangeMap();
  const why = allowed ? "" : observerReason() || "no platform shown";
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

function drawKeepout() {
  if (patrol.drawing) { stopDrawing(); patrolAnswer("Keep-out cancelled."); return; }
  if (!state.current || !mayChangeMap()) return;
  stopEditing();
  const drawing = { points: [], handle: null };
  drawing.handle = map.drawPolygon((points) => { drawing.points = points; renderKeepouts(); });
  patrol.drawing = drawing;
  $("#keepout-name").value = "";
  $("#keepout-draw").setAttribute("aria-pressed", "true");
  $("#keepout-drafting").hidden = false;
  renderKeepouts();
  patrolAnswer("Drawing a keep-out: click the map for each corner (or pan the map with the arrows and add one at the centre), drag one to move it, right-click one to delete it; then send (Escape cancels).");
}

async function sendKeepout() {
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
  patrolAnswer(`keep-out sent: the platform's keep-outs are ${result.map.keepouts.join(", ")}.`);
  if (state.current === platformId) await loadArea(platformId); // at once, not at the next push
}

async function removeKeepout(id) {
  const platformId = state.current;
  if (!platformId || !mayChangeMap()) return;
  const result = await patrolCall(`remove keep-out ${id}`, "map_update", { remove: [id] });
  if (!result) return;
  patrolAnswer(`keep-out ${id} removed: the platform's keep-outs are ${result.map.keepouts.join(", ") || "none"}.`);
  if (state.current === platformId) await loadArea(platformId);
}

export function startPatrol() {
  // Starting (or resuming) a patrol moves the robot: the button offers a slide to confirm.
  const startSlide = slideToConfirm("patrol-start-slide", "slide to confirm start patrol", () => {
    startSlide.box.hidden = true;
    patrolCall("start patrol", "patrol_start");
  });
  startSlide.box.hidden = true;
  $("#patrol-start").after(startSlide.box);
  $("#patrol-start").onclick = () => { startSlide.box.hidden = !startSlide.box.hidden; };
  $("#patrol-stop").onclick = () => patrolCall("stop patrol", "patrol_stop");
  $("#route-edit").onclick = editRoute;
  $("#route-send").onclick = sendRoute;
  $("#route-cancel").onclick = () => { stopEditing(); patrolAnswer("Route edit cancelled."); };
  $("#keepout-draw").onclick = drawKeepout;
  $("#keepout-corner").onclick = () => patrol.drawing?.handle.addAtCentre();
  $("#keepout-cancel").onclick = () => { stopDrawing(); patrolAnswer("Keep-out cancelled."); };
  $("#keepout-send").onclick = sendKeepout;
  window.addEventListener("keydown", (event) => {
    if (event.key === "Escape" && patrol.drawing) { stopDrawing(); patrolAnswer("Keep-out cancelled."); }
  });
  // The operator's backgrounds: apart from the platform's area map, which stays drawn.
  $("#map-image").onchange = (event) => {
    const file = event.target.files[0];
    const corners = $("#map-bounds").value.split(",").map(Number);
    if (!file || corners.length !== 4 || corners.some(Number.isNaN)) {
      patrolAnswer("Area image: give the corners as south,west,north,east first.", true);
      return;
    }
    map.setImage(URL.createObjectURL(file), ...corners);
  };
  $("#map-geojson").onchange = async (event) => {
    const file = event.target.files[0];
    if (!file) return;
    try { map.setGeoJson(JSON.parse(await file.text())); } catch (error) { patrolAnswer(`GeoJSON: ${error.message}.`, true); }
  };
  $("#map-clear").onclick = () => map.clearBackground();
  subscribe("area-changed", (platformId) => { if (platformId === state.current) loadArea(platformId, { refit: true }); }); // a file imported

  subscribe("platforms", renderPlatforms);
  subscribe("connections", () => { renderPlatforms(); renderPatrol(); });
  subscribe("telemetry", (platformId) => {
    updateMarker(platformId);
    if (platformId === state.current) renderPatrol();
  });
  subscribe("current", (previous) => {
    if (previous) clearArea(previous);
    renderPlatforms();
    renderPatrol();
  });
  subscribe("shown", (platformId) => loadArea(platformId));
  renderPatrol();
  return { mapPixel: (lat, lon) => map.pixel(lat, lon), map };
}
