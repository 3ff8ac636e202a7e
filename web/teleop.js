// Teleop in the browser: the keyboard (WASD / arrows, space = stop) and a game controller
// (Gamepad API, standard mapping: hold LB to drive with the left stick; A toggles the override,
// Y the main lights). While this console drives, the velocity goes to the station 20 times a
// second; losing focus, hiding the tab or a vanished gamepad sends a stop at once. The station
// stops the robot by itself when the sends stop coming (console.drive_timeout).

import { keyForFocusedField } from "./common.js";

const PERIOD_MS = 50;
const KEY_SPEED = 0.5;
const DEADZONE = 0.15;
const ENABLE = 4, BUTTON_OVERRIDE = 0, BUTTON_LIGHTS = 3;
const KEYS = {
  KeyW: [1, 0], ArrowUp: [1, 0], KeyS: [-1, 0], ArrowDown: [-1, 0],
  KeyA: [0, 1], ArrowLeft: [0, 1], KeyD: [0, -1], ArrowRight: [0, -1],
};

export class Teleop {
  constructor({ send, onOverrideButton, onLightsButton, onIgnored }) {
    this.send = send; // (linear, angular) => Promise
    this.onIgnored = onIgnored ?? (() => {}); // a drive key while this console does not drive
    this.onOverrideButton = onOverrideButton;
    this.onLightsButton = onLightsButton;
    this.held = new Set();
    this.active = false; // this console drives
    this.buttons = [];
    this.sentZero = true;
    this.lastSource = "idle";
    this.commanded = [0, 0]; // what is being sent now: [linear, angular], each -1..1
    window.addEventListener("keydown", (event) => this.key(event, true));
    window.addEventListener("keyup", (event) => this.key(event, false));
    window.addEventListener("blur", () => this.halt("focus lost"));
    document.addEventListener("visibilitychange", () => { if (document.hidden) this.halt("tab hidden"); });
    window.addEventListener("pagehide", () => this.halt("page closed"));
    window.addEventListener("gamepaddisconnected", () => this.halt("gamepad vanished"));
    setInterval(() => this.tick(), PERIOD_MS);
  }

  key(event, down) {
    if (keyForFocusedField(event)) return;
    if (event.code === "Space") {
      if (down) this.held.clear();
      event.preventDefault();
      return;
    }
    if (!(event.code in KEYS)) return;
    event.preventDefault();
    if (down && !this.active && !event.repeat) this.onIgnored();
    if (down) this.held.add(event.code); else this.held.delete(event.code);
  }

  /** Stop now: forget held keys and send zeros (the loop goes on sending zeros). */
  halt(reason) {
    this.held.clear();
    this.lastSource = reason;
    if (this.active) this.send(0, 0).catch(() => {});
    this.sentZero = true;
  }

  setActive(active) {
    if (this.active && !active) this.held.clear();
    this.active = active;
  }

  gamepad() {
    const pads = navigator.getGamepads ? [...navigator.getGamepads()].filter(Boolean) : [];
    const pad = pads.find((p) => p.mapping === "standard") ?? pads[0];
    if (!pad) return null;
    const pressed = pad.buttons.map((b) => b.pressed);
    const edge = (i) => pressed[i] && !this.buttons[i];
    if (edge(BUTTON_OVERRIDE)) this.onOverrideButton();
    if (edge(BUTTON_LIGHTS)) this.onLightsButton();
    this.buttons = pressed;
    if (!pressed[ENABLE]) return [0, 0, false];
    const axis = (v) => (Math.abs(v) < DEADZONE ? 0 : Math.sign(v) * (Math.abs(v) - DEADZONE) / (1 - DEADZONE));
    return [-axis(pad.axes[1] ?? 0), -axis(pad.axes[0] ?? 0), true];
  }

  velocity() {
    const pad = this.gamepad();
    if (pad && pad[2]) { this.lastSource = "gamepad"; return [pad[0], pad[1]]; }
    let linear = 0, angular = 0;
    for (const code of this.held) { linear += KEYS[code][0]; angular += KEYS[code][1]; }
    if (this.held.size) this.lastSource = "keyboard";
    const clamp = (v) => Math.max(-1, Math.min(1, v));
    return [clamp(linear) * KEY_SPEED, clamp(angular) * KEY_SPEED];
  }

  tick() {
    if (!this.active) { this.commanded = [0, 0]; this.gamepad(); return; }
    if (document.hidden) this.held.clear();
    const [linear, angular] = this.velocity();
    this.commanded = [linear, angular];
    const zero = linear === 0 && angular === 0;
    if (zero && this.sentZero) return; // idle: the station already streams zeros
    this.sentZero = zero;
    this.send(linear, angular).catch(() => {});
  }
}
