// An independent client of the Foxglove WebSocket protocol (@foxglove/ws-protocol, the
// protocol's reference TypeScript implementation), run by tests/test_foxglove.py.
//
//   node foxglove_client.mjs URL COUNT TIMEOUT_S TOPIC...
//
// The server lets in only who holds its token: in URL (the ready line's ws://…/?token=…),
// or in $FOXGLOVE_TOKEN, sent as "Authorization: Bearer" (what a browser cannot do).
// $FOXGLOVE_ORIGIN, when set, is sent as the Origin a browser page would send.
// Connects to URL, subscribes to each TOPIC as soon as it is advertised and prints one
// JSON line per event: {"advertised": channel} for every channel the server advertises,
// {"topic", "logTime", "message"} for every message of a subscribed topic, its payload
// decoded as JSON. Exits 0 when every TOPIC has had COUNT messages, 1 after TIMEOUT_S
// seconds or on an error (the reason on stderr).
import wsProtocol from "@foxglove/ws-protocol"; // CommonJS: no named exports under Node
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const [url, countText, timeoutText, ...topics] = process.argv.slice(2);
const count = Number(countText);
const wanted = new Set(topics);
const got = new Map(topics.map((t) => [t, 0]));
const bySubscription = new Map();
const decoder = new TextDecoder();

// the foxglove-sdk server speaks the protocol's "foxglove.sdk.v1" version
const { FOXGLOVE_TOKEN: token, FOXGLOVE_ORIGIN: origin } = process.env;
const ws = new WebSocket(url, ["foxglove.sdk.v1", FoxgloveClient.SUPPORTED_SUBPROTOCOL], {
  headers: token ? { Authorization: `Bearer ${token}` } : {},
  ...(origin ? { origin } : {}),
});
const client = new FoxgloveClient({ ws });
const print = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");
const fail = (why) => {
  process.stderr.write(`foxglove_client: ${why}\n`);
  process.exit(1);
};

setTimeout(() => fail(`timed out; messages so far: ${JSON.stringify([...got])}`), Number(timeoutText) * 1000);

client.on("serverInfo", (info) => print({ serverInfo: info }));
client.on("advertise", (channels) => {
  for (const ch of channels) {
    print({ advertised: ch });
    if (wanted.has(ch.topic)) bySubscription.set(client.subscribe(ch.id), ch);
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const ch = bySubscription.get(subscriptionId);
  if (ch === undefined) return;
  const message = JSON.parse(decoder.decode(data));
  print({ topic: ch.topic, logTime: timestamp.toString(), message });
  got.set(ch.topic, got.get(ch.topic) + 1);
  if ([...got.values()].every((n) => n >= count)) {
    client.close();
    process.exit(0);
  }
});
client.on("error", (err) => fail(err?.message ?? String(err)));
client.on("close", () => fail("the server closed the connection"));
