#!/usr/bin/env node
// Subscribe to the cellbridge daemon and print each message as one JSON line:
//   {"topic":"contact","payload":{...}}
//
// Needs Node.js >= 18 and two npm packages: npm install   (zeromq, @msgpack/msgpack)
// Run:   node subscriber.js [-e ENDPOINT] [-n COUNT] [-s SERVER.key -k CLIENT.key_secret] [TOPIC...]
//
// -s/-k make it a CURVE client: the daemon's public key file and this client's secret
// key file, both written by `cellbridge keys gen` (the client's .key must be allowed).
"use strict";

const fs = require("node:fs");
const { parseArgs } = require("node:util");
const zmq = require("zeromq");
const { decode } = require("@msgpack/msgpack");

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
  const sock = new zmq.Subscriber({ linger: 0 });
  if (values["server-key"] && values["client-key"]) {
    sock.curveServerKey = readKey(values["server-key"], "public-key");
    sock.curvePublicKey = readKey(values["client-key"], "public-key");
    sock.curveSecretKey = readKey(values["client-key"], "secret-key");
  }
  sock.connect(values.endpoint);
  if (positionals.length === 0) sock.subscribe(); // every topic
  else sock.subscribe(...positionals); // prefix match

  const count = Number(values.count);
  let received = 0;
  for await (const [topic, payload] of sock) {
    const message = { topic: topic.toString(), payload: decode(payload) }; // every payload has "v" and "t_host"
    process.stdout.write(JSON.stringify(message, replacer) + "\n");
    if (count && ++received >= count) break;
  }
  sock.close();
}

main().catch((err) => {
  console.error(err.message);
  process.exit(2);
});
