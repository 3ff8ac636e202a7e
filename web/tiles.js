// The map's offline background: the operator's own tiles (an MBTiles file or a tile URL in
// the station's config, console.tiles), served by the station at /tiles/{z}/{x}/{y}. The map
// is a local metric frame (map.js), so each Web Mercator tile in sight is placed as an image
// between its corners there (straight enough over a patrol's few hundred metres). Beside the
// area image; the "tiles" box turns them off and on.

import { $, element } from "./common.js";
import { map } from "./patrol.js";

const L = window.L;
const MAX_TILES = 64; // in sight at once: a zoomed-out map asks for a coarser zoom instead
const MAX_ZOOM = 20;
const MERCATOR_M_PER_PX = 156_543.034; // at the equator, zoom 0, 256 px tiles

const lonOf = (x, z) => (x / 2 ** z) * 360 - 180;
const latOf = (y, z) => (Math.atan(Math.sinh(Math.PI * (1 - (2 * y) / 2 ** z))) * 180) / Math.PI;
const tileX = (lon, z) => Math.floor(((lon + 180) / 360) * 2 ** z);
const tileY = (lat, z) => {
  const rad = (lat * Math.PI) / 180;
  return Math.floor(((1 - Math.log(Math.tan(rad) + 1 / Math.cos(rad)) / Math.PI) / 2) * 2 ** z);
};

class TileBackground {
  constructor(frame) {
    this.frame = frame;
    this.on = true;
    this.drawn = new Map(); // "z/x/y" → its image overlay
    this.pane = frame.map.createPane("basemap");
    this.pane.style.zIndex = 150; // under the grid (tilePane, 200) and everything drawn
    frame.map.on("moveend zoomend", () => this.draw());
  }

  /** The tiles in sight, at the Mercator zoom whose pixel is nearest the screen's. */
  draw() {
    const { frame } = this;
    if (!this.on || !frame.origin) { this.clear(); return; }
    const bounds = frame.map.getBounds();
    const [south, west] = frame.geo(bounds.getSouthWest());
    const [north, east] = frame.geo(bounds.getNorthEast());
    const metresPerPixel = 1 / 2 ** frame.map.getZoom(); // CRS.Simple: a unit is a metre
    const cos = Math.cos((frame.origin[0] * Math.PI) / 180);
    let z = Math.max(0, Math.min(MAX_ZOOM, Math.round(Math.log2((MERCATOR_M_PER_PX * cos) / metresPerPixel))));
    const span = (zoom) => (tileX(east, zoom) - tileX(west, zoom) + 1) * (tileY(south, zoom) - tileY(north, zoom) + 1);
    while (z > 0 && span(z) > MAX_TILES) z -= 1;
    const wanted = new Set();
    for (let x = tileX(west, z); x <= tileX(east, z); x += 1) {
      for (let y = tileY(north, z); y <= tileY(south, z); y += 1) {
        const key = `${z}/${x}/${y}`;
        wanted.add(key);
        if (this.drawn.has(key)) continue;
        const corners = [frame.local(latOf(y + 1, z), lonOf(x, z)), frame.local(latOf(y, z), lonOf(x + 1, z))];
        const image = L.imageOverlay(`/tiles/${key}`, corners, { pane: "basemap", className: "basemap-tile", alt: "", interactive: false });
        this.drawn.set(key, image.addTo(frame.map));
      }
    }
    for (const [key, image] of this.drawn) if (!wanted.has(key)) { image.remove(); this.drawn.delete(key); }
  }

  clear() {
    for (const image of this.drawn.values()) image.remove();
    this.drawn.clear();
  }
}

export async function startTiles() {
  if (!map.available) return;
  let about;
  try {
    about = await (await fetch("/tiles.json")).json();
  } catch {
    return; // an older station: no tiles
  }
  if (!about.tiles) return;
  const background = new TileBackground(map);
  const box = element("input", { id: "map-tiles", type: "checkbox", checked: "" });
  box.onchange = () => { background.on = box.checked; background.draw(); };
  $("#map-clear").before(element("label", { title: `the station's tiles (${about.kind === "mbtiles" ? "an MBTiles file" : "a tile server, kept for offline use"})` }, box, " tiles"));
  background.draw();
  // The frame's origin comes with the first platform heard: draw once it is there.
  const waiting = setInterval(() => { if (map.origin) { clearInterval(waiting); background.draw(); } }, 500);
}
