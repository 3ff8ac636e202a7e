// The answer line: what the platform or the station said to the operator's last action, in a
// sentence, gone after a while so an old answer is never read as a new one.

import { $ } from "./common.js";

const KEEP_MS = 8000;
let timer = null;

/** Say ``text`` (a sentence) on the answer line; ``refused`` shows it as a refusal. */
export function say(text, { refused = false } = {}) {
  const line = $("#answer");
  line.textContent = text;
  line.classList.toggle("refused", refused);
  clearTimeout(timer);
  timer = setTimeout(() => { line.textContent = ""; }, KEEP_MS);
}

/** A command's answer as a sentence: "diagnostics: acknowledged." or "…: refused (reason)." */
export function sentence(label, result) {
  if (result && result.accepted === false) return `${label}: refused (${result.reason || "no reason given"}).`;
  const detail = result?.result ?? result;
  const said = typeof detail === "string" && detail && detail !== "OK" ? ` (${detail})` : "";
  return `${label}: acknowledged${said}.`;
}
