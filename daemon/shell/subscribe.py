"""``cellbridge sub``: print what the daemon publishes, one JSON line per message.

For looking at a live skin from a shell (``cellbridge sub contact | jq .payload``)
and for scripts in languages without a ZeroMQ binding. Generic on purpose: it
prints whatever keys a payload holds, so it needs no change when topics grow.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, TextIO

import msgpack
import zmq
from cellbridge.daemon.ops.security import apply_client, endpoint_error
from cellbridge.daemon.shell.publisher import TOPICS

DEFAULT_PUB = "tcp://127.0.0.1:5560"
#: Seconds without a first message before `sub` says so (and waits on).
QUIET_S = 5.0


def jsonable(obj: Any) -> Any:
    """A msgpack value as JSON data: bytes as hex, map keys as strings, NaN/inf as null."""
    if isinstance(obj, dict):
        return {k if isinstance(k, str) else json.dumps(jsonable(k)): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return bytes(obj).hex()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, msgpack.Timestamp):
        return obj.to_unix()
    if isinstance(obj, msgpack.ExtType):
        return {"ext": obj.code, "data": obj.data.hex()}
    return obj


def message_to_json(parts: list[bytes]) -> dict[str, Any]:
    """One published message ``[topic, msgpack payload]`` as a JSON-able dict.

    A message of another shape, or a payload that is not msgpack, is kept with an
    ``error`` key and its raw bytes: shown, never dropped.
    """
    topic = parts[0].decode("utf-8", "replace") if parts else ""
    if len(parts) != 2:
        return {"topic": topic, "error": f"expected 2 frames [topic, payload], got {len(parts)}",
                "raw": [p.hex() for p in parts[1:]]}
    try:
        payload = msgpack.unpackb(parts[1], raw=False, strict_map_key=False)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as exc:
        return {"topic": topic, "error": f"payload is not msgpack: {exc}", "raw": parts[1].hex()}
    return {"topic": topic, "payload": jsonable(payload)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Subscribe to the daemon's PUB socket and print each message as one JSON line\n"
        '{"topic": ..., "payload": {...}} (bytes as hex, NaN as null). A message that is\n'
        'not [topic, msgpack] is printed with an "error" key instead of "payload".\n'
        "Counters go to stderr at exit. Topics: contact, element, raw, health, topology, serial.\n"
        "When nothing comes in the first 5 s, not even the daemon's health, a line on stderr\n"
        "says so (no daemon there?); it waits on.\n\n"
        "examples:\n"
        "  cellbridge sub                        # everything\n"
        "  cellbridge sub contact | jq .payload  # contacts only\n"
        "  cellbridge sub health --count 1       # one health message, then exit\n"
        "  cellbridge sub --endpoint tcp://robot:5560 \\\n"
        "      --server-key server.key --client-key me.key_secret   # a CURVE daemon"
    )
    parser.add_argument("topics", nargs="*", metavar="TOPIC",
                        help="topic prefix to receive (ZeroMQ prefix match; default: all topics)")
    parser.add_argument("--endpoint", default=DEFAULT_PUB, help=f"daemon's PUB endpoint (default: {DEFAULT_PUB})")
    parser.add_argument("--count", type=int, default=None, metavar="N",
                        help="exit after N messages (default: run until Ctrl-C)")
    parser.add_argument("--timeout", type=float, default=0.0, metavar="SECONDS",
                        help="exit with status 1 when no message arrives for this long (default: wait forever)")
    parser.add_argument("--server-key", type=Path, metavar="FILE",
                        help="daemon's public key file (NAME.key) when it runs with CURVE")
    parser.add_argument("--client-key", type=Path, metavar="FILE",
                        help="this client's secret key file (NAME.key_secret); "
                             "its NAME.key must be allowed by the daemon")


def run(args: argparse.Namespace) -> int:
    if (args.server_key is None) != (args.client_key is None):
        print("cellbridge sub: --server-key and --client-key go together (CURVE needs both)", file=sys.stderr)
        return 2
    if args.count is not None and args.count < 1:  # --count 0 ran until Ctrl-C, as if left out
        print(f"cellbridge sub: --count must be at least 1, got {args.count} (leave it out to run until Ctrl-C)",
              file=sys.stderr)
        return 2
    if args.timeout < 0:
        print("cellbridge sub: --timeout must not be negative", file=sys.stderr)
        return 2
    # a prefix no topic starts with ('helth', 'contacts') would wait forever without a word
    unknown = [t for t in args.topics if not any(topic.startswith(t) for topic in TOPICS)]
    if unknown:
        print(f"cellbridge sub: no topic starts with {unknown[0]!r} (topics: {', '.join(TOPICS)})", file=sys.stderr)
        return 2
    context = zmq.Context()
    sock = context.socket(zmq.SUB)
    sock.linger = 0
    counters = {"received": 0, "malformed": 0}
    try:
        if args.server_key is not None:
            apply_client(sock, args.server_key, args.client_key)
        for topic in args.topics or [""]:
            sock.subscribe(topic)
        sock.connect(args.endpoint)
        return _print_messages(sock, args, counters, sys.stdout, health_probe(context, args))
    except ValueError as exc:  # bad key file
        print(f"cellbridge sub: {exc}", file=sys.stderr)
        return 2
    except zmq.ZMQError as exc:
        print(f"cellbridge sub: {endpoint_error(args.endpoint, exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:  # the reader went away (| head): that is the end, not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    finally:
        print(json.dumps(counters), file=sys.stderr)
        sock.close()
        context.term()


def health_probe(context: zmq.Context, args: argparse.Namespace) -> zmq.Socket:
    """A SUB socket on ``args.endpoint``'s ``health`` alone (with ``args``' CURVE keys): a
    running daemon publishes it every second, so it tells a daemon that is not there from
    one whose other topics are quiet (an untouched skin publishes no contact)."""
    probe = context.socket(zmq.SUB)
    probe.linger = 0
    if args.server_key is not None:
        apply_client(probe, args.server_key, args.client_key)
    probe.subscribe(b"health")
    probe.connect(args.endpoint)
    return probe


def not_there(command: str, args: argparse.Namespace, sock: zmq.Socket, probe: zmq.Socket, then: str) -> bool:
    """Wait up to :data:`QUIET_S` for a first message on ``sock``; when neither it nor the
    ``health`` ``probe`` got one, say on stderr that the daemon may not be there (connecting
    never fails: a daemon that is not there says nothing), ending with ``then``. Whether it
    was said. Closes ``probe``."""
    try:
        if sock.poll(int(QUIET_S * 1000)) or probe.poll(0):
            return False
    finally:
        probe.close()
    print(f"cellbridge {command}: nothing in {QUIET_S:g} s from {args.endpoint}, not even its health: is the "
          "daemon running" + (" and does it allow this client's key" if args.server_key is not None else "")
          + f"? ({then})", file=sys.stderr, flush=True)
    return True


def _print_messages(sock: zmq.Socket, args: argparse.Namespace, counters: dict[str, int], out: TextIO,
                    probe: zmq.Socket) -> int:
    timeout_ms = int(args.timeout * 1000) if args.timeout else None
    wait_ms = timeout_ms
    if args.timeout and args.timeout <= QUIET_S:  # (it gives up before it would say so)
        probe.close()
    else:
        start = time.monotonic()
        not_there("sub", args, sock, probe, "waiting on; Ctrl-C stops, --timeout S gives up")
        if timeout_ms is not None:  # the first message's wait includes this one
            wait_ms = max(0, timeout_ms - int((time.monotonic() - start) * 1000))
    while args.count is None or counters["received"] < args.count:
        if not sock.poll(wait_ms):
            print(f"cellbridge sub: no message for {args.timeout:g} s on {args.endpoint}", file=sys.stderr)
            return 1
        wait_ms = timeout_ms
        line = message_to_json(sock.recv_multipart())
        counters["received"] += 1
        counters["malformed"] += "error" in line
        out.write(json.dumps(line) + "\n")
        out.flush()
    return 0
