#!/usr/bin/env python3
"""Subscribe to the cellbridge daemon and print each message as one JSON line.

Needs only pyzmq and msgpack (pip install pyzmq msgpack), not cellbridge.

    python3 subscriber.py                         # every topic from tcp://127.0.0.1:5560
    python3 subscriber.py contact health -n 10    # two topics, ten messages
    python3 subscriber.py -e tcp://robot:5560 -s server.key -k me.key_secret   # CURVE

-s/-k: the daemon's public key file and this client's secret key file, both
written by `cellbridge keys gen`; the client's .key must be allowed by the daemon.

Nothing in 5 s, not even the daemon's health (no daemon there, a key it does not allow),
is said on stderr, and it waits on. A message it cannot decode prints with "error" instead of "payload". Ctrl-C or a
reader that went away (| head) ends it with status 0; bad arguments with a sentence, 2.
"""

import argparse
import json
import math
import os
import sys

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
    if isinstance(k, bytes):  # as a bytes value prints: hex
        return k.hex()
    return k


#: Seconds without a message before the subscriber says so (and waits on).
QUIET_S = 5.0


def count_arg(text):
    """-n: a whole number, 0 for no limit."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be 0 (no limit) or more, got {n}")
    return n


def main() -> int:
    parser = argparse.ArgumentParser(description="Print the cellbridge daemon's messages as JSON lines.")
    parser.add_argument("topics", nargs="*", help="topic prefixes (default: all)")
    parser.add_argument("-e", "--endpoint", default="tcp://127.0.0.1:5560")
    parser.add_argument("-n", "--count", type=count_arg, default=0,
                        help="stop after N messages (default 0: until Ctrl-C)")
    parser.add_argument("-s", "--server-key", help="daemon's public key file (CURVE)")
    parser.add_argument("-k", "--client-key", help="this client's secret key file (CURVE)")
    args = parser.parse_args()
    if (args.server_key is None) != (args.client_key is None):
        parser.error("CURVE needs both -s SERVER.key and -k CLIENT.key_secret")

    context = zmq.Context.instance()
    sock, probe = context.socket(zmq.SUB), context.socket(zmq.SUB)  # probe: the daemon's health alone
    try:
        for s in (sock, probe):
            s.linger = 0
        if args.server_key:
            server_public, _ = zmq.auth.load_certificate(args.server_key)
            public, secret = zmq.auth.load_certificate(args.client_key)
            if secret is None:
                raise ValueError(f"{args.client_key}: no secret key in it (-k takes the NAME.key_secret file)")
            for s in (sock, probe):
                s.curve_serverkey, s.curve_publickey, s.curve_secretkey = server_public, public, secret
        for topic in args.topics or [""]:
            sock.subscribe(topic)
        probe.subscribe("health")
        for s in (sock, probe):
            s.connect(args.endpoint)
    except (OSError, ValueError) as exc:  # a key file missing or not a key
        print(f"subscriber: {exc}", file=sys.stderr)
        return 2
    except zmq.ZMQError as exc:  # an endpoint ZeroMQ cannot connect to ("robot:5560": no tcp://)
        print(f"subscriber: {args.endpoint}: {exc}", file=sys.stderr)
        return 2

    received = 0
    try:
        # Connecting never fails: a daemon that is not there says nothing. A running one
        # publishes its health every second, even while the topics asked for are quiet.
        if not sock.poll(QUIET_S * 1000) and not probe.poll(0):
            print(f"subscriber: nothing from {args.endpoint} in {QUIET_S:g} s, not even its health: is the "
                  "daemon running" + (" and does it allow this client's key?" if args.server_key else "?")
                  + " (waiting on; Ctrl-C stops)", file=sys.stderr, flush=True)
        probe.close()
        while not args.count or received < args.count:
            parts = sock.recv_multipart()
            line = {"topic": parts[0].decode(errors="replace")}
            try:
                if len(parts) != 2:
                    raise ValueError("expected 2 frames [topic, payload]")
                line["payload"] = plain(msgpack.unpackb(parts[1], strict_map_key=False))  # "v", "t_host", ...
            except ValueError as exc:  # (msgpack's errors are ValueErrors): said on its line, and read on
                line["error"] = str(exc) if len(parts) != 2 else "payload is not msgpack"
            print(json.dumps(line, default=bytes.hex, allow_nan=False), flush=True)
            received += 1
    except KeyboardInterrupt:  # Ctrl-C: the end, not an error
        pass
    except BrokenPipeError:  # the reader went away (| head): the end of the output
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # (no second error at exit)
    finally:
        sock.close()
        probe.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
