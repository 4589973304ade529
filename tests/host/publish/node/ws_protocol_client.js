// A Foxglove WebSocket protocol v1 client as Lichtblick and foxglove-era tools use it: the npm
// package @foxglove/ws-protocol (FoxgloveClient), offering its own subprotocol
// (FoxgloveClient.SUPPORTED_SUBPROTOCOL, "foxglove.websocket.v1").
//
//   node ws_protocol_client.js URL TOPICS_JSON WANT TIMEOUT_S
//
// Subscribes to every advertised channel whose topic is in TOPICS_JSON, collects WANT messages per
// topic, then prints one JSON document on stdout: the subprotocol the server answered with, the
// server's name, the advertised channels and the messages (base64 payloads) per topic. Exit 0
// when every topic got WANT messages, 1 on a timeout or an error (the document is printed anyway).
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");

let WebSocketImpl;
try {
  WebSocketImpl = require("ws"); // the npm package when installed beside it
} catch (e) {
  WebSocketImpl = globalThis.WebSocket; // Node >= 22 (or --experimental-websocket)
}

const [url, topicsJson, wantText, timeoutText] = process.argv.slice(2);
const topics = JSON.parse(topicsJson);
const want = Number(wantText);
const out = { subprotocol: null, serverName: null, channels: [], messages: {}, errors: [], resubscribed: [] };
for (const t of topics) out.messages[t] = [];

const ws = new WebSocketImpl(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const subscribed = new Map(); // subscription id -> topic

let finished = false;
function finish(code) {
  if (finished) return; // messages that come while the document is being written
  finished = true;
  try {
    client.close();
  } catch (e) {
    // already closed
  }
  // exit once the document is written: a pipe takes it asynchronously, and exiting at once cut it
  // at 64 KiB
  process.stdout.write(JSON.stringify(out) + "\n", () => process.exit(code));
}

const timer = setTimeout(() => {
  out.errors.push("timeout");
  finish(1);
}, Number(timeoutText) * 1000);

client.on("open", () => {
  out.subprotocol = ws.protocol;
});
client.on("error", (err) => {
  out.errors.push(String(err && err.message ? err.message : err));
});
client.on("close", () => {
  if (!topics.every((t) => out.messages[t].length >= want)) {
    out.errors.push("closed by the server");
    clearTimeout(timer);
    finish(1);
  }
});
client.on("serverInfo", (info) => {
  out.serverName = info.name;
});
// foxglove-sdk (0.30) sends a channel's advertise before it records the channel as advertised to
// that client (ConnectedClient::advertise_channels: send_control_msg, then channels.insert): a
// client that answers fast enough, or a server thread preempted between the two, gets the status
// error "Unknown channel ID: N" for its subscribe, and that channel stays silent for the session.
// A client that wants the data subscribes again; each time is listed in `resubscribed`.
const RESUBSCRIBE_LIMIT = 5;
const topicOfChannel = new Map(); // advertised channel id -> topic
client.on("status", (status) => {
  const m = /Unknown channel ID: (\d+)/.exec(String(status && status.message));
  if (!m) return;
  const channelId = Number(m[1]);
  const topic = topicOfChannel.get(channelId);
  if (topic === undefined || !topics.includes(topic)) return;
  if (out.resubscribed.filter((t) => t === topic).length >= RESUBSCRIBE_LIMIT) {
    out.errors.push(`channel ${channelId} (${topic}) still unknown after ${RESUBSCRIBE_LIMIT} subscribes`);
    return;
  }
  out.resubscribed.push(topic);
  setTimeout(() => subscribed.set(client.subscribe(channelId), topic), 50);
});
client.on("advertise", (channels) => {
  for (const ch of channels) {
    out.channels.push({ id: ch.id, topic: ch.topic, encoding: ch.encoding, schemaName: ch.schemaName, schema: ch.schema });
    topicOfChannel.set(ch.id, ch.topic);
    if (topics.includes(ch.topic)) subscribed.set(client.subscribe(ch.id), ch.topic);
  }
});
client.on("message", ({ subscriptionId, data }) => {
  const topic = subscribed.get(subscriptionId);
  if (topic === undefined) return;
  const bytes = Buffer.from(data.buffer, data.byteOffset, data.byteLength);
  out.messages[topic].push(bytes.toString("base64"));
  if (topics.every((t) => out.messages[t].length >= want)) {
    clearTimeout(timer);
    finish(0);
  }
});
