// What the lidar sees, on the map: the platform's latest scan (a dot a 5° sector, around the
// platform as its telemetry places it), the obstacles it makes of it (rings at their size),
// and the occupancy grid the platform keeps (an image under everything else, fetched with
// perception_grid when the lidar_view section's revision moves). The obstacles that became
// the patrol's temporary keep-outs (lidar:N) are the area map's, drawn in their own colour.

import { compassHeading, section, snapshotOf } from "./common.js";
import { map } from "./patrol.js";
import { api } from "./station.js";
import { state, subscribe } from "./store.js";

const L = window.L;
const OCCUPIED_PERCENT = 65; // brasidas/perception/view.py
const UNKNOWN = 255;
const SCAN_STYLE = { radius: 2, color: "#ff5a5a", weight: 0, fillOpacity: 0.9, interactive: false, className: "lidar-point" };
const OBSTACLE_STYLE = { color: "#ffb347", weight: 2, fill: false, interactive: false, className: "lidar-obstacle" };

const drawn = { platform: null, scan: null, obstacles: null, grid: null, gridRev: 0, fetching: null };

/** Where the platform is and which way it faces: its pose (as its marker), else the lidar's
 * fused pose. */
function placement(snapshot) {
  const pose = section(snapshot, "pose");
  const view = section(snapshot, "lidar_view");
  const heading = compassHeading(snapshot) ?? view?.fused_heading_deg ?? null;
  if (pose?.lat != null && heading != null) return { at: [pose.lat, pose.lon], heading };
  if (view?.fused_lat != null) return { at: [view.fused_lat, view.fused_lon], heading: view.fused_heading_deg ?? 0 };
  return null;
}

/** Map position (local [north, east]) of a point ``range`` metres at ``bearing`` degrees
 * clockwise from the platform's forward axis. */
function around(centre, heading, bearing, range) {
  const angle = ((heading + bearing) * Math.PI) / 180;
  return [centre[0] + range * Math.cos(angle), centre[1] + range * Math.sin(angle)];
}

function clear() {
  for (const key of ["scan", "obstacles", "grid"]) {
    drawn[key]?.remove();
    drawn[key] = null;
  }
  drawn.gridRev = 0;
}

function render() {
  if (!map.available || !L) return;
  if (drawn.platform !== state.current) {
    clear();
    drawn.platform = state.current;
  }
  const snapshot = snapshotOf();
  const view = section(snapshot, "lidar_view");
  const where = placement(snapshot);
  const ranges = where ? view?.ranges_dm ?? [] : [];
  const centre = where ? map.local(where.at[0], where.at[1]) : null;
  const points = [];
  const width = ranges.length ? 360 / ranges.length : 0;
  ranges.forEach((dm, k) => { if (dm > 0) points.push(around(centre, where.heading, k * width, dm / 10)); });
  drawn.scan ??= L.layerGroup().addTo(map.map);
  redraw(drawn.scan, points, (point) => L.circleMarker(point, SCAN_STYLE));
  const obstacles = where ? section(snapshot, "perception")?.obstacles ?? [] : [];
  drawn.obstacles ??= L.layerGroup().addTo(map.map);
  const rings = obstacles.map(([bearing, range, radius]) => ({ at: around(centre, where.heading, bearing, range), radius: Math.max(0.2, radius) }));
  redraw(drawn.obstacles, rings, (ring) => L.circle(ring.at, { ...OBSTACLE_STYLE, radius: ring.radius }), (layer, ring) => { layer.setLatLng(ring.at); layer.setRadius(ring.radius); });
  if (view?.grid_rev && view.grid_rev !== drawn.gridRev && !drawn.fetching) fetchGrid(state.current, view.grid_rev);
}

/** Reuse the group's layers (moved) rather than rebuilding them: this runs on every report. */
function redraw(group, items, make, move = (layer, item) => layer.setLatLng(item)) {
  const layers = group.getLayers();
  items.forEach((item, index) => {
    if (index < layers.length) move(layers[index], item);
    else group.addLayer(make(item));
  });
  for (const layer of layers.slice(items.length)) group.removeLayer(layer);
}

async function fetchGrid(platformId, rev) {
  drawn.fetching = (async () => {
    try {
      const grid = await api.call("perception_grid", { platform_id: platformId }, 8000);
      if (platformId !== state.current || !grid?.rev) return;
      const url = await gridImage(grid);
      const south = map.local(grid.south_west[0], grid.south_west[1]);
      const north = map.local(grid.north_east[0], grid.north_east[1]);
      drawn.grid?.remove();
      drawn.grid = L.imageOverlay(url, [south, north], { className: "lidar-grid", interactive: false, alt: "occupancy grid" }).addTo(map.map);
      drawn.grid.bringToBack();
      drawn.grid.getElement()?.setAttribute("data-rev", String(grid.rev));
      drawn.gridRev = rev;
    } catch {
      drawn.gridRev = rev; // refused or gone: wait for the next revision rather than asking again
    } finally {
      drawn.fetching = null;
    }
  })();
}

/** The grid's cells (zlib, base64) as a PNG data URL: obstacles light, free space faint,
 * never-seen cells transparent; row 0 is the southernmost, drawn at the bottom. */
async function gridImage(grid) {
  const packed = Uint8Array.from(atob(grid.cells), (c) => c.charCodeAt(0));
  const stream = new Blob([packed]).stream().pipeThrough(new DecompressionStream("deflate"));
  const cells = new Uint8Array(await new Response(stream).arrayBuffer());
  const canvas = document.createElement("canvas");
  canvas.width = grid.columns;
  canvas.height = grid.rows;
  const context = canvas.getContext("2d");
  const image = context.createImageData(grid.columns, grid.rows);
  for (let row = 0; row < grid.rows; row += 1) {
    for (let column = 0; column < grid.columns; column += 1) {
      const value = cells[row * grid.columns + column];
      const at = ((grid.rows - 1 - row) * grid.columns + column) * 4;
      if (value === UNKNOWN) continue;
      const occupied = value >= OCCUPIED_PERCENT;
      image.data.set(occupied ? [235, 235, 235, 230] : [95, 208, 160, 40], at);
    }
  }
  context.putImageData(image, 0, 0);
  return canvas.toDataURL("image/png");
}

export function startPerception() {
  subscribe("telemetry", (platformId) => { if (platformId === state.current) render(); });
  subscribe("current", render);
  render();
}
