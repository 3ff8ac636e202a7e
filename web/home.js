// Home (a QGroundControl user's "H"): the platform's home from its telemetry (the route's
// home, else its first fix) drawn on the map, and the distance and bearing from the platform
// to it in the toolbar ("⌂ 42 m 215°"). "⌂ —" while the platform has no home or no position.

import { $, element, section, snapshotOf } from "./common.js";
import { map } from "./patrol.js";
import { state, subscribe } from "./store.js";

const EARTH_RADIUS_M = 6_371_000;
const pill = element("span", { id: "tb-home", class: "pill", "aria-label": "home", title: "distance and bearing from the platform to its home" }, "⌂ —");

/** Metres and bearing (degrees from north, clockwise) from ``from`` to ``to`` ([lat, lon]). */
export function distanceAndBearing(from, to) {
  const rad = Math.PI / 180;
  const [lat1, lat2] = [from[0] * rad, to[0] * rad];
  const dLat = lat2 - lat1;
  const dLon = (to[1] - from[1]) * rad;
  const a = Math.sin(dLat / 2) ** 2 + Math.cos(lat1) * Math.cos(lat2) * Math.sin(dLon / 2) ** 2;
  const metres = 2 * EARTH_RADIUS_M * Math.asin(Math.min(1, Math.sqrt(a)));
  const y = Math.sin(dLon) * Math.cos(lat2);
  const x = Math.cos(lat1) * Math.sin(lat2) - Math.sin(lat1) * Math.cos(lat2) * Math.cos(dLon);
  return { metres, bearing: ((Math.atan2(y, x) / rad) + 360) % 360 };
}

function words(metres) {
  return metres < 1000 ? `${Math.round(metres)} m` : `${(metres / 1000).toFixed(2)} km`;
}

function render() {
  const snapshot = snapshotOf();
  const home = section(snapshot, "autonomy")?.home;
  const pose = section(snapshot, "pose");
  const gps = section(snapshot, "gps");
  const here = pose?.lat != null ? [pose.lat, pose.lon] : gps?.fix && gps.lat != null ? [gps.lat, gps.lon] : null;
  const known = Array.isArray(home) && home.length === 2;
  map.flag("home", known ? home : null, "home");
  if (!known || !here) {
    pill.textContent = "⌂ —";
    pill.dataset.metres = "";
    return;
  }
  const { metres, bearing } = distanceAndBearing(here, home);
  pill.textContent = `⌂ ${words(metres)} ${Math.round(bearing) % 360}°`;
  pill.dataset.metres = metres.toFixed(1);
}

export function startHome() {
  $("#tb-gps").after(pill);
  subscribe("telemetry", (platformId) => { if (platformId === state.current) render(); });
  subscribe("current", render);
  render();
}
