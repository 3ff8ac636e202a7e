// Safety on the console (issue 27): a STOP every operator has (an observer's too: stopping
// never needs control), and a platform that went silent shown as such: within 3 s of its
// last telemetry the instruments grey out with the age and a notification says so; when it
// comes back, the NavCam is asked for again by itself (a restarted platform lost the stream);
// releasing the override while the patrol waits behind it asks first (the robot drives off).

import { $, engagedHere, holding, put, section, snapshotOf, telemetryAgeMs } from "./common.js";
import { say } from "./answer.js";
import { api } from "./station.js";
import { notify, state, subscribe } from "./store.js";

const SILENT_MS = 2500; // "within 3 s": telemetry comes five times a second
const CHECK_MS = 250;
const silent = new Set(); // platform ids said silent

async function stop() {
  const platformId = state.current;
  if (!platformId) return;
  try {
    const answer = await api.call("stop", { platform_id: platformId }, 5000);
    say(`STOP: ${platformId} stopped, disarmed (${answer.last_stop}).`);
  } catch (error) {
    say(`STOP failed: ${error.message}.`, { refused: true });
  }
}

function note(platformId, active, message) {
  notify("notification", { platform_id: platformId, name: "platform_silent", active, message, time: Date.now() / 1000 });
}

function checkSilence() {
  const platformId = state.current;
  const panel = $("#instruments");
  const ageLine = $("#instruments-age");
  $("#stop").hidden = !platformId;
  if (!platformId) { panel.classList.remove("silent"); ageLine.hidden = true; return; }
  const entry = state.telemetry.get(platformId);
  const age = telemetryAgeMs(entry);
  const quiet = entry != null && age > SILENT_MS;
  panel.classList.toggle("silent", quiet);
  ageLine.hidden = !quiet;
  if (quiet) put(ageLine, `platform silent ${(age / 1000).toFixed(1)} s: the last values shown`);
  if (quiet && !silent.has(platformId)) {
    silent.add(platformId);
    note(platformId, true, `platform silent: no telemetry for ${(age / 1000).toFixed(1)} s`);
  } else if (!quiet && silent.has(platformId) && entry != null) {
    silent.delete(platformId);
    note(platformId, false, "platform silent");
    // It is back (perhaps restarted): ask for its picture again, as the operator's click would.
    const again = $("#video-resume");
    if (!again.closest("[hidden]")) again.click();
  }
}

let releaseConfirmed = false;
const patrolSpeeds = new Map(); // platform id → its patrol speed, km/h (the connect answer's limits)

async function patrolSpeed(platformId) {
  if (!patrolSpeeds.has(platformId)) {
    const list = await api.call("connections", {}, 2000).catch(() => []);
    const kmh = list.find((c) => c.platform_id === platformId)?.parameters?.limits?.patrol_speed_kmh;
    if (typeof kmh === "number") patrolSpeeds.set(platformId, kmh);
  }
  return patrolSpeeds.get(platformId);
}

function releaseText(autonomy, kmh) {
  const away = typeof autonomy.distance_m === "number" ? `, ${Math.round(autonomy.distance_m)} m away,` : "";
  const toward = autonomy.waypoint != null ? `waypoint ${autonomy.waypoint + 1} of ${autonomy.waypoints}${away}` : "its route";
  const speed = typeof kmh === "number" ? `at ${kmh.toFixed(kmh % 1 ? 1 : 0)} km/h` : "at its cruise speed";
  return `Release the override? The patrol resumes toward ${toward} at once, ${speed}.`;
}

function guardRelease(event) {
  // Runs before controls.js's handler (a capture listener on the button itself).
  if (releaseConfirmed) { releaseConfirmed = false; return; }
  if (!engagedHere() || holding()) return; // engaging, or re-engaging after a hold: no question
  const autonomy = section(snapshotOf(), "autonomy");
  if (autonomy?.state !== "suspended") return;
  event.stopImmediatePropagation();
  event.preventDefault();
  const platformId = state.current;
  put($("#release-text"), releaseText(autonomy, patrolSpeeds.get(platformId)));
  $("#release-confirm").hidden = false;
  patrolSpeed(platformId).then((kmh) => {
    if (state.current === platformId && !$("#release-confirm").hidden) put($("#release-text"), releaseText(autonomy, kmh));
  });
}

function answerRelease(release) {
  $("#release-confirm").hidden = true;
  if (!release) return;
  releaseConfirmed = true;
  $("#override").click();
}

/** Start the STOP button, the silent-platform marking and the release confirmation. */
export function startSafety() {
  $("#stop").onclick = stop;
  $("#override").addEventListener("click", guardRelease, { capture: true });
  $("#release-yes").onclick = () => answerRelease(true);
  $("#release-no").onclick = () => answerRelease(false);
  subscribe("current", checkSilence);
  setInterval(checkSilence, CHECK_MS);
}
