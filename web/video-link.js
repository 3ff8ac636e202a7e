// The watched feed's link, beside glass-to-glass in the video overlay: the bitrate arriving at
// the station and the repairs its receiver made (packets asked for again and recovered, those
// given up on), from the station's word on the feed (the "video" push, once a second).
import { state, subscribe } from "./store.js";

const $ = (selector) => document.querySelector(selector);

export function startVideoLink() {
  let last = null;
  subscribe("video-state", () => {
    const video = state.videoState;
    const element = $("#video-link");
    if (!element) return;
    if (!video?.watching) { element.textContent = "—"; last = null; return; }
    const now = performance.now();
    const sameFeed = last && last.feed === video.feed && video.bytes >= last.bytes;
    const kbps = sameFeed ? ((video.bytes - last.bytes) * 8) / (now - last.at) : null;
    last = { feed: video.feed, bytes: video.bytes ?? 0, at: now };
    const repair = video.repair ?? {};
    const rate = kbps == null ? "— kbit/s" : `${Math.round(kbps)} kbit/s`;
    element.textContent = `${rate} · ${repair.repaired ?? 0} repaired · ${repair.lost ?? 0} lost`;
    element.dataset.kbps = kbps == null ? "" : String(Math.round(kbps));
    element.title = `packets asked for again: ${repair.retransmission_requests ?? 0}; ` +
      `keyframes asked for: ${repair.keyframe_requests ?? 0}; round trip ${repair.rtt_ms ?? "—"} ms`;
  });
}
