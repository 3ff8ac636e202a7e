// The map: offline only. Leaflet (Debian's libjs-leaflet, served by the station) in a local
// metric frame (CRS.Simple: x east, y north, in metres from an origin), over a plain grid, an
// operator-loaded area image with its corner coordinates, or a GeoJSON background.
//
// For autonomous patrol: setRoute / setPlannedPath draw a platform's waypoint route and the
// path its planner chose; editWaypoints(points, onChange) lets the operator edit a route and
// drawPolygon(onChange) draw a keep-out zone (click the map to append a point, drag one to move
// it, right-click one to delete it). Points are [lat, lon] throughout.

const L = window.L;
const EARTH_M_PER_DEG = 111_320;
const TRACK_POINTS = 600;

const INSET_ROOM_PX = 360; // the NavCam inset's width in map main, and a margin
const REFIT_SETTLE_MS = 1000; // after a swap, each resize of the map fits it again

export class PlatformMap {
  constructor(element, { onSelect }) {
    this.onSelect = onSelect;
    this.origin = null; // [lat, lon] of local (0, 0)
    this.markers = new Map();
    this.background = null;
    this.declutterRuns = 0; // read by the tests: one run per frame at most, only after a change
    this.forgetLabelBoxes(); // labelOffsets: a platform's name → side → its box relative to
    // its icon; tooltipBoxes: a named point's or waypoint's tooltip → direction → its box, in
    // the view labelView (zoom, pan, the map's place on the page)
    this.available = Boolean(L);
    if (!this.available) {
      element.textContent = "Map unavailable: Leaflet not installed on the station (make deps installs libjs-leaflet).";
      return;
    }
    this.map = L.map(element, { crs: L.CRS.Simple, minZoom: -6, maxZoom: 6, zoomSnap: 0.5, attributionControl: false });
    this.map.setView([0, 0], 1);
    new (metricGrid())({ minZoom: -6, maxZoom: 6 }).on("tileload", () => this.declutterSoon()).addTo(this.map);
    L.control.scale({ imperial: false, position: "bottomright" }).addTo(this.map); // CRS.Simple: metres
    this.area = null; // the platform's area map: under, and apart from, the operator's background
    // Until the operator takes the view (drags, scrolls, zooms) or a background is fitted, the
    // view follows the platforms: all of them in sight. Centring the first one alone left a
    // second rover 130 m away off the map, where it could be neither seen nor clicked.
    this.following = true;
    this.framed = false; // the view has been set on a platform at least once
    const taken = () => { this.following = false; };
    this.map.on("dragstart dblclick", taken);
    element.addEventListener("wheel", taken, { passive: true });
    element.addEventListener("keydown", (event) => { if (/^(Arrow|[-+=_])/.test(event.key)) taken(); });
    this.map.zoomControl?.getContainer()?.addEventListener("click", taken);
    // Leaflet keeps the container's size from when it looked last: when the layout changes it
    // (the stylesheet applying after the map was made, a resized window) fitting uses a stale
    // size and a marker can sit outside the visible map, where it cannot be clicked.
    new ResizeObserver(() => {
      this.map.invalidateSize();
      if (performance.now() < this.refitUntil) this.refit(); // the swap's layout settling
    }).observe(element);
    this.refitUntil = 0;
    this.shown = null; // the platform shown (the re-centre button's)
    const centre = L.control({ position: "topleft" });
    centre.onAdd = () => {
      const button = L.DomUtil.create("button", "map-centre");
      button.type = "button";
      button.textContent = "centre";
      button.title = "centre on the platform shown (the view follows it again)";
      button.setAttribute("aria-label", "centre on the platform");
      L.DomEvent.disableClickPropagation(button);
      button.onclick = () => this.centreOnShown();
      return button;
    };
    centre.addTo(this.map);
    // Map main (layout.js): the NavCam inset sits over the map's lower left; what is fitted
    // (the area, the route, the platforms) is fitted beside it, not under it. In the full view
    // the instruments (and the panels drawer, when open) cover the right as well.
    const layout = () => ["map-main", "full-bleed", "panels-open"].map((name) => document.body.classList.contains(name)).join();
    new MutationObserver(() => {
      if (layout() === this.layout) return;
      this.layout = layout();
      this.inset = document.body.classList.contains("map-main");
      this.refitUntil = performance.now() + REFIT_SETTLE_MS;
      requestAnimationFrame(() => this.refit());
    }).observe(document.body, { attributes: true, attributeFilter: ["class"] });
    this.layout = layout();
    this.inset = document.body.classList.contains("map-main");
    this.map.on("zoomend moveend resize", () => this.declutterSoon());
  }

  /** fitBounds' padding: room for the NavCam inset on the left in map main, and in the full
   * view for the values bar above and the instruments (and open drawer) on the right. */
  fitPadding() {
    if (!this.inset) return {};
    if (!document.body.classList.contains("full-bleed")) return { paddingTopLeft: [INSET_ROOM_PX, 20], paddingBottomRight: [20, 20], animate: false };
    const covered = (selector) => { const box = document.querySelector(selector)?.getBoundingClientRect(); return box?.width ? box.width + 20 : 0; };
    const right = covered("#middle") + (document.body.classList.contains("panels-open") ? covered("#side") : 0);
    return { paddingTopLeft: [covered("#video-box") || INSET_ROOM_PX, 60], paddingBottomRight: [Math.max(20, right), 20], animate: false };
  }

  /** Fit the area, the routes and the platforms again (after the layout changed). */
  refit() {
    this.map.invalidateSize({ pan: false }); // the map just moved: its new size, not the old
    const bounds = L.latLngBounds([]);
    if (this.area) bounds.extend(this.area.getBounds());
    for (const { layer } of this.waypointLabels?.values() ?? []) layer.eachLayer((point) => bounds.extend(point.getLatLng()));
    for (const entry of this.markers.values()) bounds.extend(entry.marker.getLatLng());
    if (!bounds.isValid()) return;
    this.map.fitBounds(bounds, this.fitPadding());
    this.following = false; // following one platform would pan the fitted route out again
  }

  /** Re-centre on the platform shown (else every platform) and follow again. */
  centreOnShown() {
    const entry = this.shown ? this.markers.get(this.shown) : null;
    this.following = true;
    if (entry) this.map.setView(entry.marker.getLatLng(), Math.max(this.map.getZoom(), 1), { animate: false });
    else this.followPlatforms();
  }

  /** Local metres [north, east] (Leaflet's [y, x] in CRS.Simple) of a WGS-84 position. */
  local(lat, lon) {
    if (!this.origin) this.origin = [lat, lon];
    const [lat0, lon0] = this.origin;
    return [(lat - lat0) * EARTH_M_PER_DEG, (lon - lon0) * EARTH_M_PER_DEG * Math.cos((lat0 * Math.PI) / 180)];
  }

  /** One platform at ``position`` [lat, lon] with ``heading`` degrees (0 north, clockwise). */
  update(id, position, heading, { current = false, connected = false } = {}) {
    if (!this.available || !position) return;
    if (current) this.shown = id;
    else if (this.shown === id) this.shown = null;
    const point = this.local(position[0], position[1]);
    let entry = this.markers.get(id);
    if (!entry) {
      const marker = L.marker(point, { icon: platformIcon(id, 0, false, false), keyboard: true, title: id, alt: `platform ${id}` });
      marker.on("click", () => this.onSelect(id));
      const track = L.polyline([], { color: "#e8a33d", weight: 2, opacity: 0.7 });
      marker.addTo(this.map);
      track.addTo(this.map);
      entry = { marker, track, points: [] };
      this.markers.set(id, entry);
    }
    const last = entry.points[entry.points.length - 1];
    if (!last || Math.hypot(last[0] - point[0], last[1] - point[1]) > 0.05) {
      entry.points.push(point);
      if (entry.points.length > TRACK_POINTS) entry.points.shift();
      entry.track.setLatLngs(entry.points);
    }
    // Without a reported heading (a platform not connected): the direction of its track.
    const before = entry.points[entry.points.length - 2];
    if (heading == null && before) heading = (Math.atan2(point[1] - before[1], point[0] - before[0]) * 180) / Math.PI;
    entry.marker.setLatLng(point);
    entry.current = current;
    // A new icon only when it looks different: rebuilding it five times a second is the
    // page's costliest work otherwise. Its name keeps the side the last declutter gave it. A
    // new heading turns the arrow of the icon drawn (a platform standing still reports one
    // that wanders: each report would have rebuilt it).
    const look = `${Math.round(heading ?? 0)}|${current}|${connected}`;
    if (entry.look !== look) {
      const arrow = entry.look?.endsWith(`|${current}|${connected}`) && entry.marker.options.icon.options.html.querySelector?.(".arrow");
      if (arrow) arrow.style.transform = `rotate(${Number(heading) || 0}deg)`;
      else entry.marker.setIcon(platformIcon(id, heading ?? 0, current, connected, entry.labelSide));
      entry.look = look;
    }
    if (this.following) this.followPlatforms();
    // Labels are placed again only when the marker moved on screen (a report at 10 Hz of a
    // robot at walking pace moves it less than a pixel; view changes declutter by themselves).
    const at = this.map.latLngToContainerPoint(point);
    if (!entry.placedAt || Math.abs(at.x - entry.placedAt.x) >= 1 || Math.abs(at.y - entry.placedAt.y) >= 1 || entry.placedLook !== look) {
      entry.placedAt = at;
      entry.placedLook = look;
      this.declutterSoon();
    }
  }

  /** Labels never cover each other: platform names (the shown platform's first), the area
   * map's named points (right, left, above, below), the route's waypoint numbers (left, above,
   * below), then the grid's distances (along their line), each hidden when no place is free,
   * until the view gives it room. Placed by their drawn boxes, after every view change, marker
   * move and new grid tile.
   *
   * Every box is read first and every change written after, so a run costs the page one layout
   * (the one its next frame needs anyway). A label's box on a side it is not on is the one
   * measured when it last stood there: a platform's name relative to its icon (its offset on
   * each side is fixed by the stylesheet), a named point's or waypoint's in this view (the same
   * zoom, pan and map box). Only a side not measured yet is tried on the page (a write and a
   * forced layout each), once. Trying every side on the page at every marker move was the
   * console's costliest work: ~15 forced layouts a run, 5 runs a second. */
  declutter() {
    this.declutterPending = false;
    if (!this.available) return;
    this.declutterRuns += 1;
    // Nor over the map's own controls (zoom, scale bar) or a platform's arrow.
    // Nor over the values bar, a flag, a route's or keep-out's editing markers, a named point.
    const container = this.map.getContainer();
    const placed = [...container.querySelectorAll(".leaflet-control, .platform-icon .arrow, .values-bar, .map-flag, .leaflet-marker-icon:not(:has(.platform-icon)), .area-point")]
      .map((element) => element.getBoundingClientRect());
    // Nor under what lies over the map (layout.js): the NavCam inset in map main, and in the
    // full view the instruments and the open drawer.
    const classes = document.body.classList;
    const over = [classes.contains("map-main") && "#video-box", classes.contains("full-bleed") && "#middle", classes.contains("panels-open") && classes.contains("full-bleed") && "#side"];
    for (const selector of over.filter(Boolean)) {
      const box = document.querySelector(selector)?.getBoundingClientRect();
      if (box?.width) placed.push(box);
    }
    // The view the tooltips' measured boxes belong to: any pan, zoom or move of the map
    // forgets them.
    const frame = container.getBoundingClientRect();
    const view = [this.map.getZoom(), this.map.getPixelOrigin(), this.map.containerPointToLayerPoint([0, 0]), frame.left, frame.top, frame.width, frame.height].join();
    if (view !== this.labelView) { this.labelView = view; this.tooltipBoxes = new WeakMap(); }
    // Each label in placing order, with its box where it stands now (still reading).
    const labels = [];
    for (const entry of [...this.markers.values()].sort((a, b) => Number(b.current) - Number(a.current))) {
      const icon = entry.marker.getElement()?.querySelector(".platform-icon");
      const label = icon?.querySelector("span");
      if (!label) continue;
      const at = icon.getBoundingClientRect();
      const offsets = this.labelOffsets.get(label) ?? new Map();
      this.labelOffsets.set(label, offsets);
      const standing = LABEL_SIDES.find((name) => icon.classList.contains(`label-${name}`)) ?? "right";
      offsets.set(standing, shifted(label.getBoundingClientRect(), -at.left, -at.top));
      const standOn = (side) => {
        entry.labelSide = side;
        for (const other of LABEL_SIDES) icon.classList.toggle(`label-${other}`, other === side);
      };
      // The side it has first (a label that jumps at every move is hard to follow).
      const first = entry.labelSide ?? "right";
      labels.push({
        element: label,
        sides: [first, ...LABEL_SIDES.filter((name) => name !== first)],
        keep: entry.current,
        box: (side) => {
          if (!offsets.has(side)) { // never measured on this side: on the page, once
            standOn(side);
            offsets.set(side, shifted(label.getBoundingClientRect(), -at.left, -at.top));
          }
          return shifted(offsets.get(side), at.left, at.top);
        },
        standOn,
      });
    }
    const tooltips = (group, directions) => group?.eachLayer((layer) => {
      const tooltip = layer.getTooltip?.();
      const element = tooltip?.getElement?.();
      if (!element || !tooltip.options.permanent) return;
      const boxes = this.tooltipBoxes.get(element) ?? new Map();
      this.tooltipBoxes.set(element, boxes);
      boxes.set(tooltip.options.direction, element.getBoundingClientRect());
      const standOn = (direction) => {
        if (tooltip.options.direction === direction) return;
        tooltip.options.direction = direction;
        tooltip.update();
      };
      labels.push({
        element,
        sides: directions,
        keep: false,
        box: (direction) => {
          if (!boxes.has(direction)) { standOn(direction); boxes.set(direction, element.getBoundingClientRect()); }
          return boxes.get(direction);
        },
        standOn,
      });
    });
    tooltips(this.area, ["right", "left", "top", "bottom"]);
    for (const { layer } of this.waypointLabels?.values() ?? []) tooltips(layer, ["left", "top", "bottom"]);
    const grid = measureGridLabels(container);
    // Deciding: each label takes its first free side; the boxes taken are in the way of the
    // labels after it. `keep`: the shown platform's own name is never hidden; with no side
    // clear of the map's furniture (zoomed far out, every marker on one spot) it takes its
    // first side anyway. A label with no free side is hidden on the last side it tried.
    const overlaps = (box) => placed.some((o) => box.left < o.right && o.left < box.right && box.top < o.bottom && o.top < box.bottom);
    const chosen = labels.map(({ sides, keep, box }) => {
      for (const side of sides) {
        const drawn = box(side);
        if (!drawn.width || !overlaps(drawn)) { placed.push(drawn); return { side, hidden: false }; }
      }
      if (keep && sides.length) { placed.push(box(sides[0])); return { side: sides[0], hidden: false }; }
      return { side: sides[sides.length - 1], hidden: true };
    });
    // Writing: only what changed.
    labels.forEach(({ element, standOn }, index) => {
      const { side, hidden } = chosen[index];
      standOn(side);
      element.classList.toggle("label-hidden", hidden);
    });
    placeGridLabels(container, placed, grid); // the grid's labels give way to everything else
  }

  /** Forget every label box measured: the next declutter tries each side on the page (for
   * tests: what it places then is what the remembered boxes must have placed). */
  forgetLabelBoxes() {
    this.labelOffsets = new WeakMap();
    this.tooltipBoxes = new WeakMap();
    this.labelView = null;
  }

  /** One declutter on the next frame, however many changes came before it. */
  declutterSoon() {
    if (this.declutterPending) return;
    this.declutterPending = true;
    requestAnimationFrame(() => this.declutter());
  }

  /** Every platform in sight, the view changed only when one is not (or close to the edge). */
  followPlatforms() {
    const points = [...this.markers.values()].map((entry) => entry.marker.getLatLng());
    if (!points.length) return;
    const bounds = L.latLngBounds(points);
    if (this.framed && this.map.getBounds().pad(-0.1).contains(bounds)) return;
    // More room on the right: each marker's name is written there.
    if (points.length > 1) this.map.fitBounds(bounds, { paddingTopLeft: [40, 40], paddingBottomRight: [110, 40], maxZoom: 2, animate: false });
    else if (this.framed) this.map.panTo(points[0], { animate: false });
    else this.map.setView(points[0], 2, { animate: false });
    this.framed = true;
  }

  remove(id) {
    const entry = this.markers.get(id);
    if (!entry) return;
    entry.marker.remove();
    entry.track.remove();
    this.markers.delete(id);
  }

  ids() { return [...this.markers.keys()]; }

  setImage(url, south, west, north, east) {
    this.clearBackground();
    const sw = this.local(south, west), ne = this.local(north, east);
    this.background = L.imageOverlay(url, [sw, ne], { opacity: 0.9, className: "area-image", alt: "area image" }).addTo(this.map);
    this.background.bringToBack();
    this.map.fitBounds([sw, ne]);
    this.following = false;
  }

  /** An operator's GeoJSON background (offline: drawn as loaded). ``fit`` zooms to it. */
  setGeoJson(data, { fit = true } = {}) {
    this.clearBackground();
    this.background = this.geoJsonLayer(data, () => "area-background").addTo(this.map);
    this.background.bringToBack();
    const bounds = this.background.getBounds();
    if (fit && bounds.isValid()) { this.map.fitBounds(bounds); this.following = false; }
  }

  /** The platform's area map: its boundary, keep-outs (role "keepout", red) and named points,
   * kept apart from the operator's background (loading or clearing one leaves the other). */
  setArea(data, { fit = true } = {}) {
    this.clearArea();
    this.area = this.geoJsonLayer(data, (role) => `area-map${role ? ` area-${role}` : ""}`).addTo(this.map);
    const bounds = this.area.getBounds();
    if (fit && bounds.isValid()) { this.map.fitBounds(bounds, this.fitPadding()); this.following = false; }
    this.declutterSoon();
  }

  clearArea() {
    if (this.area) { this.area.remove(); this.area = null; }
  }

  geoJsonLayer(data, className) {
    return L.geoJSON(data, {
      coordsToLatLng: (coords) => L.latLng(this.local(coords[1], coords[0])),
      style: (feature) => {
        const role = feature?.properties?.role ?? "";
        const keepout = role === "keepout";
        const seen = keepout && feature?.properties?.source === "lidar"; // lidar:N, temporary
        return { color: seen ? "#ffb347" : keepout ? "#d66a6a" : "#7aa2d6", weight: keepout ? 2 : 1, fillOpacity: keepout ? 0.3 : 0.15, className: `${className(role)}${seen ? " area-lidar" : ""}` };
      },
      onEachFeature: (feature, layer) => {
        if (feature?.properties?.role === "keepout" && feature.id != null) layer.bindTooltip(`keep-out ${feature.id}`);
      },
      pointToLayer: (feature, latlng) => {
        const marker = L.circleMarker(latlng, { radius: 3, color: "#aaa", weight: 1, className: "area-point" });
        const name = feature?.properties?.name;
        if (name) marker.bindTooltip(String(name), { permanent: true, direction: "right", className: "area-point-name" });
        return marker;
      },
    });
  }

  /** Draw ``platformId``'s waypoint route ([lat, lon] points; closed when last = first), each
   * waypoint numbered from 1 as the patrol's status counts them. */
  setRoute(platformId, points) {
    this.setLine(`route:${platformId}`, points, { color: "#d6d67a", weight: 2, dashArray: "6 4", className: "route-line" });
    if (!this.available) return;
    this.waypointLabels ??= new Map(); // platform id → { wanted, layer }
    const wanted = JSON.stringify(points ?? []);
    const known = this.waypointLabels.get(platformId);
    if (known?.wanted === wanted) return;
    known?.layer.remove();
    const stops = points?.length >= 3 && samePlace(points[0], points[points.length - 1]) ? points.slice(0, -1) : points ?? [];
    const layer = L.layerGroup(stops.map(([lat, lon], index) => L.circleMarker(this.local(lat, lon), { radius: 0, opacity: 0, interactive: false })
      .bindTooltip(String(index + 1), { permanent: true, direction: "top", className: "waypoint-label" }))).addTo(this.map);
    this.waypointLabels.set(platformId, { wanted, layer });
    this.declutterSoon();
  }

  /** Draw the path ``platformId``'s planner chose. */
  setPlannedPath(platformId, points) { this.setLine(`path:${platformId}`, points, { color: "#5fd0a0", weight: 3, className: "planned-path" }); }

  setLine(key, points, style) {
    if (!this.available) return;
    this.lines ??= new Map();
    this.drawn ??= new Map(); // key → the points drawn (redrawn only when they change)
    const wanted = JSON.stringify(points ?? []);
    if (this.drawn.get(key) === wanted) return;
    this.drawn.set(key, wanted);
    this.lines.get(key)?.remove();
    if (!points || !points.length) { this.lines.delete(key); return; }
    this.lines.set(key, L.polyline(points.map(([lat, lon]) => this.local(lat, lon)), style).addTo(this.map));
  }

  /** Let the operator edit a route's ``points``; ``onChange(points)`` after every edit.
   * Returns the edit's handle (see editPoints). */
  editWaypoints(points, onChange) {
    return this.editPoints(points, onChange, { label: "waypoint", closeLoop: true, shape: (latlngs) => L.polyline(latlngs, { color: "#f0f080", weight: 2, className: "route-edit" }) });
  }

  /** Let the operator draw a keep-out polygon's corners (a draft: the area map itself is
   * redrawn only from the platform's answer). */
  drawPolygon(onChange) {
    return this.editPoints([], onChange, { label: "corner", shape: (latlngs) => L.polygon(latlngs, { color: "#ff9a5a", weight: 2, dashArray: "4 3", fillOpacity: 0.2, className: "keepout-draft" }) });
  }

  /** Edit ``points`` ([lat, lon]) on the map: click the map to append one, drag one to move it,
   * right-click one to delete it; ``onChange(points)`` after every edit. Returns { stop(),
   * addAtCentre() } — the keyboard's way: arrows pan the focused map, then add at its centre. */
  editPoints(points, onChange, { label, shape, closeLoop = false }) {
    if (!this.available) return { stop: () => {}, addAtCentre: () => {} };
    this.following = false; // the operator works on this view: it must not move under the clicks
    const frame = this;
    const current = points.map((p) => [...p]);
    const layer = L.layerGroup().addTo(this.map);
    const draw = () => {
      layer.clearLayers();
      shape(current.map(([lat, lon]) => frame.local(lat, lon))).addTo(layer);
      current.forEach(([lat, lon], index) => {
        const marker = L.marker(frame.local(lat, lon), { draggable: true, title: `${label} ${index + 1}`, alt: `${label} ${index + 1}` });
        marker.on("dragend", () => { current[index] = frame.geo(marker.getLatLng()); changed(); });
        marker.on("contextmenu", () => { current.splice(index, 1); changed(); });
        marker.addTo(layer);
      });
    };
    const changed = () => { draw(); onChange(current.map((p) => [...p])); };
    // A closed route (last = first) stays closed: a new point goes before the closing one.
    const closed = () => current.length >= 3 && samePlace(current[0], current[current.length - 1]);
    const add = (latlng) => {
      if (!frame.origin) return;
      if (closeLoop && closed()) current.splice(current.length - 1, 0, frame.geo(latlng));
      else current.push(frame.geo(latlng));
      changed();
    };
    const append = (event) => add(event.latlng);
    this.map.on("click", append);
    draw();
    return {
      stop: () => { this.map.off("click", append); layer.remove(); },
      addAtCentre: () => add(this.map.getCenter()),
    };
  }

  /** The next click on the map picks a point: ``onPick([lat, lon])``; returns stop(). */
  pickPoint(onPick) {
    if (!this.available) return () => {};
    const picked = (event) => { if (this.origin) onPick(this.geo(event.latlng)); };
    this.map.on("click", picked);
    return () => this.map.off("click", picked);
  }

  /** A flag at [lat, lon] (``className``: its look), or none (null). One per class. */
  flag(className, point, title) {
    if (!this.available) return;
    this.flags ??= new Map();
    const at = point && this.origin ? this.local(point[0], point[1]) : null;
    const drawn = this.flags.get(className);
    if (drawn && at && drawn.options.title === title) { drawn.setLatLng(at); return; } // each report
    drawn?.remove();
    this.flags.delete(className);
    if (!at) return;
    const icon = L.divIcon({ html: "", className: `map-flag ${className}`, iconSize: [16, 16], iconAnchor: [8, 8] });
    this.flags.set(className, L.marker(at, { icon, title, alt: title, keyboard: false, interactive: false }).addTo(this.map));
  }

  /** [lat, lon] of a map position (local metres). */
  geo(latlng) {
    const [lat0, lon0] = this.origin;
    return [lat0 + latlng.lat / EARTH_M_PER_DEG, lon0 + latlng.lng / (EARTH_M_PER_DEG * Math.cos((lat0 * Math.PI) / 180))];
  }

  /** Where [lat, lon] is drawn, in pixels from the map's top-left corner (for tests). */
  pixel(lat, lon) {
    const point = this.map.latLngToContainerPoint(this.local(lat, lon));
    return { x: point.x, y: point.y };
  }

  clearBackground() {
    if (this.background) { this.background.remove(); this.background = null; }
  }
}

/** ``box`` (a DOMRect's edges) moved by ``dx``, ``dy``. */
function shifted(box, dx, dy) {
  return { left: box.left + dx, right: box.right + dx, top: box.top + dy, bottom: box.bottom + dy, width: box.width, height: box.height };
}

function samePlace(a, b) { return Math.abs(a[0] - b[0]) < 1e-7 && Math.abs(a[1] - b[1]) < 1e-7; }

/** Where a platform's name may be written beside its arrow (console.css .label-*). */
const LABEL_SIDES = ["right", "left", "below", "above"];

function platformIcon(id, heading, current, connected, labelSide = "right") {
  const element = document.createElement("div");
  element.className = `platform-icon${current ? " current" : ""}${connected ? " connected" : ""}${labelSide === "right" ? "" : ` label-${labelSide}`}`;
  const arrow = document.createElement("div");
  arrow.className = "arrow";
  arrow.style.transform = `rotate(${Number(heading) || 0}deg)`;
  const label = document.createElement("span");
  label.textContent = id;
  element.append(arrow, label);
  return L.divIcon({ html: element, className: "", iconSize: [24, 24], iconAnchor: [12, 12] });
}

/** Where along its tile's edge a grid label may sit (fractions of the edge): the middle
 * first, then a quarter either way (map.js declutter moves it off a waypoint's number). */
const GRID_LABEL_SPOTS = [0.5, 0.25, 0.75];

function metricGrid() {
  // Each tile's border is a grid line, labelled in metres from the origin along it: the bottom
  // line's north, the left line's east, halfway along each at first. Not at the corner: the
  // origin is where the first platform was heard, and its name is written there. The labels
  // are elements (not drawn into the tile) so that declutter can keep them off the labels and
  // markers drawn over the map.
  return L.GridLayer.extend({
    createTile(coords) {
      const tile = document.createElement("div");
      tile.className = "grid-tile";
      const size = this.getTileSize();
      const metres = size.x / 2 ** coords.z;
      // Distances, not coordinates: "64 E" read as a longitude.
      const along = (value, ahead, behind) => (value >= 0 ? `${value} m ${ahead}` : `${-value} m ${behind}`);
      const north = document.createElement("span");
      north.className = "grid-label grid-north";
      north.textContent = along(Math.round(-(coords.y + 1) * metres), "north", "south");
      const east = document.createElement("span");
      east.className = "grid-label grid-east";
      east.textContent = along(Math.round(coords.x * metres), "east", "west");
      for (const label of [north, east]) label.dataset.spot = "0.5";
      tile.append(north, east);
      return tile;
    },
  });
}

/** The length of a grid tile's edge a label's spot is a fraction of, in screen pixels: its
 * padding box (the `left`/`top` percentages' base, inside the grid line's border) at the
 * view's scale. Not its border box, 1 px longer: a label moved by it lands up to half a pixel
 * (more when zoomed in) from where its room was measured, over its neighbour's edge. */
function spotEdges(tile) {
  const box = tile.getBoundingClientRect();
  if (!tile.offsetWidth || !tile.offsetHeight) return { across: 0, down: 0 };
  return { across: (tile.clientWidth * box.width) / tile.offsetWidth, down: (tile.clientHeight * box.height) / tile.offsetHeight };
}

/** Every grid label with its box and its tile's edges (reads only). */
export function measureGridLabels(container) {
  return [...container.querySelectorAll(".grid-label")].map((label) => ({ label, box: label.getBoundingClientRect(), edges: spotEdges(label.parentElement) }));
}

/** Grid labels off everything in ``placed`` (boxes; each label's chosen box is added to it):
 * each tries its spots along its line and is hidden when none is free. Reads every box first
 * (``measured``: measureGridLabels, when the caller read them with its own) and writes after
 * (one layout). */
export function placeGridLabels(container, placed, measured = measureGridLabels(container)) {
  const overlaps = (box) => placed.some((o) => box.left < o.right && o.left < box.right && box.top < o.bottom && o.top < box.bottom);
  const chosen = measured.map(({ label, box, edges }) => {
    if (!box.width || !edges.across) return null;
    const north = label.classList.contains("grid-north");
    const from = Number(label.dataset.spot);
    for (const spot of GRID_LABEL_SPOTS) {
      const shift = (spot - from) * (north ? edges.across : edges.down);
      const moved = north
        ? { left: box.left + shift, right: box.right + shift, top: box.top, bottom: box.bottom }
        : { left: box.left, right: box.right, top: box.top + shift, bottom: box.bottom + shift };
      if (!overlaps(moved)) { placed.push(moved); return spot; }
    }
    return null;
  });
  measured.forEach(({ label }, index) => {
    const spot = chosen[index];
    label.classList.toggle("label-hidden", spot === null);
    if (spot === null || String(spot) === label.dataset.spot) return;
    label.dataset.spot = String(spot);
    label.style.setProperty(label.classList.contains("grid-north") ? "left" : "top", `${spot * 100}%`);
  });
}
