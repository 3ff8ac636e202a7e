// The answer line: what the platform or the station said to the operator's last action, in a
// sentence, gone after a while so an old answer is never read as a new one.

import { $, plainReason } from "./common.js";

const KEEP_MS = 8000;
const timers = new WeakMap(); // answer line → its expiry

/** Say ``text`` (a sentence) on ``line``, an answer line of the page, for ``keepMs``;
 * ``refused`` shows it as a refusal. */
export function sayOn(line, text, { refused = false, keepMs = KEEP_MS } = {}) {
  line.textContent = plainReason(text);
  line.title = line.textContent; // one line on screen: the whole answer on hover
  line.classList.toggle("refused", refused);
  clearTimeout(timers.get(line));
  timers.set(line, setTimeout(() => { line.textContent = ""; line.classList.remove("refused"); }, keepMs));
}

/** Say ``text`` (a sentence) on the console's answer line. */
export function say(text, { refused = false } = {}) {
  sayOn($("#answer"), text, { refused });
}

/** A command's answer as a sentence: "diagnostics: acknowledged." or "…: refused (reason)." */
export function sentence(label, result) {
  if (result && result.accepted === false) return `${label}: refused (${result.reason || "no reason given"}).`;
  const detail = result?.result ?? result;
  const said = typeof detail === "string" && detail && detail !== "OK" ? ` (${detail})` : "";
  return `${label}: acknowledged${said}.`;
}
