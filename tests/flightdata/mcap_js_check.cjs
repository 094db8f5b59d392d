// Reads a flight log with Foxglove's official TypeScript MCAP library (@mcap/core), an implementation
// independent of the python one: indexed reader when the file is finalised, stream reader always.
// Usage: SKYCAP_MCAP_JS=<dir with node_modules/@mcap/{core,support,nodejs}> node mcap_js_check.cjs FILE
// Prints JSON {indexed: {topic: n} | null, stream: {topic: n}, streamDone: bool, encodings: [...]}.
const path = require("path");
const fs = require("fs");
const base = process.env.SKYCAP_MCAP_JS;
const req = (m) => require(require.resolve(m, { paths: [base] }));
const { McapIndexedReader, McapStreamReader } = req("@mcap/core");
const { FileHandleReadable } = req("@mcap/nodejs");
const { loadDecompressHandlers } = req("@mcap/support");

async function main() {
  const file = process.argv[2];
  const decompressHandlers = await loadDecompressHandlers();
  const out = { indexed: null, stream: {}, streamDone: false, encodings: [] };
  const bytes = fs.readFileSync(file);
  const stream = new McapStreamReader({ decompressHandlers, validateCrcs: true });
  stream.append(new Uint8Array(bytes.buffer, bytes.byteOffset, bytes.byteLength));
  const channels = new Map();
  for (;;) {
    let rec;
    try { rec = stream.nextRecord(); } catch (e) { out.streamError = String(e); break; }
    if (!rec) break;
    if (rec.type === "Channel") { channels.set(rec.id, rec); out.encodings.push(rec.messageEncoding); }
    if (rec.type === "Message") { const t = channels.get(rec.channelId).topic; out.stream[t] = (out.stream[t] || 0) + 1; }
  }
  out.streamDone = stream.done();
  out.encodings = [...new Set(out.encodings)];
  if (out.streamDone) {
    const fh = await fs.promises.open(file, "r");
    const reader = await McapIndexedReader.Initialize({ readable: new FileHandleReadable(fh), decompressHandlers });
    out.indexed = {};
    for await (const m of reader.readMessages()) {
      const t = reader.channelsById.get(m.channelId).topic;
      out.indexed[t] = (out.indexed[t] || 0) + 1;
    }
    out.profile = reader.header.profile;
    await fh.close();
  }
  console.log(JSON.stringify(out));
}
main().catch((e) => { console.error(String(e && e.stack || e)); process.exit(1); });
