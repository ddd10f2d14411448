// Read a loopcal recording with the TypeScript MCAP reader and message decoders Foxglove uses,
// and print what it holds as one JSON object (tests/daemon/recording/test_foxglove.py compares it with
// Python). A complete file is read through its index (McapIndexedReader); a file without a
// summary (a crash) record by record (McapStreamReader) up to where it was cut.
//
// Usage: node read_mcap.mjs FILE. Exits 1 with a message on stderr if the file is not MCAP or
// a record or message does not decode.
import { readFile } from "node:fs/promises";
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { loadDecompressHandlers } from "@mcap/support";
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";

// A decoded message as plain JSON: bigints (64-bit integers) and non-finite numbers (NaN in
// float fields) become strings, typed arrays plain arrays.
const plain = (value) =>
  JSON.parse(
    JSON.stringify(value, (_, v) => {
      if (typeof v === "bigint" || (typeof v === "number" && !Number.isFinite(v))) return String(v);
      return ArrayBuffer.isView(v) ? Array.from(v) : v;
    }),
  );

// Foxglove turns a jsonschema channel into datatypes with parseJsonSchema (packages/mcap-support
// of foxglove/studio, not published on npm) and shows nothing of the channel if that throws.
// This walks a schema the way it does and lists what it would reject.
function jsonSchemaErrors(schema, path, errors = []) {
  if (schema?.type !== "object") {
    errors.push(`${path}: "type" is ${JSON.stringify(schema?.type)}, expected "object"`);
  } else if (schema.properties == null) {
    errors.push(`${path}: object without "properties" (Object.entries(undefined): TypeError)`);
  } else {
    for (const [name, field] of Object.entries(schema.properties)) {
      const at = `${path}.${name}`;
      if (Array.isArray(field.oneOf)) {
        if (!field.oneOf.every((alt) => typeof alt.const === "number")) {
          errors.push(`${at}: oneOf alternatives must have number values`);
        }
        continue;
      }
      const [item, itemAt] = field.type === "array" ? [field.items ?? {}, `${at}[]`] : [field, at];
      if (item.type === "object") jsonSchemaErrors(item, itemAt, errors);
      else if (!["boolean", "string", "number", "integer"].includes(item.type)) {
        errors.push(`${itemAt}: unsupported type ${JSON.stringify(item.type)}`);
      }
    }
  }
  return errors;
}

const out = {
  indexed: false, truncated: false, leftoverBytes: 0, header: null, schemas: {}, channels: {},
  metadata: {}, counts: {}, scans: [], states: { count: 0 }, transforms: { count: 0 },
  events: [], logs: [], scene: null, trailingBytes: 0, jsonSchemaErrors: {},
};
const schemas = new Map();
const channels = new Map(); // channel id -> { topic, decode(data) }
const text = new TextDecoder();

function addSchema(s) {
  schemas.set(s.id, s);
  out.schemas[s.name] = s.encoding;
}

function addChannel(c) {
  const s = schemas.get(c.schemaId);
  if (s === undefined) throw new Error(`channel ${c.topic} refers to unknown schema ${c.schemaId}`);
  out.channels[c.topic] = { schema: s.name, messageEncoding: c.messageEncoding };
  let decode;
  if (c.messageEncoding === "cdr" && s.encoding === "ros2msg") {
    const reader = new MessageReader(parse(text.decode(s.data), { ros2: true }));
    decode = (data) => {
      const msg = reader.readMessage(data);
      if (reader.lastReadHadTrailingBytes()) out.trailingBytes += 1;
      return msg;
    };
  } else if (c.messageEncoding === "json" && s.encoding === "jsonschema") {
    const errors = jsonSchemaErrors(JSON.parse(text.decode(s.data)), s.name);
    if (errors.length) out.jsonSchemaErrors[s.name] = errors;
    decode = (data) => JSON.parse(text.decode(data));
  } else {
    throw new Error(`${c.topic}: unexpected encoding ${c.messageEncoding} / ${s.encoding}`);
  }
  channels.set(c.id, { topic: c.topic, decode });
}

function onMessage(m) {
  const channel = channels.get(m.channelId);
  if (channel === undefined) throw new Error(`message on unknown channel ${m.channelId}`);
  const { topic } = channel;
  out.counts[topic] = (out.counts[topic] ?? 0) + 1;
  let msg;
  try {
    msg = channel.decode(m.data);
  } catch (err) {
    throw new Error(`${topic}: message ${out.counts[topic]} does not decode: ${err.message}`);
  }
  if (topic === "/daq/scans" && msg.scans === undefined) {
    // a compacted file's block of columns (loopcal_msgs/msg/ScanColumns): decoded by its
    // schema as Foxglove does, its packed scans counted
    out.packedScans = (out.packedScans ?? 0) + msg.count;
    out.packedBytes = (out.packedBytes ?? 0) + msg.data.length;
  } else if (topic === "/daq/scans") {
    for (const scan of plain(msg.scans)) out.scans.push(scan);
  } else if (topic === "/joint/state" || topic === "/plate/transform") {
    const views = topic === "/joint/state" ? out.states : out.transforms;
    views.count += 1;
    views.first ??= plain(msg);
    views.last = plain(msg);
  } else if (topic === "/loopcal/events") {
    out.events.push(msg);
  } else if (topic === "/loopcal/log") {
    out.logs.push(msg);
  } else if (topic === "/plate/scene") {
    out.scene ??= msg.entities.map((e) => ({ id: e.id, frame_id: e.frame_id }));
  }
}

async function openIndexed(bytes, decompressHandlers) {
  try {
    return await McapIndexedReader.Initialize({
      readable: {
        size: async () => BigInt(bytes.length),
        read: async (offset, length) => bytes.subarray(Number(offset), Number(offset + length)),
      },
      decompressHandlers,
    });
  } catch {
    return undefined; // no footer or summary: a file cut short (or not MCAP: the stream says)
  }
}

async function main(path) {
  const bytes = new Uint8Array(await readFile(path));
  const decompressHandlers = await loadDecompressHandlers();
  const indexed = await openIndexed(bytes, decompressHandlers);
  if (indexed) {
    out.indexed = true;
    out.header = { profile: indexed.header.profile, library: indexed.header.library };
    for (const s of indexed.schemasById.values()) addSchema(s);
    for (const c of indexed.channelsById.values()) addChannel(c);
    for await (const m of indexed.readMetadata()) {
      out.metadata[m.name] = Object.fromEntries(m.metadata);
    }
    for await (const m of indexed.readMessages()) onMessage(m); // log-time order
  } else {
    const reader = new McapStreamReader({ decompressHandlers });
    reader.append(bytes);
    // nextRecord() gives undefined at the end, or where the rest is an incomplete record
    for (let rec; (rec = reader.nextRecord()); ) {
      if (rec.type === "Header") out.header = { profile: rec.profile, library: rec.library };
      else if (rec.type === "Schema") addSchema(rec);
      else if (rec.type === "Channel") addChannel(rec);
      else if (rec.type === "Metadata") out.metadata[rec.name] = Object.fromEntries(rec.metadata);
      else if (rec.type === "Message") onMessage(rec);
    }
    out.truncated = !reader.done();
    out.leftoverBytes = reader.bytesRemaining();
  }
  return out;
}

const path = process.argv[2];
if (process.argv.length !== 3) {
  console.error("usage: node read_mcap.mjs FILE");
  process.exit(2);
}
try {
  console.log(JSON.stringify(await main(path)));
} catch (err) {
  console.error(`read_mcap.mjs: ${path}: ${err.message}`);
  process.exit(1);
}
