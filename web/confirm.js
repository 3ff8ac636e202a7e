// Slide to confirm: an act that moves the robot or powers it (arm, start patrol) is a slider
// pulled to its end, never a single click. Released short of the end it springs back; the
// keyboard's End key (or the arrows) reaches the end too.

import { element } from "./common.js";

const END = 100;
const CONFIRMED_AT = 95;

/** A slider labelled ``text`` that calls ``onConfirm()`` once pulled to its end. */
export function slideToConfirm(id, text, onConfirm) {
  const slider = element("input", { id, type: "range", min: "0", max: String(END), value: "0", "aria-label": text });
  const caption = element("span", { class: "slide-text" }, text);
  const box = element("label", { class: "slide-confirm" }, caption, slider);
  const settle = () => {
    const confirmed = Number(slider.value) >= CONFIRMED_AT;
    slider.value = "0";
    box.style.setProperty("--done", "0");
    if (confirmed) onConfirm();
  };
  slider.addEventListener("input", () => box.style.setProperty("--done", String(Number(slider.value) / END)));
  slider.addEventListener("change", settle); // released (pointer) or moved by a key
  return {
    box,
    /** A new wording (arm ↔ disarm); the slider keeps its place in the page. */
    say(words) {
      if (caption.textContent !== words) caption.textContent = words;
      if (slider.getAttribute("aria-label") !== words) slider.setAttribute("aria-label", words);
    },
    enable(why) {
      slider.disabled = Boolean(why);
      box.title = why;
      box.classList.toggle("disabled", Boolean(why));
    },
  };
}
