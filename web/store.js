// The console's one state and its change notices. Modules read ``state`` and change it only
// through the functions that own each part; after a change they ``notify(topic)`` and every
// view subscribed to that topic redraws itself. No view calls another view's render.
//
// Topics: "platforms" (beacons heard), "connections" (sessions, override, who drives),
// "telemetry" (a report arrived; detail: platform id), "current" (the platform shown
// changed), "shown" (the station connected it and the page may watch it), "video" (decoder
// figures), "video-state" (the station's word on the feed), "notification" (a warning raised
// or cleared), "session" (the station connection opened), "area-changed" (a map or route
// file was imported: detail: platform id).

export const state = {
  current: null,          // the platform shown, controlled and driven
  platforms: [],          // beacons heard (pushed)
  connections: new Map(), // platform id → connection summary (pushed)
  telemetry: new Map(),   // platform id → { report, at }: at = page time it arrived
  session: null,
  stationId: null,        // this station's id (console_subscribe)
  taken: new Map(),       // platform id → the 90.17 note: control taken from this station
  clockOffsetMs: 0,       // station clock − page clock
  override: "idle",       // idle | pending | engaged | error
  overrideError: null,
  video: null,            // the decoder's latest figures (video.js)
  videoState: null,       // the station's last word on the watched feed
};

const listeners = new Map(); // topic → Set of functions

/** Call ``listener(detail)`` after each ``notify(topic)``; returns the way to stop. */
export function subscribe(topic, listener) {
  if (!listeners.has(topic)) listeners.set(topic, new Set());
  listeners.get(topic).add(listener);
  return () => listeners.get(topic)?.delete(listener);
}

/** Tell every subscriber of ``topic``; one failing view never stops the others. */
export function notify(topic, detail) {
  for (const listener of [...(listeners.get(topic) ?? [])]) {
    try { listener(detail); } catch (error) { console.error(`${topic} subscriber failed`, error); }
  }
}
