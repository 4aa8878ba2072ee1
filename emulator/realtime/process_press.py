"""``cellbridge press``: press on a running emulated skin (sends one contact to the world)."""

from __future__ import annotations

import argparse
import math
import sys

import msgpack
import zmq
from cellbridge.emulator.realtime.realtime import add_endpoint_arguments, endpoints

#: Longest --timeout: a day (zmq's poll takes milliseconds as a C int; beyond, it overflowed).
MAX_TIMEOUT_S = 86400.0


def timeout_arg(text: str) -> float:
    """argparse type of ``--timeout``: finite seconds in (0, MAX_TIMEOUT_S] (a negative one
    meant 'wait for ever' to zmq, NaN or 1e20 a traceback)."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and 0 < v <= MAX_TIMEOUT_S):
        raise argparse.ArgumentTypeError(f"expected seconds > 0 and <= {MAX_TIMEOUT_S:g}, got {text!r}")
    return v


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Press on a running emulated skin ('cellbridge mesh up'): a disk of the "
                          "given force and diameter centred at X, Y (metres, the mesh file's element "
                          "positions) for DURATION seconds, starting now.")
    parser.add_argument("x", type=float, help="centre x (m)")
    parser.add_argument("y", type=float, help="centre y (m)")
    parser.add_argument("--force", type=float, default=2.0, help="force in newtons (default 2)")
    parser.add_argument("--diameter", type=float, default=0.02, help="contact diameter in metres (default 0.02)")
    parser.add_argument("--duration", type=float, default=1.0, help="seconds (default 1)")
    parser.add_argument("--velocity", type=float, nargs=2, default=None, metavar=("VX", "VY"),
                        help="optional straight-line motion in m/s")
    parser.add_argument("--timeout", type=timeout_arg, default=3.0, metavar="SECONDS",
                        help=f"seconds to wait for the world's answer, > 0 and <= {MAX_TIMEOUT_S:g} (default 3)")
    add_endpoint_arguments(parser)


def run(args: argparse.Namespace) -> int:
    req = {"duration": args.duration, "position": [args.x, args.y], "force": args.force,
           "diameter": args.diameter}
    if args.velocity:
        req["velocity"] = list(args.velocity)
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
    sock = ctx.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoints(args).control)
    try:
        sock.send(msgpack.packb(req))
        if not sock.poll(max(1, round(args.timeout * 1000))):
            print(f"cellbridge press: no world process answered at {endpoints(args).control} "
                  f"(is 'cellbridge mesh up' running with this --base-port?)", file=sys.stderr)
            return 1
        answer = msgpack.unpackb(sock.recv())
    finally:
        sock.close()
    if not answer.get("ok"):
        print(f"cellbridge press: {answer.get('error')}", file=sys.stderr)
        return 2
    print(f"pressed {args.force} N, {args.diameter * 1000:.1f} mm at ({args.x}, {args.y}) for {args.duration} s")
    return 0
