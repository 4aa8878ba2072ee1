"""``cellbridge bridge``: one bridge (chip + firmware) as a real-time process.

The chip's cycle counter is the host's monotonic clock at 50 MHz. The loop sleeps in
``poll`` until the firmware's next timer or until a message arrives (the medium's
carrier reports and deliveries, the world's contacts, the host's bytes on a gateway's
serial line); nothing busy-waits. Samples are computed lazily, when their DATA frame
(or the decision that none is due) is, with the capacitance at their gate: the bridge
wakes once per frame, not once per gate, and the cell sees the same frames at the same
times. A sample computed at a wake that came more than one gate (2 ms) after the
firmware asked for it counts as ``late_gates``, the measure of whether a machine
holds the mesh in real time; more than a whole sampling period after (the bridge
fell behind), also as ``behind_gates``. SIGUSR1 marks a moment (``late_gates_since_mark`` and
``samples_since_mark`` count from it: a benchmark marks the end of start-up). On
SIGTERM/SIGINT it prints its counters as JSON on stderr and exits.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys

import zmq

from cellbridge.emulator.commands import Settings
from cellbridge.emulator.firmware import Firmware, FirmwareConfig
from cellbridge.emulator.gateway_port import GatewayPort, open_pty
from cellbridge.emulator.mesh import MeshError, load_mesh
from cellbridge.emulator.medium_wire import (
    CARRIER, EVENTS, NOBLOCK, POLLIN, RX, WANT_OFF, WANT_ON, decode_carrier, decode_rx, encode_tx,
)
from cellbridge.emulator.process_world import decode_contacts
from cellbridge.emulator.transceiver import TransceiverConfig
from cellbridge.emulator.realtime import (
    CLOCK_HZ, REPORTING_HELP, StopFlag, add_endpoint_arguments, endpoints, now_tick, rate_arg,
    reporting_arg,
)
from cellbridge.emulator.virtual import default_chip
from cellbridge.emulator.world import World


ACK_SLACK = 10 * CLOCK_HZ // 1000  # a LINK_ACK crosses two processes and the medium: allow 10 ms


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Run one emulated bridge in real time. It talks to the other bridges "
                          "through 'cellbridge medium' and reads stimuli from 'cellbridge world'; "
                          "a gateway also serves its serial line on a pseudo-terminal (printed "
                          "as 'gateway <id> <device>') and, with --tcp, on a TCP port.")
    parser.add_argument("--mesh", required=True, help="mesh file (TOML)")
    parser.add_argument("--id", type=int, required=True, help="this bridge's id in the mesh file")
    parser.add_argument("--seed", type=int, default=0, help="seed of the chip noise and backoff (default 0)")
    parser.add_argument("--rate", type=rate_arg, default=100,
                        help="sampling rate in Hz at power-on, 1..250 (default 100)")
    parser.add_argument("--reporting", type=reporting_arg, default="periodic", metavar="MODE",
                        help=REPORTING_HELP)
    parser.add_argument("--tcp", type=int, default=None, metavar="PORT",
                        help="gateway: also serve the serial stream on 127.0.0.1:PORT (0 = any free port)")
    parser.add_argument("--pty-fd", type=int, default=None, help=argparse.SUPPRESS)  # from mesh up
    add_endpoint_arguments(parser)


def run(args: argparse.Namespace) -> int:
    mark = {"late": 0, "behind": 0, "samples": 0, "set": False, "asked": False}
    signal.signal(signal.SIGUSR1, lambda *_: mark.update(asked=True))  # before anything slow
    try:
        mesh = load_mesh(args.mesh)
        br = mesh.bridge(args.id)
    except MeshError as exc:
        print(f"cellbridge bridge: {exc}", file=sys.stderr)
        return 2
    ep = endpoints(args)
    stop = StopFlag()
    ctx = zmq.Context.instance()
    medium = ctx.socket(zmq.DEALER)
    medium.setsockopt(zmq.IDENTITY, str(br.id).encode())
    medium.setsockopt(zmq.LINGER, 0)
    medium.setsockopt(zmq.SNDHWM, 1000)
    medium.setsockopt(zmq.IMMEDIATE, 1)  # no medium: a transmission is lost now, not replayed later
    medium.connect(ep.medium)
    stimuli = ctx.socket(zmq.SUB)
    stimuli.setsockopt(zmq.LINGER, 0)
    stimuli.setsockopt(zmq.SUBSCRIBE, b"")
    stimuli.connect(ep.world)

    world = World(mesh, bridges=[br.id])
    fw = Firmware(FirmwareConfig(br.id, br.cells, br.gateway, br.position, mesh.side,
                                 settings=Settings(rate_hz=args.rate, reporting=args.reporting), ack_slack=ACK_SLACK,
                                 transceiver=TransceiverConfig(bit_cycles=CLOCK_HZ // mesh.bitrate),
                                 lazy_sampling=True),
                  default_chip(br.id, args.seed), world.sense_for(br.id), args.seed, now_tick())
    port = None
    if br.gateway:
        master = args.pty_fd
        if master is None:
            master, _slave, device = open_pty()  # keep the slave open: no EIO while nobody reads
            print(f"gateway {br.id} {device}", flush=True)
        tcp = args.tcp if args.tcp is not None else br.tcp
        port = GatewayPort(master, tcp)
        if port.tcp_port is not None:
            print(f"gateway {br.id} socket://127.0.0.1:{port.tcp_port}", flush=True)

    poller = zmq.Poller()
    poller.register(medium, zmq.POLLIN)
    poller.register(stimuli, zmq.POLLIN)
    registered: set[int] = set()
    late = behind = 0
    wanting, told = False, 0.0  # contention state last reported to the medium, and when
    try:
        while not stop.stopped:
            if port is not None:
                fds = set(port.fds())
                for fd in fds - registered:
                    poller.register(fd, zmq.POLLIN)
                for fd in registered - fds:
                    poller.unregister(fd)
                registered = fds
            due = fw.sampler.next_tick  # when the samples computed at the next wake were wanted
            wait_ms = max(0, math.ceil((fw.next_tick - now_tick()) * 1000 / CLOCK_HZ))  # never spin
            ready = dict(poller.poll(min(wait_ms, 200)))
            tick = now_tick()
            taken = fw.counters["samples"]
            if mark["asked"]:
                mark.update(late=late, behind=behind, samples=fw.counters["samples"], set=True, asked=False)
            if medium in ready:
                while medium.getsockopt(EVENTS) & POLLIN:  # drained without raising zmq.Again each time
                    msg = medium.recv(NOBLOCK)
                    kind = msg[0] if msg else -1
                    if kind == RX and (rx := decode_rx(msg)) is not None:
                        fw.receive(rx[1], tick, rx[0])
                    elif kind == CARRIER and (cs := decode_carrier(msg)) is not None:
                        fw.carrier(*cs)
            if stimuli in ready:
                while stimuli.getsockopt(EVENTS) & POLLIN:
                    contacts = decode_contacts(stimuli.recv(NOBLOCK))
                    if contacts is None:
                        fw.counters["stimuli_malformed"] += 1
                    else:
                        world.set_contacts(contacts)
            if port is not None:
                data = port.read({k for k in ready if isinstance(k, int)})
                if data:
                    fw.serial_in(data, tick)
            out = fw.advance(tick)
            settings = fw.sampler.settings
            if tick - due > settings.gate_cycles:  # this wake came more than one gate late
                n = fw.counters["samples"] - taken
                late += n
                if tick - due > settings.period_cycles(CLOCK_HZ):
                    behind += n
            want = not fw.radio.idle
            if out is not None:  # the contention state after it travels with it: one message
                try:
                    medium.send(encode_tx(out[1], out[0], want), NOBLOCK)
                    wanting, told = want, tick
                except zmq.Again:  # the medium is away: the transmission is lost, as on a cut cell
                    fw.counters["medium_unreachable"] += 1
            if port is not None and fw.serial_out:
                port.write(fw.take_serial())
            if want != wanting or (want and tick - told > CLOCK_HZ):  # repeated: a medium may restart
                try:
                    medium.send(WANT_ON if want else WANT_OFF, NOBLOCK)
                    wanting, told = want, tick
                except zmq.Again:
                    pass
    finally:
        fw.power_off()  # what this process still held is lost with it: counted
        counters = fw.counters_snapshot()
        counters["late_gates"] = late
        counters["behind_gates"] = behind
        if mark["set"]:
            counters["late_gates_since_mark"] = late - mark["late"]
            counters["behind_gates_since_mark"] = behind - mark["behind"]
            counters["samples_since_mark"] = fw.counters["samples"] - mark["samples"]
        if port is not None:
            counters.update(port.counters)
            port.close()
        # one write, so the lines of many bridges sharing a stderr never interleave
        sys.stderr.write(json.dumps({"bridge": br.id, "counters": counters}) + "\n")
        sys.stderr.flush()
        medium.close()
        stimuli.close()
    return 0
