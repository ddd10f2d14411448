// Read a loopcal recording with Foxglove's TypeScript MCAP reader and message decoders, and
// print what it holds as one JSON object (tests/test_recording_foxglove.py compares it with
// Python). A complete file is read through its index (McapIndexedReader); a file without a
// summary (a crash) record by record (McapStreamReader) up to where it was cut.
import { readFile } from "node:fs/promises";
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { loadDecompressHandlers } from "@mcap/support";
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";

const path = process.argv[2];
const bytes = new Uint8Array(await readFile(path));
const decompressHandlers = await loadDecompressHandlers();

// BigInts (uint64/int64 fields) become strings; typed arrays become plain arrays.
const plain = (value) =>
  JSON.parse(
    JSON.stringify(value, (_, v) =>
      typeof v === "bigint" ? v.toString() : ArrayBuffer.isView(v) ? Array.from(v) : v,
    ),
  );

const out = {
  indexed: false, truncated: false, header: null, schemas: {}, channels: {}, metadata: {},
  counts: {}, scans: [], states: { count: 0 }, transforms: { count: 0 }, events: [], logs: [],
  scene: null, trailingBytes: 0,
};
const schemas = new Map();
const channels = new Map();
const readers = new Map(); // channel id -> decode(data)

function addSchema(s) {
  schemas.set(s.id, s);
  out.schemas[s.name] = s.encoding;
}

function addChannel(c) {
  channels.set(c.id, c);
  const s = schemas.get(c.schemaId);
  out.channels[c.topic] = { schema: s?.name, messageEncoding: c.messageEncoding };
  if (c.messageEncoding === "cdr") {
    const text = new TextDecoder().decode(s.data);
    const reader = new MessageReader(parse(text, { ros2: true }));
    readers.set(c.id, (data) => {
      const msg = reader.readMessage(data);
      if (reader.lastReadHadTrailingBytes()) out.trailingBytes += 1;
      return msg;
    });
  } else if (c.messageEncoding === "json") {
    readers.set(c.id, (data) => JSON.parse(new TextDecoder().decode(data)));
  } else {
    throw new Error(`unexpected message encoding ${c.messageEncoding} on ${c.topic}`);
  }
}

function onMessage(m) {
  const topic = channels.get(m.channelId).topic;
  out.counts[topic] = (out.counts[topic] ?? 0) + 1;
  const msg = readers.get(m.channelId)(m.data);
  if (topic === "/daq/scans") {
    out.scans.push(...plain(msg.scans));
  } else if (topic === "/joint/state" || topic === "/plate/transform") {
    const key = topic === "/joint/state" ? "states" : "transforms";
    out[key].count += 1;
    out[key].first ??= plain(msg);
    out[key].last = plain(msg);
  } else if (topic === "/loopcal/events") {
    out.events.push(msg);
  } else if (topic === "/loopcal/log") {
    out.logs.push(msg);
  } else if (topic === "/plate/scene") {
    out.scene ??= msg.entities.map((e) => ({ id: e.id, frame_id: e.frame_id }));
  }
}

let indexed = null;
try {
  indexed = await McapIndexedReader.Initialize({
    readable: {
      size: async () => BigInt(bytes.length),
      read: async (offset, length) => bytes.subarray(Number(offset), Number(offset + length)),
    },
    decompressHandlers,
  });
} catch {
  indexed = null; // no footer or summary: a file cut short
}

if (indexed) {
  out.indexed = true;
  out.header = { profile: indexed.header.profile, library: indexed.header.library };
  for (const s of indexed.schemasById.values()) addSchema(s);
  for (const c of indexed.channelsById.values()) addChannel(c);
  for await (const m of indexed.readMetadata()) out.metadata[m.name] = Object.fromEntries(m.metadata);
  // Log-time order, as Foxglove plays it; scans are compared after sorting by counter.
  for await (const m of indexed.readMessages()) onMessage(m);
} else {
  const reader = new McapStreamReader({ decompressHandlers });
  reader.append(bytes);
  for (;;) {
    let rec;
    try {
      rec = reader.nextRecord();
    } catch (err) {
      console.error(`undecodable record: ${err.message}`);
      process.exit(1);
    }
    if (rec === undefined) break;
    if (rec.type === "Header") out.header = { profile: rec.profile, library: rec.library };
    else if (rec.type === "Schema") addSchema(rec);
    else if (rec.type === "Channel") addChannel(rec);
    else if (rec.type === "Metadata") out.metadata[rec.name] = Object.fromEntries(rec.metadata);
    else if (rec.type === "Message") onMessage(rec);
  }
  out.truncated = !reader.done();
}
console.log(JSON.stringify(out));
