// The control interface of the shown platform: command authority (who holds control, take
// control with a confirmation), the override, lights, NavCam framerate, diagnostics, the
// battery monitor, the platform's streams, audio, disconnect, and driving (keyboard, game
// controller). An observer's controls are disabled before any click, saying who holds
// control; only *take control* stays. With no platform shown the controls are hidden.

import { PlatformAudio } from "./audio.js";
import { say } from "./answer.js";
import { $, controlHolder, engagedHere, fixed, holding, observerReason, put, section, setPill, snapshotOf } from "./common.js";
import { api, command, disconnect, onBinary } from "./station.js";
import { notify, state, subscribe } from "./store.js";
import { Teleop } from "./teleop.js";

const OBSERVER_DISABLED = ["#override", "#lights-main", "#lights-pos", "#set-framerate", "#framerate", "#diagnostics", "#battery-monitor", "#talk"];

export const teleop = new Teleop({
  send: (linear, angular) => api.call("console_drive", { platform_id: state.current, linear, angular }, 1000),
  onOverrideButton: () => $("#override").click(),
  onLightsButton: () => $("#lights-main").click(),
  onIgnored: () => say(whyNotDriving()),
});

export const audio = new PlatformAudio(api, {
  onStats: (stats) => {
    $("#listen").dataset.decoded = String(stats.decoded);
    $("#audio-latency").textContent = stats.latencyMs == null ? "" : `audio ${stats.latencyMs.toFixed(0)} ms`;
  },
});

/** Why a drive key moves nothing, in a sentence. */
function whyNotDriving() {
  if (!state.current) return "Nothing moves: no platform is shown. Choose one on the map or in the list.";
  const holder = controlHolder();
  if (holder != null && holder !== state.stationId) return `Nothing moves: station ${holder} holds control of ${state.current}. Take control first.`;
  if (holding()) return `Nothing moves: ${state.current} holds after a link loss. Press the override to re-engage.`;
  return `Nothing moves: engage the override to drive ${state.current}.`;
}

/** The driving hint under the instruments: what to do, never a disabled button's name. */
export function drivingHint() {
  if (engagedHere()) return "Driving: hold W/A/S/D or the arrows, space stops; game controller: hold LB and use the left stick.";
  const holder = controlHolder();
  if (holder != null && holder !== state.stationId) return `Watching: ${holder} holds control of ${state.current}. Take control to drive.`;
  return "Not driving: engage the override to drive (a drive key says why nothing moves).";
}

async function toggleOverride() {
  if (!state.current || state.override === "pending") return;
  // During the platform's hold, pressing the switch re-engages (the deliberate act it waits for).
  const engage = !engagedHere() || holding();
  state.override = "pending";
  render();
  const result = await command("manual override", "console_override", { engaged: engage }, 6000);
  if (result && result.accepted) state.override = engage ? "engaged" : "idle";
  else { state.override = "error"; state.overrideError = result ? result.reason : "no answer"; }
  render();
}

async function takeControl() {
  $("#takeover-confirm").hidden = true;
  if (!state.current || state.override === "pending") return;
  state.override = "pending";
  render();
  // movrd --force: the platform moves control to this station and engages its override.
  const result = await command("take control", "console_override", { engaged: true, force: true }, 6000);
  if (result && result.accepted) { state.override = "engaged"; state.taken.delete(state.current); }
  else { state.override = "error"; state.overrideError = result ? result.reason : "no answer"; }
  render();
}

async function talk(on) {
  const button = $("#talk");
  if (on === (button.getAttribute("aria-pressed") === "true")) return;
  if (on && button.disabled) return;
  button.setAttribute("aria-pressed", String(on));
  try {
    if (on) await audio.startTalking(state.current);
    else await audio.stopTalking(state.current);
  } catch (error) {
    button.setAttribute("aria-pressed", "false");
    say(`Push-to-talk failed: ${error.message}.`, { refused: true });
    await audio.stopTalking(state.current);
  }
}

function renderAuthority(drives) {
  const holder = controlHolder();
  const box = $("#authority");
  const taken = state.taken.get(state.current);
  // The telemetry can still name this station for a moment after the 90.17 note came.
  if (taken && (drives || (holder === state.stationId && performance.now() - taken.at > 3000))) state.taken.delete(state.current);
  const other = holder != null && holder !== state.stationId;
  const [kind, text] = drives ? ["driving", "this console is driving"]
    : holder === state.stationId ? ["station", "this station holds control (not driven from this console)"]
    : other && state.taken.has(state.current) ? ["taken", `CONTROL TAKEN by station ${holder}: observing`]
    : other ? ["observing", `observing — control held by station ${holder}`]
    : ["free", "control free: engage the override to drive"];
  box.dataset.state = kind;
  box.dataset.holder = holder ?? "";
  put($("#control-state"), text);
  $("#takeover").hidden = !other || !$("#takeover-confirm").hidden;
  put($("#takeover-holder"), `station ${holder}`);
  if (!other) $("#takeover-confirm").hidden = true;
}

function renderFailsafe() {
  // The platform's failsafe ladder (hold, released) and this page's own view of the link.
  const entry = state.current ? state.telemetry.get(state.current) : null;
  const connection = state.current ? state.connections.get(state.current) : null;
  const banner = $("#failsafe");
  const failsafe = section(entry?.report.snapshot, "failsafe");
  const age = entry ? (entry.report.link?.silence_s ?? 0) * 1000 + performance.now() - entry.at : 0;
  const stale = entry && age > 2000;
  let step = "normal";
  let text = "";
  if (connection && connection.connected === false) {
    [step, text] = ["lost", `LINK LOST: ${connection.close_reason || "connection to the platform closed"}`];
  } else if (failsafe && failsafe.step !== "normal") {
    // This station's link is back (fresh telemetry, connected) while the platform still holds
    // for it: driving resumes only when the operator re-engages, deliberately.
    const back = !stale && connection && connection.connected !== false && failsafe.controller === state.stationId;
    step = back && failsafe.step === "hold" ? "rejoin" : failsafe.step;
    text = failsafe.step === "hold"
      ? `LINK LOST — platform on HOLD (${failsafe.reason})${back ? ". Link back: re-engage the override to drive" : ""}`
      : `LINK LOST — override released, autonomy resumed (${failsafe.reason})`;
  } else if (stale && state.override === "engaged") {
    [step, text] = ["lost", "LINK LOST: no telemetry from the platform"];
  }
  banner.dataset.step = step;
  put(banner, text);
  banner.hidden = !text;
}

function renderTurret(snapshot) {
  const turret = section(snapshot, "turret");
  const readout = $("#turret");
  readout.hidden = !turret;
  if (!turret) return;
  readout.dataset.trigger = turret.trigger ? "armed" : "safe";
  readout.dataset.line = turret.connected ? "up" : "down";
  // As brasidas-station status words it: why the serial line is down, else where it points;
  // then its sight (the thermal camera registered as its stream) and that stream's state.
  const streams = Object.entries(turret.streams).map(([name, stream]) => `${name} ${stream}`);
  put(readout, [
    "turret:",
    ...(turret.connected
      ? [turret.trigger ? "trigger ARMED" : "trigger safe", `azimuth ${fixed(turret.azimuth, 1)}°`, `elevation ${fixed(turret.elevation, 1)}°`]
      : [turret.error ? `LINE DOWN: ${turret.error}` : "LINE DOWN"]),
    streams.length ? `sight ${streams.join("  ")}` : null,
  ].filter(Boolean).join("  "));
}

function renderLights(lights) {
  // A light that cannot be switched (its GPIO chip missing, its line busy) says so and why, next
  // to its button; pressing it asks again (the platform retries the line at each switch).
  const errors = lights ? Object.entries(lights.errors) : [];
  for (const [selector, which] of [["#lights-main", "main"], ["#lights-pos", "positional"]]) {
    const error = lights ? lights.errors[which] : undefined;
    $(selector).dataset.error = error ? "true" : "";
  }
  const readout = $("#lights-error");
  put(readout, errors.length
    ? `lights cannot be switched: ${errors.sort().map(([which, error]) => `${which}: ${error}`).join("; ")}`
    : "");
  readout.hidden = !errors.length;
}

function renderStreams(snapshot, why) {
  const streams = Object.entries(section(snapshot, "streams")?.states ?? {});
  const body = $("#streams tbody");
  const wanted = streams.map(([name, stream]) => `${name}:${stream}`).join(",") + `|${why}`;
  if (body.dataset.shown === wanted) return;
  body.dataset.shown = wanted;
  body.replaceChildren(...streams.map(([name, stream]) => {
    const row = document.createElement("tr");
    row.dataset.stream = name;
    const label = document.createElement("td");
    label.textContent = `${name}: ${stream}`;
    row.append(label);
    for (const action of ["start", "pause", "stop"]) {
      const cell = document.createElement("td");
      const button = document.createElement("button");
      button.type = "button";
      button.textContent = action;
      button.setAttribute("aria-label", `${action} ${name}`);
      // An observer starts and stops its own copy of a stream (OBSERVER_CODES); pausing is
      // the platform's stream for everyone: a control command.
      const forEveryone = action === "pause" ? why : "";
      button.disabled = Boolean(forEveryone);
      button.title = forEveryone || (why ? `${action} this console's own copy of ${name}` : "");
      button.onclick = () => command(`${action} ${name}`, "console_stream", { name, action });
      cell.append(button);
      row.append(cell);
    }
    return row;
  }));
}

function render() {
  const connection = state.current ? state.connections.get(state.current) : null;
  $("#controls").hidden = !connection;
  const drives = engagedHere();
  renderFailsafe();
  renderAuthority(drives);
  if (state.override !== "pending" && state.override !== "error") state.override = drives ? "engaged" : "idle";
  const button = $("#override");
  button.setAttribute("aria-pressed", String(drives));
  button.dataset.state = state.override;
  const snapshot = snapshotOf();
  const holder = section(snapshot, "override");
  put(button, {
    idle: holder?.engaged ? `override: held by ${holder.station ?? "another station"}` : "override: autonomous",
    pending: "override: pending…",
    engaged: holding() ? "override: HOLD — press to re-engage" : "override: ENGAGED",
    error: `override: error (${state.overrideError ?? "no answer"})`,
  }[state.override]);
  teleop.setActive(drives);
  setPill("#driving", drives ? `this console is driving ${state.current}` : "not driving", drives ? "teleop" : "");
  const why = observerReason();
  for (const selector of OBSERVER_DISABLED) {
    const control = $(selector);
    if (control.disabled !== Boolean(why)) control.disabled = Boolean(why);
    if (control.title !== why) control.title = why;
  }
  const lights = section(snapshot, "lights");
  if (lights) {
    $("#lights-main").setAttribute("aria-pressed", String(Boolean(lights.main)));
    $("#lights-pos").setAttribute("aria-pressed", String(Boolean(lights.positional)));
  }
  renderLights(lights);
  renderTurret(snapshot);
  if (snapshot) {
    $("#diagnostics").setAttribute("aria-pressed", String(section(snapshot, "diagnostics") != null));
    const battery = section(snapshot, "battery");
    if (battery) $("#battery-monitor").setAttribute("aria-pressed", String(Boolean(battery.monitor)));
  }
  renderStreams(snapshot, why);
  notify("authority");
}

export function startControls() {
  onBinary(2, (buffer) => audio.onPacket(buffer));
  $("#override").onclick = toggleOverride;
  for (const [selector, which] of [["#lights-main", "main"], ["#lights-pos", "pos"]]) {
    $(selector).onclick = async (event) => {
      const on = event.currentTarget.getAttribute("aria-pressed") !== "true";
      const result = await command(`${which === "pos" ? "positional" : "main"} lights`, "lights", { which, on });
      if (result && result.accepted !== false) $(selector).setAttribute("aria-pressed", String(on));
    };
  }
  $("#set-framerate").onclick = () => command("NavCam framerate", "command", { group: 10, command: 5, payload: `navcam=${$("#framerate").value}` });
  for (const [selector, label, code] of [["#diagnostics", "diagnostics", 0], ["#battery-monitor", "battery monitor", 4]]) {
    $(selector).onclick = async (event) => {
      const on = event.currentTarget.getAttribute("aria-pressed") !== "true";
      const result = await command(label, "command", { group: 20, command: code, payload: on ? "ON" : "OFF" });
      if (result && result.accepted !== false) $(selector).setAttribute("aria-pressed", String(on));
    };
  }
  $("#disconnect").onclick = async () => { teleop.halt("disconnect"); await disconnect(); };
  $("#takeover").onclick = () => {
    $("#takeover").hidden = true;
    $("#takeover-confirm").hidden = false;
    $("#takeover-yes").focus();
  };
  $("#takeover-no").onclick = () => { $("#takeover-confirm").hidden = true; render(); };
  $("#takeover-yes").onclick = takeControl;
  $("#listen").onclick = async (event) => {
    const listen = event.currentTarget;
    if (listen.getAttribute("aria-pressed") === "true") {
      listen.setAttribute("aria-pressed", "false");
      await audio.stopListening();
      return;
    }
    try {
      await audio.listen(state.current);
      listen.setAttribute("aria-pressed", "true");
    } catch (error) { say(`Listening failed: ${error.message}.`, { refused: true }); }
  };
  const talkButton = $("#talk");
  talkButton.addEventListener("pointerdown", () => talk(true));
  for (const name of ["pointerup", "pointerleave", "pointercancel"]) talkButton.addEventListener(name, () => talk(false));
  talkButton.addEventListener("keydown", (event) => { if (event.key === "Enter" || event.key === " ") { event.preventDefault(); talk(true); } });
  talkButton.addEventListener("keyup", (event) => { if (event.key === "Enter" || event.key === " ") talk(false); });
  window.addEventListener("blur", () => talk(false));

  subscribe("current", async () => {
    teleop.halt("switched platform");
    await talk(false);
    if (audio.listening) { $("#listen").setAttribute("aria-pressed", "false"); await audio.stopListening(); }
    setPill("#current", state.current ?? "no platform", state.current ? "ok" : "");
    render();
  });
  subscribe("shown", async () => {
    if (audio.listening) await audio.listen(audio.listening).catch(() => {});
  });
  subscribe("clock", () => { audio.clockOffsetMs = state.clockOffsetMs; });
  subscribe("connections", render);
  subscribe("telemetry", (platformId) => { if (platformId === state.current) render(); });
  subscribe("notification", (note) => {
    if (note.name === "control_taken" && note.active && !note.replayed) {
      state.taken.set(note.platform_id, { note, at: performance.now() }); // said at once, until this station holds it again
      if (note.platform_id === state.current) { teleop.halt("control taken"); render(); }
    }
  });
  setInterval(renderFailsafe, 500);
  render();
  return { audio: () => ({ ...audio.stats }) };
}
