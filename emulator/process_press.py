"""``cellbridge press``: press on a running emulated skin (sends one contact to the world)."""

from __future__ import annotations

import argparse
import sys

import msgpack
import zmq

from cellbridge.emulator.realtime import add_endpoint_arguments, endpoints


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
    parser.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the world (default 3)")
    add_endpoint_arguments(parser)


def run(args: argparse.Namespace) -> int:
    req = {"duration": args.duration, "position": [args.x, args.y], "force": args.force,
           "diameter": args.diameter}
    if args.velocity:
        req["velocity"] = list(args.velocity)
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoints(args).control)
    try:
        sock.send(msgpack.packb(req))
        if not sock.poll(int(args.timeout * 1000)):
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
