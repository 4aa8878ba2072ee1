#!/usr/bin/env python3
"""Subscribe to the cellbridge daemon and print each message as one JSON line.

Needs only pyzmq and msgpack (pip install pyzmq msgpack), not cellbridge.

    python3 subscriber.py                         # every topic from tcp://127.0.0.1:5560
    python3 subscriber.py contact health -n 10    # two topics, ten messages
    python3 subscriber.py -e tcp://robot:5560 -s server.key -k me.key_secret   # CURVE

-s/-k: the daemon's public key file and this client's secret key file, both
written by `cellbridge keys gen`; the client's .key must be allowed by the daemon.
"""

import argparse
import json
import math

import msgpack
import zmq
import zmq.auth


def plain(value):
    """``value`` with every NaN and infinity as None: JSON has neither (an element's force
    is NaN where it is not valid, a σ infinite along an axis the readings leave open)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        if set(map(type, value)) <= {float, int}:  # an array of numbers: one pass, no call per item
            return [v if v - v == 0 else None for v in value]  # (inf - inf and NaN - NaN are NaN)
        return [plain(v) for v in value]
    return value


def key(k):
    """A map key as JSON writes it: a JSON key is a string, so a NaN or infinite one is
    its name (json.dumps would refuse it, and this subscriber would stop)."""
    if isinstance(k, float) and not math.isfinite(k):
        return "NaN" if k != k else "Infinity" if k > 0 else "-Infinity"
    return k


def main() -> None:
    parser = argparse.ArgumentParser(description="Print the cellbridge daemon's messages as JSON lines.")
    parser.add_argument("topics", nargs="*", help="topic prefixes (default: all)")
    parser.add_argument("-e", "--endpoint", default="tcp://127.0.0.1:5560")
    parser.add_argument("-n", "--count", type=int, default=0, help="stop after N messages")
    parser.add_argument("-s", "--server-key", help="daemon's public key file (CURVE)")
    parser.add_argument("-k", "--client-key", help="this client's secret key file (CURVE)")
    args = parser.parse_args()

    sock = zmq.Context.instance().socket(zmq.SUB)
    if args.server_key and args.client_key:
        sock.curve_serverkey, _ = zmq.auth.load_certificate(args.server_key)
        sock.curve_publickey, sock.curve_secretkey = zmq.auth.load_certificate(args.client_key)
    for topic in args.topics or [""]:
        sock.subscribe(topic)
    sock.connect(args.endpoint)

    received = 0
    while not args.count or received < args.count:
        topic, payload = sock.recv_multipart()
        message = msgpack.unpackb(payload, strict_map_key=False)  # every payload carries "v" and "t_host"
        print(json.dumps({"topic": topic.decode(), "payload": plain(message)}, default=bytes.hex, allow_nan=False),
              flush=True)
        received += 1
    sock.close(linger=0)


if __name__ == "__main__":
    main()
