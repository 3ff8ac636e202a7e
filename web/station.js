// The station connection: one WebSocket to the station daemon's local API (JSON-RPC 2.0);
// pushes update the store, binary messages go to whoever registered for their type, and the
// platform shown is chosen here (select / disconnect).

import { StationApi } from "./api.js";
import { say, sentence } from "./answer.js";
import { setPill } from "./common.js";
import { notify, state } from "./store.js";

const binary = new Map(); // message type → handler(buffer)

/** Receive the binary messages of ``type`` (1 video, 2 platform audio). */
export function onBinary(type, handler) { binary.set(type, handler); }

export const apiStates = [];
export const apiUrl = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/api/rpc/ws`;
export const api = new StationApi(apiUrl, {
  onState: (text) => {
    apiStates.push(text);
    setPill("#api-state", text === "connected" ? "station connected" : `station ${text}…`, text === "connected" ? "ok" : "bad");
  },
  onBinary: (buffer) => binary.get(new Uint8Array(buffer, 0, 1)[0])?.(buffer),
  onOpen: () => { hello().catch((error) => console.warn("subscribe failed", error)); },
});

const requestedPlatform = new URLSearchParams(location.search).get("platform"); // ?platform=ID

async function hello() {
  performance.mark("station-open");
  const answer = await api.call("console_subscribe");
  state.session = answer.session;
  state.mediaToken = answer.media_token; // the video worker's own socket proves it (video.js)
  state.stationId = answer.station_id;
  notify("session");
  // The picture first: the clock offset (ten round trips) is measured once it is asked for.
  const clock = () => measureClock().catch((error) => console.warn("clock offset not measured", error));
  if (state.current) {
    await api.call("connect", { platform_id: state.current }, 8000).catch(() => {});
    notify("shown", state.current);
    await api.call("console_focus", { platform_id: state.current }).catch(() => {});
  } else if (requestedPlatform) {
    await select(requestedPlatform);
  }
  clock();
}

async function measureClock() {
  // Station clock − page clock, from the fastest of ten round trips (its midpoint). An offset
  // within that round trip's half is measurement noise (one host: one clock), taken as 0.
  let best = null;
  for (let i = 0; i < 10; i++) {
    const sent = performance.timeOrigin + performance.now();
    const station = await api.call("station_time", {}, 2000);
    const back = performance.timeOrigin + performance.now();
    if (!best || back - sent < best.rtt) best = { rtt: back - sent, offset: station - (sent + back) / 2 };
  }
  state.clockOffsetMs = Math.abs(best.offset) <= best.rtt / 2 ? 0 : best.offset;
  notify("clock");
}

api.on("platforms", (platforms) => { state.platforms = platforms; notify("platforms"); });
api.on("connections", (connections) => {
  state.connections = new Map(connections.map((c) => [c.platform_id, c]));
  if (state.current && !state.connections.has(state.current) && state.override !== "pending") state.override = "idle";
  notify("connections");
});
api.on("telemetry", (report) => {
  state.telemetry.set(report.platform_id, { report, at: performance.now() });
  notify("telemetry", report.platform_id);
});
api.on("notification", (note) => notify("notification", note));
api.on("video", (video) => { state.videoState = video; notify("video-state"); });

/** Show, control and drive ``platformId``; connects first. Others stay connected. */
export async function select(platformId) {
  if (platformId === state.current) return;
  const previous = state.current;
  state.current = platformId;
  state.override = "idle";
  state.videoState = null;
  notify("current", previous);
  try {
    await api.call("connect", { platform_id: platformId }, 8000);
  } catch (error) {
    say(`Connecting to ${platformId} failed: ${error.message}.`, { refused: true });
    return;
  }
  if (state.current !== platformId) return;
  notify("shown", platformId); // the NavCam asked for at once (video_watch focuses it too)
  await api.call("console_focus", { platform_id: platformId }).catch(() => {});
}

/** Disconnect the shown platform (it returns to autonomous mode); nothing is shown after. */
export async function disconnect() {
  const platformId = state.current;
  if (!platformId) return;
  await command("disconnect", "disconnect", {});
  state.current = null;
  state.override = "idle";
  state.videoState = null;
  notify("current", platformId);
}

/** Send ``method`` for the shown platform; the answer line says how it went. */
export async function command(label, method, params, timeoutMs = 5000) {
  if (!state.current) return null;
  try {
    const result = await api.call(method, { platform_id: state.current, ...params }, timeoutMs);
    say(sentence(label, result), { refused: result?.accepted === false });
    return result;
  } catch (error) {
    say(`${label}: ${error.message}.`, { refused: true });
    return null;
  }
}
