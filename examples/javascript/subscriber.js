#!/usr/bin/env node
// Subscribe to the cellbridge daemon and print each message as one JSON line:
//   {"topic":"contact","payload":{...}}
//
// Needs Node.js >= 18 and two npm packages: npm install   (zeromq, @msgpack/msgpack)
// Run:   node subscriber.js [-e ENDPOINT] [-n COUNT] [-s SERVER.key -k CLIENT.key_secret] [TOPIC...]
//
// -s/-k make it a CURVE client: the daemon's public key file and this client's secret
// key file, both written by `cellbridge keys gen` (the client's .key must be allowed).
//
// When nothing comes in the first 5 s, not even the daemon's health (published every
// second), a line on stderr says so and it waits on. Ctrl-C ends it, exit 0.
"use strict";

const fs = require("node:fs");
const { parseArgs } = require("node:util");
const zmq = require("zeromq");
const { decode } = require("@msgpack/msgpack");

const QUIET_MS = 5000; // ms without a message before it says so (and waits on)

// The Z85 key after `name = "` in a ZeroMQ certificate file.
function readKey(path, name) {
  const match = fs.readFileSync(path, "utf8").match(new RegExp(`${name}\\s*=\\s*"(.{40})"`));
  if (!match) throw new Error(`${path}: no ${name} in this file`);
  return match[1];
}

// JSON.stringify with bytes as hex (as `cellbridge sub` prints them) and 64-bit integers as numbers.
// this[key] is the value before Buffer's own toJSON turned it into {type, data}.
function replacer(key, value) {
  const raw = this[key];
  if (raw instanceof Uint8Array) return Buffer.from(raw).toString("hex");
  if (typeof value === "bigint") return Number(value);
  return value;
}

async function main() {
  const { values, positionals } = parseArgs({
    allowPositionals: true,
    options: {
      endpoint: { type: "string", short: "e", default: "tcp://127.0.0.1:5560" },
      count: { type: "string", short: "n", default: "0" },
      "server-key": { type: "string", short: "s" },
      "client-key": { type: "string", short: "k" },
    },
  });
  process.on("SIGINT", () => process.exit(0)); // Ctrl-C: the end, not an error
  const sock = new zmq.Subscriber({ linger: 0 });
  const probe = new zmq.Subscriber({ linger: 0 }); // the daemon's health alone: is a daemon there?
  const curve = Boolean(values["server-key"] && values["client-key"]);
  if (curve) {
    for (const s of [sock, probe]) {
      s.curveServerKey = readKey(values["server-key"], "public-key");
      s.curvePublicKey = readKey(values["client-key"], "public-key");
      s.curveSecretKey = readKey(values["client-key"], "secret-key");
    }
  }
  sock.connect(values.endpoint);
  probe.connect(values.endpoint);
  if (positionals.length === 0) sock.subscribe(); // every topic
  else sock.subscribe(...positionals); // prefix match
  probe.subscribe("health");

  // Connecting never fails: a daemon that is not there says nothing. A running one
  // publishes its health every second, even while the topics asked for are quiet.
  let heard = false;
  probe.receive().then(() => { heard = true; }, () => {}); // (rejected when closed)
  const quiet = setTimeout(() => {
    if (!heard) {
      console.error(`subscriber: nothing from ${values.endpoint} in ${QUIET_MS / 1000} s, not even its health: ` +
        `is the daemon running${curve ? " and does it allow this client's key?" : "?"} (waiting on; Ctrl-C stops)`);
    }
    probe.close();
  }, QUIET_MS);

  const count = Number(values.count);
  let received = 0;
  for await (const [topic, payload] of sock) {
    heard = true;
    const message = { topic: topic.toString(), payload: decode(payload) }; // every payload has "v" and "t_host"
    process.stdout.write(JSON.stringify(message, replacer) + "\n");
    if (count && ++received >= count) break;
  }
  clearTimeout(quiet);
  if (!probe.closed) probe.close();
  sock.close();
}

main().catch((err) => {
  console.error(err.message);
  process.exit(2);
});
