// A Foxglove WebSocket client we did not write: @foxglove/ws-protocol's FoxgloveClient over `ws`,
// offering only the published subprotocol foxglove.websocket.v1. It subscribes to every channel the
// server advertises, decodes every message with the schema the server sent (protobufjs for protobuf,
// JSON.parse for json) and prints, as one JSON line, what it saw per topic.
//
// usage: node client.mjs ws://127.0.0.1:PORT SECONDS [MIN_MESSAGES_PER_TOPIC]
import wsProtocol from "@foxglove/ws-protocol";
import protobuf from "protobufjs";
import descriptor from "protobufjs/ext/descriptor/index.js";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const [url, seconds = "20", minMessages = "1"] = process.argv.slice(2);
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const channels = new Map(); // subscription id -> {channel, decode}
const seen = {}; // topic -> {schemaName, encoding, messages, errors, last}
let serverInfo = null;
let error = null;

function decoderOf(channel) {
  if (channel.encoding === "json") {
    const text = new TextDecoder();
    return (data) => JSON.parse(text.decode(data));
  }
  if (channel.encoding === "protobuf") {
    const fds = descriptor.FileDescriptorSet.decode(Buffer.from(channel.schema, "base64"));
    const type = protobuf.Root.fromDescriptor(fds).lookupType(channel.schemaName);
    return (data) => {
      const object = type.toObject(type.decode(data), { longs: Number, enums: String, defaults: true });
      if (object.data instanceof Uint8Array || Buffer.isBuffer(object.data)) {
        const bytes = Buffer.from(object.data);
        object.data = { length: bytes.length, head: bytes.subarray(0, 4).toString("hex") };
      }
      return object;
    };
  }
  throw new Error(`no decoder for encoding ${channel.encoding}`);
}

function done() {
  const topics = Object.values(seen);
  return topics.length > 0 && topics.length === channels.size && topics.every((t) => t.messages >= Number(minMessages));
}

function finish(code) {
  process.stdout.write(JSON.stringify({ protocol: ws.protocol, serverInfo, error, topics: seen }) + "\n");
  try { client.close(); } catch { /* closing */ }
  process.exit(code);
}

client.on("open", () => {});
client.on("error", (e) => { error = String(e?.message ?? e); finish(1); });
client.on("serverInfo", (info) => { serverInfo = info; });
client.on("advertise", (advertised) => {
  for (const channel of advertised) {
    const id = client.subscribe(channel.id);
    channels.set(id, { channel, decode: decoderOf(channel) });
  }
});
client.on("message", ({ subscriptionId, data }) => {
  const entry = channels.get(subscriptionId);
  if (!entry) return;
  const { channel, decode } = entry;
  const topic = (seen[channel.topic] ??= { schemaName: channel.schemaName, encoding: channel.encoding, messages: 0, errors: 0, last: null });
  try {
    topic.last = decode(new Uint8Array(data.buffer, data.byteOffset, data.byteLength));
    topic.messages += 1;
  } catch (e) {
    topic.errors += 1;
    topic.lastError = String(e?.message ?? e);
  }
  if (done()) finish(0);
});
ws.on("unexpected-response", (_req, res) => { error = `HTTP ${res.statusCode} at the handshake`; finish(1); });
setTimeout(() => finish(2), Number(seconds) * 1000);
