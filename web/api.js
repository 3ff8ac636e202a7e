// The station daemon's local API over one WebSocket (JSON-RPC 2.0): calls with timeouts,
// pushed notifications by method name, binary messages (the NavCam), reconnection.

export class StationApi {
  constructor(url, { onState, onBinary, onOpen } = {}) {
    this.url = url;
    this.nextId = 1;
    this.pending = new Map();
    this.handlers = new Map();
    this.onState = onState ?? (() => {});
    this.onBinary = onBinary ?? (() => {});
    this.onOpen = onOpen ?? (() => {});
    this.ws = null;
    this.attempt = 0;
    this.open();
  }

  get connected() { return this.ws !== null && this.ws.readyState === WebSocket.OPEN; }

  on(method, handler) { this.handlers.set(method, handler); }

  open() {
    this.onState(this.attempt === 0 ? "connecting" : "reconnecting");
    const ws = new WebSocket(this.url);
    ws.binaryType = "arraybuffer";
    ws.onopen = () => {
      this.ws = ws;
      this.attempt = 0;
      this.onState("connected");
      this.onOpen();
    };
    ws.onclose = () => {
      if (this.ws === ws) this.ws = null;
      for (const call of this.pending.values()) { clearTimeout(call.timer); call.reject(new Error("station connection lost")); }
      this.pending.clear();
      this.attempt += 1;
      this.onState("reconnecting");
      setTimeout(() => this.open(), Math.min(2000, 250 * this.attempt));
    };
    ws.onmessage = (event) => {
      if (typeof event.data !== "string") { this.onBinary(event.data); return; }
      let message;
      try { message = JSON.parse(event.data); } catch { return; }
      if (message.id === undefined || message.id === null) {
        const handler = this.handlers.get(message.method);
        if (handler) handler(message.params);
        return;
      }
      const call = this.pending.get(message.id);
      if (!call) return;
      this.pending.delete(message.id);
      clearTimeout(call.timer);
      if (message.error) call.reject(Object.assign(new Error(message.error.message), { code: message.error.code }));
      else call.resolve(message.result);
    };
  }

  /** Call ``method``; rejects after ``timeoutMs`` or when the socket is down. */
  call(method, params = {}, timeoutMs = 5000) {
    if (!this.connected) return Promise.reject(new Error("station not connected"));
    const id = this.nextId++;
    return new Promise((resolve, reject) => {
      const timer = setTimeout(() => {
        this.pending.delete(id);
        reject(new Error(`${method}: no answer in ${timeoutMs / 1000} s`));
      }, timeoutMs);
      this.pending.set(id, { resolve, reject, timer });
      this.ws.send(JSON.stringify({ jsonrpc: "2.0", id, method, params }));
    });
  }

  /** Send a binary message (push-to-talk audio); dropped while the socket is down. */
  sendBinary(buffer) { if (this.connected) this.ws.send(buffer); }

  /** True when the socket has more than ``bytes`` waiting to be sent (a stalled link). */
  backedUp(bytes = 4096) { return !this.connected || this.ws.bufferedAmount > bytes; }
}
