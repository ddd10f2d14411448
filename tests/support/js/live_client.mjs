// Watch a loopcal live view as Foxglove does: the Foxglove WebSocket protocol's own client
// (@foxglove/ws-protocol over ws), subscribed to every channel the server advertises, each
// message decoded with the schema the server advertised for it (ROS 2 messages in CDR with
// the decoder Foxglove uses, JSON as JSON). Prints one JSON object and exits: the server's
// info, the channels, per topic the messages received and decoded and their log times
// (first and last, ns), the first and the last message of each topic decoded (sample, last),
// and every decoding error.
//
// Usage: node live_client.mjs ws://127.0.0.1:PORT SECONDS [CLIENTS [STALLED]]: CLIENTS
// clients at once (the first one's findings are printed; "others" counts what the rest
// received), of which STALLED subscribe to everything and then never read their socket again
// (a viewer whose network stalled).
import wsProtocol from "@foxglove/ws-protocol";
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";
import { WebSocket } from "ws";

const { FoxgloveClient } = wsProtocol; // a CommonJS package

const [url, seconds, clients = "1", stalled = "0"] = process.argv.slice(2);
const plain = (value) =>
  JSON.parse(
    JSON.stringify(value, (_, v) => {
      if (typeof v === "bigint" || (typeof v === "number" && !Number.isFinite(v))) return String(v);
      return ArrayBuffer.isView(v) ? Array.from(v) : v;
    }),
  );

// The protocol's current name, which foxglove-sdk's server requires (the same protocol as
// foxglove.websocket.v1, the name this client was written for; since 0.7.5 it does not
// insist on it)
const connect = () => {
  const ws = new WebSocket(url, ["foxglove.sdk.v1"]);
  return { ws, client: new FoxgloveClient({ ws }) };
};
const out = { serverInfo: null, channels: [], topics: {}, errors: [], others: { received: 0 } };
const utf8 = new TextDecoder();
const { client } = connect();
const bySubscription = new Map();

client.on("serverInfo", (info) => {
  out.serverInfo = info;
});
client.on("error", (e) => out.errors.push(`connection: ${e?.message ?? e}`));
client.on("advertise", (channels) => {
  for (const ch of channels) {
    out.channels.push({ topic: ch.topic, encoding: ch.encoding, schemaName: ch.schemaName,
                        schemaEncoding: ch.schemaEncoding });
    let decode;
    try {
      if (ch.encoding === "cdr" && ch.schemaEncoding === "ros2msg") {
        const reader = new MessageReader(parse(ch.schema, { ros2: true }));
        decode = (data) => reader.readMessage(data);
      } else if (ch.encoding === "json") {
        JSON.parse(ch.schema);
        decode = (data) => JSON.parse(utf8.decode(data));
      } else {
        throw new Error(`no decoder for ${ch.encoding} / ${ch.schemaEncoding}`);
      }
    } catch (e) {
      out.errors.push(`${ch.topic}: schema: ${e.message}`);
      continue;
    }
    out.topics[ch.topic] = { received: 0, decoded: 0, first_ns: null, last_ns: null, sample: null };
    bySubscription.set(client.subscribe(ch.id), { topic: ch.topic, decode });
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const sub = bySubscription.get(subscriptionId);
  if (!sub) return;
  const t = out.topics[sub.topic];
  t.received += 1;
  try {
    const bytes = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
    const msg = sub.decode(bytes);
    t.decoded += 1;
    if (t.sample === null) t.sample = plain(msg);
    t.last = msg;
  } catch (e) {
    out.errors.push(`${sub.topic}: message ${t.received}: ${e.message}`);
  }
  const ns = String(timestamp);
  if (t.first_ns === null) t.first_ns = ns;
  t.last_ns = ns;
});


for (let k = 1; k < Number(clients); k++) {
  const { ws, client: other } = connect();
  const stall = k <= Number(stalled);
  other.on("error", (e) => out.errors.push(`client ${k}: ${e?.message ?? e}`));
  other.on("advertise", (channels) => {
    for (const ch of channels) other.subscribe(ch.id);
    if (stall) ws._socket.pause(); // subscribed to everything, and never reads again
  });
  other.on("message", () => {
    out.others.received += 1;
  });
}

setTimeout(() => {
  for (const t of Object.values(out.topics)) t.last = t.last === undefined ? null : plain(t.last);
  console.log(JSON.stringify(out));
  client.close();
  process.exit(0);
}, Number(seconds) * 1000);
