// Reads an MCAP file with @mcap/core (Foxglove's TypeScript library) and prints one JSON line:
// what McapIndexedReader (through the summary and message indexes, as Foxglove opens large
// files) and McapStreamReader (record by record) see. Usage: node read_mcap.mjs FILE.mcap
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { open, readFile } from "node:fs/promises";

const path = process.argv[2];
const fh = await open(path, "r");
const readable = {
  size: async () => BigInt((await fh.stat()).size),
  read: async (offset, size) => {
    const buf = Buffer.alloc(Number(size));
    const { bytesRead } = await fh.read(buf, 0, Number(size), Number(offset));
    if (bytesRead !== Number(size)) throw new Error(`short read at ${offset}`);
    return new Uint8Array(buf.buffer, buf.byteOffset, buf.byteLength);
  },
};
const decoder = new TextDecoder();
const reader = await McapIndexedReader.Initialize({ readable });
const topics = {};
const samples = [];
let messages = 0;
let last = -1n;
let ordered = true;
for await (const msg of reader.readMessages({ validateCrcs: true })) {
  const topic = reader.channelsById.get(msg.channelId).topic;
  topics[topic] = (topics[topic] ?? 0) + 1;
  messages += 1;
  if (msg.logTime < last) ordered = false;
  last = msg.logTime;
  if (topic === "/run/sample") samples.push(JSON.parse(decoder.decode(msg.data)).config_id);
}
const metadata = [];
for await (const m of reader.readMetadata()) metadata.push(m.name);
const attachments = [];
for await (const a of reader.readAttachments({ validateCrcs: true })) attachments.push(a.name);
await fh.close();

const stream = new McapStreamReader({ validateCrcs: true });
stream.append(await readFile(path));
let streamMessages = 0;
let footer = false;
for (let rec; (rec = stream.nextRecord()); ) {
  if (rec.type === "Message") streamMessages += 1;
  if (rec.type === "Footer") footer = true;
}
console.log(JSON.stringify({
  indexed: {
    messages, topics, samples, ordered, metadata, attachments,
    chunks: reader.chunkIndexes.length,
    statistics_messages: reader.statistics ? Number(reader.statistics.messageCount) : null,
  },
  stream: { messages: streamMessages, footer, done: stream.done() },
}));
