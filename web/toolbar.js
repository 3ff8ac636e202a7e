// The toolbar a QGroundControl user looks for: the platform's mode (MANUAL / AUTO / HOLD,
// chosen here by the station holding control), its arm state with a slider to arm or disarm,
// a READY / NOT READY indicator that opens the pre-arm reasons, and link, battery, GPS and a
// message counter at a glance. Arm state and readiness come from the platform's ``arming``
// telemetry section; a platform without one shows "—" (unknown), never a guess.

import { $, element, engagedHere, fixed, observerReason, put, section, snapshotOf, telemetryAgeMs } from "./common.js";
import { slideToConfirm } from "./confirm.js";
import { command } from "./station.js";
import { state, subscribe } from "./store.js";

const MODES = ["MANUAL", "AUTO", "HOLD"];

const mode = element("select", { id: "mode", "aria-label": "mode" }, ...MODES.map((name) => element("option", { value: name }, name)));
const armed = element("span", { id: "armed", class: "pill", role: "status", "aria-label": "arm state" }, "arm —");
const ready = element("button", { id: "ready", type: "button", class: "pill", "aria-expanded": "false", "aria-controls": "prearm", "aria-label": "readiness" }, "ready —");
const prearm = element("div", { id: "prearm", class: "prearm", role: "dialog", "aria-label": "pre-arm checks", hidden: "" });
const link = element("span", { id: "tb-link", class: "pill", "aria-label": "link" }, "link —");
const battery = element("span", { id: "tb-battery", class: "pill", "aria-label": "battery state" }, "batt —");
const gps = element("span", { id: "tb-gps", class: "pill", "aria-label": "gps state" }, "GPS —");
const messages = element("button", { id: "messages", type: "button", class: "pill", "aria-label": "messages" }, "✉ 0");
const toolbar = element("span", { id: "toolbar", class: "toolbar", role: "group", "aria-label": "vehicle" }, mode, armed, ready, link, battery, gps, messages, prearm);

let confirmPending = null; // the mode waiting for its slide (AUTO)
const armSlider = slideToConfirm("arm-slide", "slide to arm", () => armOrDisarm());
const autoSlider = slideToConfirm("auto-slide", "slide to start patrol", () => { confirmPending = null; startAuto(); });
armSlider.box.hidden = true;
autoSlider.box.hidden = true;
toolbar.insertBefore(armSlider.box, ready);
toolbar.insertBefore(autoSlider.box, armed);
let messageCount = 0;

/** The mode the platform is in: the override engaged is MANUAL, a patrol driving is AUTO,
 * anything else (stopped, holding, suspended) is HOLD. */
function currentMode(snapshot) {
  if (section(snapshot, "override")?.engaged) return "MANUAL";
  const autonomy = section(snapshot, "autonomy");
  return autonomy?.state === "patrolling" ? "AUTO" : "HOLD";
}

async function startAuto() {
  if (engagedHere()) await command("release the override", "console_override", { engaged: false }, 6000);
  await command("start patrol", "patrol_start", {}, 6000);
  render();
}

async function chooseMode() {
  const wanted = mode.value;
  confirmPending = null;
  if (wanted === "MANUAL") await command("manual override", "console_override", { engaged: true }, 6000);
  else if (wanted === "AUTO") confirmPending = "AUTO"; // moves the robot: slide to confirm
  else {
    await command("hold (stop patrol)", "patrol_stop", {}, 6000);
    if (engagedHere()) await command("release the override", "console_override", { engaged: false }, 6000);
  }
  render();
}

async function armOrDisarm() {
  const arming = section(snapshotOf(), "arming");
  if (arming?.armed) await command("disarm", "disarm", { force: false }, 6000);
  else await command("arm", "arm", {}, 6000);
  render();
}

function renderArming(snapshot, why) {
  const arming = section(snapshot, "arming");
  armSlider.box.hidden = !arming;
  if (!arming) {
    put(armed, "arm —"); armed.className = "pill"; armed.title = "the platform reports no arming state";
    put(ready, "ready —"); ready.className = "pill"; ready.title = "the platform reports no pre-arm checks";
    prearm.replaceChildren(element("p", {}, "No pre-arm checks reported by this platform."));
    return;
  }
  const countdown = typeof arming.countdown_s === "number" ? ` ${arming.countdown_s.toFixed(0)} s` : "";
  put(armed, arming.armed ? `ARMED${countdown}` : "DISARMED");
  armed.className = `pill ${arming.armed ? "armed" : ""}`;
  armed.title = arming.last_stop ? `last stop: ${arming.last_stop}` : "";
  put(ready, arming.ready ? "READY" : "NOT READY");
  ready.className = `pill ${arming.ready ? "ok" : "bad"}`;
  ready.title = "pre-arm checks: click for the reasons";
  const reasons = arming.prearm ?? [];
  const wanted = JSON.stringify([reasons, arming.last_stop]);
  if (prearm.dataset.shown !== wanted) {
    prearm.dataset.shown = wanted;
    prearm.replaceChildren(
      element("strong", {}, reasons.length ? "Not ready to arm:" : "All pre-arm checks pass."),
      element("ul", {}, ...reasons.map((reason) => element("li", {}, reason))),
      arming.last_stop ? element("p", { class: "muted" }, `last stop: ${arming.last_stop}`) : "",
    );
  }
  armSlider.say(arming.armed ? "slide to disarm" : "slide to arm");
  armSlider.enable(why || (!arming.armed && !arming.ready ? "not ready: open the pre-arm reasons" : ""));
}

function renderGlance(snapshot) {
  const entry = state.telemetry.get(state.current);
  const age = telemetryAgeMs(entry);
  const loss = entry?.report.link?.loss_pct;
  const silent = age != null && age > 3000;
  put(link, silent ? `link LOST ${(age / 1000).toFixed(0)} s` : `link ${loss == null ? "—" : `${loss} % loss`}`);
  link.className = `pill ${silent ? "bad" : loss == null ? "" : "ok"}`;
  const volts = section(snapshot, "battery")?.volts;
  put(battery, `batt ${fixed(volts, 1)} V`);
  const fix = section(snapshot, "gps");
  put(gps, fix ? `GPS ${fix.fix ? "fix" : "no fix"} ${fix.sats ?? "—"} sats` : "GPS —");
  gps.className = `pill ${fix ? (fix.fix ? "ok" : "bad") : ""}`;
}

function render() {
  toolbar.hidden = !state.current;
  if (!state.current) return;
  const snapshot = snapshotOf();
  const why = observerReason();
  const now = currentMode(snapshot);
  if (document.activeElement !== mode && confirmPending === null && mode.value !== now) mode.value = now;
  mode.dataset.mode = now;
  mode.disabled = Boolean(why);
  mode.title = why || "the platform's mode: choose to change it";
  autoSlider.box.hidden = confirmPending !== "AUTO";
  autoSlider.enable(why);
  renderArming(snapshot, why);
  renderGlance(snapshot);
}

/** The toolbar in the header, after the platform's name. */
export function startToolbar() {
  $("#current").after(toolbar);
  mode.onchange = chooseMode;
  mode.addEventListener("blur", () => render());
  ready.onclick = () => {
    const open = prearm.hidden;
    prearm.hidden = !open;
    ready.setAttribute("aria-expanded", String(open));
  };
  messages.onclick = () => $("#notifications").scrollIntoView({ block: "nearest" });
  subscribe("notification", (note) => {
    if (note.replayed) return;
    messageCount += 1;
    put(messages, `✉ ${messageCount}`);
  });
  subscribe("telemetry", (platformId) => { if (platformId === state.current) render(); });
  subscribe("connections", render);
  subscribe("current", () => { confirmPending = null; render(); });
  render();
}
