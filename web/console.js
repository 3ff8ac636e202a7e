// Brasidas browser console: the station daemon's local API over a WebSocket (JSON-RPC 2.0).
// The same API the CLI uses; the station daemon holds the platform sessions.

const $ = (selector, root = document) => root.querySelector(selector);

class Api {
  constructor(url) {
    this.url = url;
    this.nextId = 1;
    this.pending = new Map();
    this.ready = this.open();
  }

  open() {
    return new Promise((resolve, reject) => {
      const ws = new WebSocket(this.url);
      ws.onopen = () => { this.ws = ws; setApiState("station connected", "ok"); resolve(); };
      ws.onerror = () => reject(new Error("station API unreachable"));
      ws.onclose = () => {
        setApiState("station disconnected", "bad");
        for (const { reject: fail } of this.pending.values()) fail(new Error("closed"));
        this.pending.clear();
        setTimeout(() => { this.ready = this.open(); }, 1000);
      };
      ws.onmessage = (event) => {
        const answer = JSON.parse(event.data);
        const call = this.pending.get(answer.id);
        if (!call) return;
        this.pending.delete(answer.id);
        if (answer.error) call.reject(new Error(answer.error.message));
        else call.resolve(answer.result);
      };
    });
  }

  async call(method, params = {}) {
    await this.ready;
    const id = this.nextId++;
    return new Promise((resolve, reject) => {
      this.pending.set(id, { resolve, reject });
      this.ws.send(JSON.stringify({ jsonrpc: "2.0", id, method, params }));
    });
  }
}

function setApiState(text, kind) {
  const pill = $("#api-state");
  pill.textContent = text;
  pill.className = `pill ${kind}`;
}

const api = new Api(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/api/rpc/ws`);
const cards = new Map();

function flags(status) {
  return Object.entries(status).filter(([, on]) => on === true).map(([name]) => name).join(" ");
}

async function refreshPlatforms() {
  const platforms = await api.call("list_platforms");
  const body = $("#platforms tbody");
  body.replaceChildren(...platforms.map((entry) => {
    const row = document.createElement("tr");
    row.dataset.platform = entry.id;
    const position = entry.position ? entry.position.map((v) => v.toFixed(6)).join(", ") : "—";
    for (const text of [entry.id, entry.url, flags(entry.status) || "—", position, `${entry.age_s.toFixed(1)} s ago`]) {
      const cell = document.createElement("td");
      cell.textContent = text;
      row.append(cell);
    }
    const action = document.createElement("td");
    const button = document.createElement("button");
    button.textContent = cards.has(entry.id) ? "connected" : "connect";
    button.disabled = cards.has(entry.id);
    button.className = "connect";
    button.onclick = () => connect(entry.id);
    action.append(button);
    row.append(action);
    return row;
  }));
  $("#no-platforms").hidden = platforms.length > 0;
}

async function connect(platformId) {
  try {
    await api.call("connect", { platform_id: platformId });
    await refreshConnections();
  } catch (error) {
    showAnswer(platformId, `connect failed: ${error.message}`);
  }
}

function showAnswer(platformId, text) {
  const card = cards.get(platformId);
  if (card) $(".answer", card).textContent = text;
}

function describeResult(result) {
  return result.accepted === false ? `rejected: ${result.reason}` : `acknowledged ${JSON.stringify(result.result ?? result)}`;
}

function card(platformId) {
  let element = cards.get(platformId);
  if (element) return element;
  element = $("#platform-card").content.firstElementChild.cloneNode(true);
  element.dataset.platform = platformId;
  $(".pid", element).textContent = platformId;
  $(".movrd", element).onclick = async () => {
    const engaged = !element.classList.contains("teleop");
    try {
      showAnswer(platformId, describeResult(await api.call("movrd", { platform_id: platformId, engaged })));
    } catch (error) { showAnswer(platformId, error.message); }
    refreshConnections();
  };
  for (const [selector, which] of [[".lights-main", "main"], [".lights-pos", "positional"]]) {
    $(selector, element).onclick = async (event) => {
      const on = !event.target.classList.contains("on");
      try {
        const result = await api.call("lights", { platform_id: platformId, which, on });
        showAnswer(platformId, describeResult(result));
        if (result.accepted !== false) event.target.classList.toggle("on", on);
      } catch (error) { showAnswer(platformId, error.message); }
    };
  }
  $(".disconnect", element).onclick = async () => {
    await api.call("disconnect", { platform_id: platformId });
    refreshConnections();
  };
  cards.set(platformId, element);
  $("#connected").append(element);
  return element;
}

async function refreshConnections() {
  const connections = await api.call("connections");
  const live = new Set();
  for (const summary of connections) {
    live.add(summary.platform_id);
    const element = card(summary.platform_id);
    const teleop = Boolean(summary.manual_override);
    element.classList.toggle("teleop", teleop);
    const mode = $(".mode", element);
    mode.textContent = teleop ? "TELEOP" : "AUTONOMOUS";
    mode.className = `mode pill ${teleop ? "teleop" : "ok"}`;
    $(".movrd", element).textContent = teleop ? "release override" : "take manual override";
    $(".rtt", element).textContent = summary.round_trip_ms == null ? "" : `${summary.round_trip_ms.toFixed(2)} ms`;
  }
  for (const [platformId, element] of cards) {
    if (!live.has(platformId)) { element.remove(); cards.delete(platformId); }
  }
}

function telemetryRows(snapshot) {
  const rows = [];
  const add = (name, value) => { if (value !== null && value !== undefined) rows.push([name, value]); };
  add("battery", snapshot.battery && `${snapshot.battery.volts ?? "?"} V ${snapshot.battery.level ?? ""}`);
  const controller = snapshot.controller;
  add("controller", controller && `${controller.connected ? "connected" : "LOST"}  heatsinks ${(controller.temps_c ?? []).join("/")} °C  motors ${(controller.amps ?? []).join("/")} A`);
  const gps = snapshot.gps;
  add("gps", gps && (gps.fix ? `${gps.lat?.toFixed(6)}, ${gps.lon?.toFixed(6)}  ${gps.sats ?? "?"} sats  hdop ${gps.hdop ?? "?"}` : "no fix"));
  add("attitude", snapshot.attitude && ["roll", "pitch", "yaw"].map((k) => `${k} ${snapshot.attitude[k]?.toFixed?.(1) ?? "?"}`).join("  "));
  const streams = Object.entries(snapshot.streams ?? {});
  add("streams", streams.length ? streams.map(([name, state]) => `${name} ${state}`).join("  ") : null);
  const computer = snapshot.computer;
  add("computer", computer && [
    computer.cpu_temp_c == null ? null : `cpu ${computer.cpu_temp_c} °C`,
    `load ${(computer.load ?? []).map((v) => v.toFixed(2)).join(" ")}`,
    `free ${Math.round(computer.mem_free_mb ?? 0)} MB`,
  ].filter(Boolean).join("  "));
  return rows;
}

async function refreshTelemetry() {
  for (const [platformId, element] of cards) {
    let report;
    try { report = await api.call("get_telemetry", { platform_id: platformId }); } catch { continue; }
    const lights = report.snapshot?.lights;
    if (lights) {
      $(".lights-main", element).classList.toggle("on", Boolean(lights.main));
      $(".lights-pos", element).classList.toggle("on", Boolean(lights.positional));
    }
    const list = $(".telemetry", element);
    const rows = report.snapshot ? telemetryRows(report.snapshot) : [];
    rows.push(["link", `loss ${report.link?.loss_pct ?? "?"}%`]);
    list.replaceChildren(...rows.flatMap(([name, value]) => {
      const term = document.createElement("dt"); term.textContent = name;
      const detail = document.createElement("dd"); detail.textContent = value;
      return [term, detail];
    }));
    $(".warnings", element).replaceChildren(...report.warnings.map((warning) => {
      const badge = document.createElement("span");
      badge.textContent = warning.message || warning.name;
      return badge;
    }));
  }
}

async function refreshNotifications() {
  const notes = await api.call("telemetry_notifications", { limit: 10 });
  $("#notifications").replaceChildren(...notes.reverse().map((note) => {
    const item = document.createElement("li");
    item.textContent = `${new Date(note.time * 1000).toLocaleTimeString()} ${note.platform_id} ${note.active ? "⚠" : "✓"} ${note.message}`;
    return item;
  }));
}

async function tick() {
  try {
    await refreshPlatforms();
    await refreshConnections();
    await refreshTelemetry();
    await refreshNotifications();
  } catch (error) {
    console.warn("refresh failed", error);
  }
}

tick();
setInterval(tick, 1000);
