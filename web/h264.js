// H.264 (Annex B) for WebCodecs, shared by the live NavCam's decoder (video-worker.js, a
// module worker) and the recordings view (recordings.js).

/** The codec string (avc1.PPCCLL: profile, constraints, level) of the first SPS (NAL type 7)
 *  after a start code in `bytes`; "" when there is none. */
export function codecFromSps(bytes) {
  for (let i = 0; i + 7 < bytes.length; i++) {
    if (bytes[i] === 0 && bytes[i + 1] === 0 && bytes[i + 2] === 1 && (bytes[i + 3] & 0x1f) === 7) {
      const hex = (v) => v.toString(16).padStart(2, "0");
      return `avc1.${hex(bytes[i + 4])}${hex(bytes[i + 5])}${hex(bytes[i + 6])}`;
    }
  }
  return "";
}
