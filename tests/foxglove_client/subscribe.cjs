// A real Foxglove WebSocket client (@foxglove/ws-protocol over ws) for the tests: connects,
// subscribes to the topics given, and prints one JSON line per message received:
// {"topic", "schema", "encoding", "logTime", "bytes", "json"} (json: the decoded message, with a
// CompressedVideo's data cut to its first bytes, base64). Exits after COUNT messages per topic.
// usage: node subscribe.js ws://127.0.0.1:PORT COUNT TOPIC...
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const [url, countText, ...topics] = process.argv.slice(2);
const wanted = Number(countText);
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL, "foxglove.sdk.v1"]);
const client = new FoxgloveClient({ ws });
const bySubscription = new Map();
const received = new Map(topics.map((t) => [t, 0]));
const decoder = new TextDecoder();

client.on("serverInfo", (info) => {
  console.log(JSON.stringify({ serverInfo: info.name, subprotocol: ws.protocol }));
});
client.on("advertise", (channels) => {
  for (const channel of channels) {
    if (received.has(channel.topic)) {
      bySubscription.set(client.subscribe(channel.id), channel);
    }
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const channel = bySubscription.get(subscriptionId);
  if (!channel || received.get(channel.topic) >= wanted) return;
  received.set(channel.topic, received.get(channel.topic) + 1);
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
  if ([...received.values()].every((n) => n >= wanted)) {
    client.close();
    process.exit(0);
  }
});
client.on("error", (error) => {
  console.error(String(error));
});
client.on("close", () => process.exit(received.size ? 3 : 0));
