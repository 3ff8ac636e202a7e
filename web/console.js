// Brasidas browser console: the wiring. Each view is a module that subscribes to the store
// (store.js) and draws its part of the page; this file starts them in order. A new view is
// one import and one start call here (and its markup in index.html).

import { startControls } from "./controls.js";
import { startGoTo } from "./goto.js";
import { startHome } from "./home.js";
import { startTiles } from "./tiles.js";
import { startInstruments } from "./instruments.js";
import { startLayout } from "./layout.js";
import { startMapFiles } from "./mapfiles.js";
import { startNotifications } from "./notifications.js";
import { startPatrol } from "./patrol.js";
import { startPerception } from "./perception.js";
import { plotPoints, startPlots } from "./plots.js";
import { startRecordings } from "./recordings.js";
import { startSafety } from "./safety.js";
import { startToolbar } from "./toolbar.js";
import { startValues } from "./values.js";
import { apiStates, api } from "./station.js";
import { startVideo } from "./video.js";
import { startVideoLink } from "./video-link.js";

const video = startVideo();
const controls = startControls();
const patrol = startPatrol();
startInstruments();
startNotifications();
startPlots();
startLayout();
startMapFiles();
startRecordings();
startSafety();
startVideoLink();
startToolbar();
startGoTo();
startHome();
startTiles();
startValues();
startPerception();

// What tests and benchmarks read (the page's CSP allows no eval of their own).
window.navcam = {
  ...video,
  ...controls,
  marks: () => Object.fromEntries(performance.getEntriesByType("mark").map((m) => [m.name, m.startTime])),
  apiStates,
  /** Drop the station connection (it reconnects by itself): for trying the reconnection. */
  dropStationConnection: () => api.ws?.close(),
  /** Where [lat, lon] is on the map, in pixels from its top-left corner: for clicking it. */
  mapPixel: patrol.mapPixel,
  /** How many times the map has placed its labels (at most once a frame, after a change). */
  declutterRuns: () => patrol.map.declutterRuns,
  plotPoints,
};
