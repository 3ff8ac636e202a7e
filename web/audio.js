// Two-way audio in the page, Opus end to end, no WebRTC. Listening: the station forwards the
// platform's microphone as Opus packets (binary messages of type 2, the NavCam's header);
// WebCodecs AudioDecoder decodes them and each 20 ms is scheduled on an AudioContext 30 ms
// ahead (a jitter margin). Push-to-talk: the page's microphone (getUserMedia) through
// MediaStreamTrackProcessor → AudioEncoder (Opus) → binary messages of type 3 → the station,
// which sends them as RTP to the platform's speaker.
//
// The latency figure shown is station arrival → scheduled output (+ the context's output
// latency): the platform's audio carries no capture stamp.

const HEADER = 24;
const LEAD_S = 0.03;
const MAX_AHEAD_S = 0.08;

export class PlatformAudio {
  constructor(api, { onStats }) {
    this.api = api;
    this.onStats = onStats;
    this.context = null;
    this.decoder = null;
    this.next = 0;
    this.listening = null;
    this.stats = { packets: 0, decoded: 0, latencyMs: null, talkPackets: 0 };
    this.arrivals = new Map();
    this.clockOffsetMs = 0;
    this.talk = null;
  }

  static supported() { return typeof AudioDecoder !== "undefined"; }

  async listen(platformId) {
    if (!PlatformAudio.supported()) throw new Error("this browser has no WebCodecs AudioDecoder");
    this.context ??= new AudioContext({ sampleRate: 48000, latencyHint: "interactive" });
    await this.context.resume();
    if (!this.decoder || this.decoder.state === "closed") {
      this.decoder = new AudioDecoder({ output: (data) => this.play(data), error: (e) => console.warn("audio decoder:", e) });
      this.decoder.configure({ codec: "opus", sampleRate: 48000, numberOfChannels: 1 });
    }
    this.listening = platformId;
    await this.api.call("audio_listen", { platform_id: platformId, on: true }, 10000);
  }

  async stopListening() {
    const was = this.listening;
    this.listening = null;
    if (was) await this.api.call("audio_listen", { platform_id: was, on: false }).catch(() => {});
  }

  onPacket(buffer) {
    if (!this.listening || !this.decoder || this.decoder.state !== "configured") return;
    const view = new DataView(buffer);
    const seq = view.getUint32(4);
    this.stats.packets += 1;
    this.arrivals.set(seq * 20000, view.getFloat64(16));
    if (this.arrivals.size > 50) this.arrivals.delete(this.arrivals.keys().next().value);
    this.decoder.decode(new EncodedAudioChunk({ type: "key", timestamp: seq * 20000, data: new Uint8Array(buffer, HEADER) }));
  }

  play(data) {
    const context = this.context;
    const buffer = context.createBuffer(1, data.numberOfFrames, data.sampleRate);
    data.copyTo(buffer.getChannelData(0), { planeIndex: 0, format: "f32-planar" });
    const arrival = this.arrivals.get(data.timestamp);
    data.close();
    const source = context.createBufferSource();
    source.buffer = buffer;
    source.connect(context.destination);
    let at = Math.max(this.next, context.currentTime + LEAD_S);
    if (at - context.currentTime > MAX_AHEAD_S) at = context.currentTime + LEAD_S; // drift: resync
    source.start(at);
    this.next = at + buffer.duration;
    this.stats.decoded += 1;
    if (arrival) {
      const wall = performance.timeOrigin + performance.now() + this.clockOffsetMs;
      const output = (context.outputLatency || context.baseLatency || 0) * 1000;
      this.stats.latencyMs = wall - arrival + (at - context.currentTime) * 1000 + output;
    }
    if (this.stats.decoded % 10 === 0) this.onStats(this.stats);
  }

  /** Start sending this page's microphone to ``platformId``'s speaker. */
  async startTalking(platformId) {
    if (typeof AudioEncoder === "undefined" || typeof MediaStreamTrackProcessor === "undefined") {
      throw new Error("push-to-talk needs WebCodecs AudioEncoder and MediaStreamTrackProcessor (Chromium)");
    }
    if (this.talk) return;
    const media = await navigator.mediaDevices.getUserMedia({ audio: { channelCount: 1, echoCancellation: true, noiseSuppression: true } });
    const track = media.getAudioTracks()[0];
    const talk = { track, seq: 0, encoder: null, stopped: false };
    this.talk = talk;
    await this.api.call("audio_talk", { platform_id: platformId, on: true }, 8000);
    const reader = new MediaStreamTrackProcessor({ track }).readable.getReader();
    (async () => {
      while (!talk.stopped) {
        const { value: data, done } = await reader.read();
        if (done) break;
        if (!talk.encoder) {
          talk.encoder = new AudioEncoder({ output: (chunk) => this.send(talk, chunk), error: (e) => console.warn("audio encoder:", e) });
          talk.encoder.configure({ codec: "opus", sampleRate: data.sampleRate, numberOfChannels: data.numberOfChannels, bitrate: 24000 });
        }
        if (talk.stopped) { data.close(); break; }
        talk.encoder.encode(data);
        data.close();
      }
      reader.cancel().catch(() => {});
    })().catch((error) => console.warn("push-to-talk:", error));
  }

  send(talk, chunk) {
    if (talk.stopped) return;
    const message = new ArrayBuffer(HEADER + chunk.byteLength);
    const view = new DataView(message);
    view.setUint8(0, 3);
    view.setUint32(4, talk.seq++);
    view.setFloat64(8, performance.timeOrigin + performance.now() + this.clockOffsetMs);
    chunk.copyTo(new Uint8Array(message, HEADER));
    this.api.sendBinary(message);
    this.stats.talkPackets += 1;
  }

  async stopTalking(platformId) {
    const talk = this.talk;
    this.talk = null;
    if (!talk) return;
    talk.stopped = true;
    talk.track.stop();
    if (talk.encoder && talk.encoder.state !== "closed") talk.encoder.close();
    await this.api.call("audio_talk", { platform_id: platformId, on: false }).catch(() => {});
  }
}
