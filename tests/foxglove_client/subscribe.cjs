// A real Foxglove WebSocket client (@foxglove/ws-protocol over ws) for the tests: connects,
// subscribes to the topics given, and prints one JSON line per message received:
// {"topic", "schema", "encoding", "logTime", "bytes", "json"} (json: the decoded message, with a
// CompressedVideo's data cut to its first bytes, base64). Exits after COUNT messages per topic.
// With --all (before the topics) it also subscribes to every other channel advertised, prints
// {"advertised": topic} for each, and exits only once every advertised channel had a message.
// usage: node subscribe.js ws://127.0.0.1:PORT COUNT [--all] TOPIC...
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const [url, countText, ...rest] = process.argv.slice(2);
const all = rest[0] === "--all";
const topics = all ? rest.slice(1) : rest;
const wanted = Number(countText);
// SUBPROTOCOLS (comma-separated) replaces the offer: "foxglove.websocket.v1" alone is what
// FoxgloveClient and older viewers offer.
const offer = process.env.SUBPROTOCOLS
  ? process.env.SUBPROTOCOLS.split(",")
  : [FoxgloveClient.SUPPORTED_SUBPROTOCOL, "foxglove.sdk.v1"];
const ws = new WebSocket(url, offer);
const client = new FoxgloveClient({ ws });
const bySubscription = new Map();
const received = new Map(topics.map((t) => [t, 0]));
const decoder = new TextDecoder();

client.on("serverInfo", (info) => {
  console.log(JSON.stringify({ serverInfo: info.name, subprotocol: ws.protocol }));
});
client.on("advertise", (channels) => {
  for (const channel of channels) {
    if (all) {
      console.log(JSON.stringify({ advertised: channel.topic, schema: channel.schemaName }));
      if (!received.has(channel.topic)) received.set(channel.topic, 0);
    }
    if (received.has(channel.topic)) {
      bySubscription.set(client.subscribe(channel.id), channel);
    }
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const channel = bySubscription.get(subscriptionId);
  if (!channel || received.get(channel.topic) >= wanted) return;
  const count = received.get(channel.topic) + 1;
  received.set(channel.topic, count);
  if (count > 1 && !topics.includes(channel.topic)) return; // --all: the first is enough
  const message = JSON.parse(decoder.decode(data));
  if (typeof message.data === "string") message.data = message.data.slice(0, 64);
  console.log(
    JSON.stringify({
      topic: channel.topic,
      schema: channel.schemaName,
      encoding: channel.encoding,
      logTime: timestamp.toString(),
      receivedNs: (BigInt(Date.now()) * 1000000n).toString(),
      bytes: data.byteLength,
      json: message,
    }),
  );
  const done = [...received].every(([topic, n]) => n >= (topics.includes(topic) ? wanted : 1));
  if (done) {
    client.close();
    process.exit(0);
  }
});
// Stopped (SIGTERM) before it had everything: say what is still missing, on stderr.
process.on("SIGTERM", () => {
  const missing = [...received].filter(([topic, n]) => n < (topics.includes(topic) ? wanted : 1));
  console.error(JSON.stringify({ missing: missing.map(([topic]) => topic) }));
  process.exit(4);
});
client.on("error", (error) => {
  console.error(String(error));
});
client.on("close", () => process.exit(received.size ? 3 : 0));
