"""``cellbridge world`` and ``cellbridge press``: stimuli for bridges running in real time.

The world process owns the list of contacts (from a scenario file, plus presses
injected live) and publishes all of it on a PUB socket whenever it changes and every
half second, so a bridge that (re)connects late has it within 0.5 s. Contact times
on the wire are absolute host monotonic seconds, the bridges' clock. A contact stays
in the list for ``KEEP_ENDED_S`` after it ends: bridges compute samples lazily (up to a
DATA frame's latency after their gate), and a sample taken during a press must see it. ``press`` sends
one contact to the world's control socket (REQ/REP, :mod:`.process_press`).
"""

from __future__ import annotations

import argparse
import sys
import time

import msgpack
import zmq
from cellbridge.emulator.mesh.mesh import Mesh, MeshError, load_mesh
from cellbridge.emulator.realtime.realtime import (
    StopFlag,
    add_endpoint_arguments,
    add_ready_argument,
    endpoints,
    signal_ready,
)
from cellbridge.emulator.world.world import (
    Contact,
    ScenarioError,
    check_on_skin,
    contact_from_mapping,
    contact_problem,
    load_scenario,
)

REPUBLISH_S = 0.5
KEEP_ENDED_S = 2.0  #: well beyond a bridge's lazy-sampling horizon (a frame's max latency, 50 ms)


def encode_contacts(contacts: list[Contact]) -> bytes:
    return msgpack.packb([[c.start, c.duration, c.x, c.y, c.force, c.diameter, c.vx, c.vy] for c in contacts])


def decode_contacts(data: bytes) -> list[Contact] | None:
    """The contacts, or None for a malformed message (ignored, never fatal to a bridge,
    and never taken for "no contacts", which would release every press)."""
    try:
        contacts = [Contact(*map(float, row)) for row in msgpack.unpackb(data)]
    except Exception:
        return None
    # values no world publishes (NaN, inf, a negative diameter, a track that overflows)
    # would stop the bridge at its next sample: the whole message is malformed
    return None if any(contact_problem(c) for c in contacts) else contacts


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Publish stimuli (contacts) to the bridge processes of a running mesh: "
                          "the scenario file's contacts, timed from this process's start, and any "
                          "'cellbridge press'.")
    parser.add_argument("--mesh", help="mesh file: a press that touches no element of it is refused")
    parser.add_argument("--scenario", help="TOML file of [[contact]] stimuli")
    add_endpoint_arguments(parser)
    add_ready_argument(parser)


def serve(contacts: list[Contact], pub_ep: str, ctl_ep: str, stop: StopFlag, mesh: Mesh | None = None,
          ready_fd: int | None = None) -> None:
    """Publish and take presses until ``stop``; zmq.ZMQError when an endpoint cannot be bound."""
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    ctl = ctx.socket(zmq.REP)
    ctl.setsockopt(zmq.LINGER, 0)
    last = 0.0
    try:
        pub.bind(pub_ep)
        ctl.bind(ctl_ep)
        signal_ready(ready_fd)
        while not stop.stopped:
            if ctl.poll(100):
                try:
                    req = msgpack.unpackb(ctl.recv())
                    now = time.monotonic()
                    c = contact_from_mapping({"start": 0.0, **req}, "press")  # start: from now, checked
                    if mesh is not None:
                        check_on_skin(mesh, c, "press")
                    contacts.append(Contact(now + c.start, c.duration, c.x, c.y,
                                            c.force, c.diameter, c.vx, c.vy))
                    ctl.send(msgpack.packb({"ok": True, "start": contacts[-1].start}))
                    last = 0.0
                except (ScenarioError, ValueError, TypeError, msgpack.UnpackException) as exc:
                    ctl.send(msgpack.packb({"ok": False, "error": str(exc)}))
            now = time.monotonic()
            if now - last >= REPUBLISH_S:
                contacts[:] = [c for c in contacts if c.start + c.duration > now - KEEP_ENDED_S]
                pub.send(encode_contacts(contacts))
                last = now
    finally:
        pub.close()
        ctl.close()


def run(args: argparse.Namespace) -> int:
    try:
        mesh = load_mesh(args.mesh) if args.mesh else None
        scenario = load_scenario(args.scenario) if args.scenario else []
        if mesh is not None:
            for i, c in enumerate(scenario):
                check_on_skin(mesh, c, f"{args.scenario}: contact[{i}]")
    except (ScenarioError, MeshError) as exc:
        print(f"cellbridge world: {exc}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    contacts = [Contact(t0 + c.start, c.duration, c.x, c.y, c.force, c.diameter, c.vx, c.vy) for c in scenario]
    ep = endpoints(args)
    try:
        serve(contacts, ep.world, ep.control, StopFlag(), mesh, args.ready_fd)
    except zmq.ZMQError as exc:
        print(f"cellbridge world: cannot bind {ep.world} and {ep.control}: {exc}", file=sys.stderr)
        return 1
    return 0
