// Map and route files for the shown platform: the operator picks a file (GeoJSON, KML, OSM,
// QGC .plan, .waypoints, ArduPilot fence, route text) and imports it as the map or the route,
// or exports the platform's route as .plan or .waypoints. The file's text goes to the station
// (map_import, route_import, route_export): it is read there by the same Python code as the
// CLI's, so the page holds no copy of any parser. After an import the patrol view reloads
// the area ("area-changed" on the store).

import { sayOn } from "./answer.js";
import { element, observerReason } from "./common.js";
import { notify, state, subscribe } from "./store.js";
import { api } from "./station.js";

const MAX_FILE_BYTES = 4 * 1024 * 1024; // brasidas.mapfiles.MAX_FILE_BYTES: refused before upload
const ACCEPT = ".plan,.waypoints,.txt,.kml,.osm,.geojson,.json,.fen,.fence";

const tools = element("div", { class: "mapfile-tools", role: "group", "aria-label": "map and route files" });
const input = element("input", { id: "mapfile", type: "file", accept: ACCEPT, "aria-label": "map or route file" });
const boundary = element("input", { id: "mapfile-boundary", type: "text", size: "8", placeholder: "boundary", "aria-label": "boundary selector" });
const keepouts = element("input", { id: "mapfile-keepouts", type: "text", size: "8", placeholder: "keep-outs", "aria-label": "keep-outs selector" });
const bbox = element("input", { id: "mapfile-bbox", type: "checkbox", "aria-label": "bounding box as boundary" });
const fence = element("input", { id: "mapfile-fence", type: "checkbox", "aria-label": "plan fence as keep-outs" });
const importMap = element("button", { type: "button", "aria-label": "import map file" }, "import map");
const importRoute = element("button", { type: "button", "aria-label": "import route file" }, "import route");
const exportPlan = element("button", { type: "button", "aria-label": "export route as plan" }, "export .plan");
const exportWaypoints = element("button", { type: "button", "aria-label": "export route as waypoints" }, "export .waypoints");
const answer = element("p", { id: "mapfile-answer", class: "muted", role: "status", "aria-live": "polite" });
function labelled(text, control) {
  const label = element("label", {}, `${text} `);
  label.append(control);
  return label;
}
function row(...children) {
  const line = element("div", { class: "mapfile-row" });
  for (const child of children) line.append(child, " "); // spaced as the page's own controls
  return line;
}
tools.append(
  row(labelled("map or route file", input)),
  row("map:", boundary, keepouts, labelled("bounding box", bbox), importMap),
  row("route:", labelled("with the plan's fence", fence), importRoute, exportPlan, exportWaypoints),
  answer,
);

function say(text, refused = false) {
  sayOn(answer, text, { refused, keepMs: 15000 });
}

function notes(result) {
  return (result.notes ?? []).length ? ` (${result.notes.join("; ")})` : "";
}

async function fileText() {
  const file = input.files?.[0];
  if (!file) throw new Error("choose a file first");
  if (file.size > MAX_FILE_BYTES) throw new Error(`${file.name} is larger than 4 MiB`);
  return { name: file.name, text: await file.text() };
}

async function run(what, work) {
  const platformId = state.current;
  if (!platformId) { say(`${what}: no platform shown`, true); return; }
  try {
    say(`${what}…`);
    say(await work(platformId));
    notify("area-changed", platformId);
  } catch (error) {
    say(`${what}: ${error.message}`, true);
  }
}

const importMapFile = () => run("import map", async (platformId) => {
  const { name, text } = await fileText();
  const result = await api.call("map_import", {
    platform_id: platformId, filename: name, text,
    boundary: boundary.value.trim(), keepouts: keepouts.value.trim(), boundary_bbox: bbox.checked,
  }, 20000);
  const area = result.map;
  return `map ${name} loaded (${result.format}): ${area.keepouts.length} keep-outs, ${area.points.length} named points${notes(result)}`;
});

const importRouteFile = () => run("import route", async (platformId) => {
  const { name, text } = await fileText();
  const result = await api.call("route_import", { platform_id: platformId, filename: name, text, fence: fence.checked }, 20000);
  return `route ${name} set (${result.format}): ${result.waypoints.length} waypoints${result.closed ? ", closed" : ""}${notes(result)}`;
});

async function exportRoute(format) {
  await run(`export .${format}`, async (platformId) => {
    const result = await api.call("route_export", { platform_id: platformId, format }, 10000);
    const link = element("a", { href: URL.createObjectURL(new Blob([result.text], { type: "text/plain" })), download: `${platformId}.${format}` });
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(link.href), 10000);
    return `${result.waypoints} waypoints exported as ${platformId}.${format}`;
  });
}
/** The file tools, with the background's under the map (folded: the column must fit a
 * 1366x768 screen with the plots in sight). */
export function startMapFiles() {
  (document.querySelector("#map-files") ?? document.body).append(tools);
  importMap.onclick = () => importMapFile();
  importRoute.onclick = () => importRouteFile();
  exportPlan.onclick = () => exportRoute("plan");
  exportWaypoints.onclick = () => exportRoute("waypoints");
  // An observer's imports would be refused: disabled before the click, saying who holds
  // control (exports only read, and stay).
  const renderImports = () => {
    const why = observerReason();
    for (const button of [importMap, importRoute]) {
      if (button.disabled !== Boolean(why)) button.disabled = Boolean(why);
      if (button.title !== why) button.title = why;
    }
  };
  subscribe("telemetry", (platformId) => { if (platformId === state.current) renderImports(); });
  subscribe("connections", renderImports);
  subscribe("current", renderImports);
}
