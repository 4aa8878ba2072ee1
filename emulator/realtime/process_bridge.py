"""``cellbridge bridge``: one bridge (chip + firmware) as a real-time process.

The chip's cycle counter is the host's monotonic clock at 50 MHz. The loop sleeps in
``poll`` until the firmware's next timer or until a message arrives (the medium's
carrier reports and deliveries, the world's contacts, the host's bytes on a gateway's
serial line); nothing busy-waits, and a timer less than a millisecond away is slept for
to the microsecond (``poll`` counts milliseconds). Samples are computed lazily, when their DATA frame
(or the decision that none is due) is, with the capacitance at their gate: the bridge
wakes once per frame, not once per gate, and the cell sees the same frames at the same
times. A sample computed at a wake that came more than one gate (2 ms) after the
firmware asked for it counts as ``late_gates``, the measure of whether a machine
holds the mesh in real time; more than a whole sampling period after (the bridge
fell behind), also as ``behind_gates``. SIGUSR1 opens a window (``late_gates_since_mark``,
``behind_gates_since_mark`` and ``samples_since_mark`` count in it: a benchmark marks
the end of start-up) and a second SIGUSR1 closes it (so that the stop of many processes
at once is not measured). On
SIGTERM/SIGINT it prints its counters as JSON on stderr (with ``gates``: the ticks it will
start the gates of two sample indices 10 s apart, :func:`planned_gates`) and exits.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import select
import signal
import socket
import sys
import time

import zmq
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.firmware import Firmware, FirmwareConfig
from cellbridge.emulator.firmware.transceiver import TransceiverConfig
from cellbridge.emulator.medium.medium_wire import (
    CARRIER,
    MAX_DATAGRAM,
    RX,
    decode_carrier,
    decode_rx,
    encode_tx,
    encode_want,
)
from cellbridge.emulator.mesh.mesh import MeshError, load_mesh
from cellbridge.emulator.mesh.virtual import default_chip
from cellbridge.emulator.realtime import udp
from cellbridge.emulator.realtime.gateway_port import GatewayPort, open_pty
from cellbridge.emulator.realtime.process_world import KEEP_ENDED_S, decode_contacts
from cellbridge.emulator.realtime.realtime import (
    CLOCK_HZ,
    REPORTING_HELP,
    Endpoints,
    StopFlag,
    add_endpoint_arguments,
    endpoints,
    now_tick,
    rate_arg,
    reporting_arg,
)
from cellbridge.emulator.world.world import World

SHORT_TIMER = CLOCK_HZ // 1000  #: a timer this close is slept for exactly, not polled for (ms granularity)
#: A transmission due this soon after a wake, with nothing else due before it, is handed to
#: the medium in that wake, stamped with its own start tick, rather than after a sleep of
#: its own (a readout record's rank slots, an acknowledgement's SIFS): the medium starts it
#: at its stamp (process_medium's ``AHEAD``), and the bridge saves a wake. It is well under
#: the datagrams' own latency, so what the bridge would have heard meanwhile comes later
#: anyway.
EARLY = CLOCK_HZ // 10_000
#: Samples whose counts the chip computes ahead, back to back, after a wake that took one
#: (Sampler.prefetch): in a wake of their own each costs several times the CPU (the chip
#: model's code and data gone cold while the other processes ran)
PREFETCH = 8
ACK_SLACK = 10 * CLOCK_HZ // 1000  # a LINK_ACK crosses two processes and the medium: allow 10 ms
#: A level of the readout schedule in the real-time shells: ``depths`` of them make the
#: span, the latest a frame's record leaves the gateway (and the base of the host's
#: deadline). Records go on as soon as they are complete; the span only bounds how long
#: the skin waits for a record that was lost, and how late a held-up one may still come.
#: A record crosses a hop in two messages (bridge to medium to parent) and the parent's
#: wake, each a few milliseconds late on a loaded host, so a leaf's record reaches the
#: gateway several hops up tens of milliseconds after its gate on average: with 10 ms levels
#: the readout fell apart once the processes' delays averaged 3-4 ms (most element-frames
#: missing, where 30 ms levels hold to about twice that, beyond which the skin's mesh time
#: is the first to go). The cost: a frame that really lost a record waits for the span
#: (180 ms on a 4x4 with its gateway at the centre, 6 levels) before the host gives it out
#: without it.
READOUT_WINDOW = 30 * CLOCK_HZ // 1000
#: The slots are packed at the span's end, this far apart (``ReadoutConfig.hop``): a relay
#: waits for a late child until this long before its parent's slot, time for its own record
#: to cross the hop (two messages and a wake, each late on a loaded host). A bridge process
#: held up by the host (a 4x4's leaf is 4 hops deep of 6 levels: for up to ~120 ms) still
#: makes its frame; with the levels spread evenly, one level after its own slot its parent
#: had given its record up, and every record it sent while behind was dropped as late, its
#: element unknown meanwhile.
READOUT_HOP = 15 * CLOCK_HZ // 1000
STIMULI_CHECK = CLOCK_HZ // 5  # the world's socket is looked at at least this often (its fd is edge-like)
FILE_TCP = -1  #: ``--tcp`` without a port: the mesh file's
_POLLIN = select.POLLIN
_EVENTS, _ZMQ_POLLIN, _NOBLOCK = int(zmq.EVENTS), int(zmq.POLLIN), int(zmq.NOBLOCK)


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
    parser.add_argument("--readout", choices=("on", "off"), default="on",
                        help="samples on mesh time in READOUT records (on, default) or DATA frames (off)")
    parser.add_argument("--tcp", type=int, nargs="?", const=FILE_TCP, default=None, metavar="PORT",
                        help="gateway: also serve the serial stream on 127.0.0.1:PORT (0 = any free port; "
                             "no PORT: the mesh file's 'tcp', else any free port). Without --tcp, "
                             "no TCP port, whatever the file says")
    parser.add_argument("--pty-fd", type=int, default=None, help=argparse.SUPPRESS)  # from mesh up
    add_endpoint_arguments(parser)


def run(args: argparse.Namespace) -> int:
    window = Window()
    signal.signal(signal.SIGUSR1, window.ask)  # before anything slow
    try:
        mesh = load_mesh(args.mesh)
        br = mesh.bridge(args.id)
    except MeshError as exc:
        print(f"cellbridge bridge: {exc}", file=sys.stderr)
        return 2
    ep = endpoints(args)
    try:
        claim = claim_id(ep, br.id)
    except OSError:
        print(f"cellbridge bridge: bridge {br.id} already runs on this host for base port {ep.base_port} "
              f"(a second process would send its samples under the same origin)", file=sys.stderr)
        return 1
    stop = StopFlag()
    try:
        medium = udp.connect(*ep.medium)
    except OSError as exc:
        print(f"cellbridge bridge: cannot reach the medium at UDP {ep.host}:{ep.base_port}: "
              f"{exc.strerror or exc}", file=sys.stderr)
        return 1
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
    stimuli = ctx.socket(zmq.SUB)
    stimuli.setsockopt(zmq.LINGER, 0)
    stimuli.setsockopt(zmq.SUBSCRIBE, b"")
    stimuli.connect(ep.world)

    world = World(mesh, bridges=[br.id])
    fw = Firmware(FirmwareConfig(br.id, br.cells, br.gateway, br.position, mesh.side,
                                 settings=Settings(rate_hz=args.rate, reporting=args.reporting), ack_slack=ACK_SLACK,
                                 readout=args.readout == "on", readout_acks=False,
                                 readout_depths=mesh.readout_depths(), readout_window=READOUT_WINDOW, readout_hop=READOUT_HOP,
                                 transceiver=TransceiverConfig(bit_cycles=CLOCK_HZ // mesh.bitrate)),
                  default_chip(br.id, args.seed), world.sense_for(br.id), args.seed, now_tick())
    port = None
    if br.gateway:
        master = args.pty_fd
        if master is None:
            master, _slave, device = open_pty()  # keep the slave open: no EIO while nobody reads
            print(f"gateway {br.id} {device}", flush=True)
        tcp = args.tcp
        if tcp == FILE_TCP:
            tcp = br.tcp or 0
        try:
            port = GatewayPort(master, tcp)
        except OSError as exc:
            print(f"cellbridge bridge: gateway {br.id}: cannot serve TCP 127.0.0.1:{tcp}: "
                  f"{exc.strerror or exc}", file=sys.stderr)
            return 1
        # Started by mesh up (--pty-fd), the supervisor prints this bridge's line, URL
        # included: a second line of another shape, printed before the supervisor's, broke
        # "one 'gateway <id> <device> [socket://...]' line per gateway".
        if port.tcp_port is not None and args.pty_fd is None:
            print(f"gateway {br.id} socket://127.0.0.1:{port.tcp_port}", flush=True)

    # select.poll, not zmq.Poller: the cell's datagrams are plain fds, and zmq_poll costs
    # tens of microseconds a call. The world's SUB socket joins by its ZMQ_FD, which only
    # says "look at ZMQ_EVENTS": it is drained when that fd wakes us and every 200 ms.
    poller = select.poll()
    medium_fd, stimuli_fd = medium.fileno(), stimuli.fileno()  # the socket's ZMQ_FD
    poller.register(medium_fd, _POLLIN)
    poller.register(stimuli_fd, _POLLIN)
    registered: set[int] = set()
    late = behind = 0
    wanting, told = False, -CLOCK_HZ  # contention state last told the medium, and when
    stimuli_at = 0
    early = 0  # the radio's start tick when the firmware runs up to it without a sleep (EARLY)
    me = br.id
    # What start-up built (modules, the chip, the layout) lives as long as the process:
    # out of the collector's reach, a full collection scans only what the loop made
    # (it took ~6 ms, more with cold caches, and a wake that late is a late gate).
    gc.freeze()
    try:
        while not stop.stopped:
            if port is not None:
                fds = set(port.fds())
                for fd in fds - registered:
                    poller.register(fd, _POLLIN)
                for fd in registered - fds:
                    poller.unregister(fd)
                registered = fds
            due = fw.sampler.next_tick  # when the samples computed at the next wake were wanted
            # Asked once a wake (it looks at every timer of the firmware): nothing changes it
            # until a message comes, and a wake by messages asks again below.
            next_tick = fw.next_tick
            wait = next_tick - now_tick()
            if wait >= SHORT_TIMER:
                ready = {fd for fd, _ in poller.poll(min(math.ceil(wait * 1000 / CLOCK_HZ), 200))}
            else:
                # A timer less than a millisecond away (an acknowledgement SIFS after a frame,
                # a backoff of a few slots) is kept to the microsecond: poll's milliseconds
                # would send every acknowledgement a millisecond late, after the other bridges'
                # next frames, and the retransmissions that followed choked the cells.
                ready = {fd for fd, _ in poller.poll(0)}
                if not ready and wait > 0:
                    if wait <= EARLY and next_tick == fw.radio.next_tick and next_tick < fw.sampler.next_tick:
                        early = next_tick  # the radio's start alone is due: go now, at its tick
                    else:
                        time.sleep(wait / CLOCK_HZ)
            tick = now_tick()
            if early:
                tick = max(tick, early)
                early = 0
            taken = fw.counters["samples"]
            fed = False  # whether the firmware was given something to act on now
            if window.asked:
                window.take((late, behind, fw.counters["samples"]))
            if medium_fd in ready:
                while True:
                    try:
                        msg = medium.recv(MAX_DATAGRAM)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:  # an earlier send found no medium listening
                        fw.counters["medium_unreachable"] += 1
                        continue
                    kind = msg[0] if msg else -1
                    if kind == RX and (rx := decode_rx(msg)) is not None:
                        # the sender's start tick is the frame's start of frame (mesh time)
                        fed |= fw.receive(rx[1], tick, rx[0], rx[2] or None)
                    elif kind == CARRIER and (cs := decode_carrier(msg)) is not None:
                        fw.carrier(*cs)
                    else:
                        fw.counters["medium_malformed"] += 1
                if not fed:  # a carrier report alone moves the radio's timers
                    next_tick = fw.next_tick
            if stimuli_fd in ready or tick >= stimuli_at:
                stimuli_at = tick + STIMULI_CHECK
                while stimuli.getsockopt(_EVENTS) & _ZMQ_POLLIN:  # type: ignore[operator]  # an int option (pyzmq types all int | bytes)
                    contacts = decode_contacts(stimuli.recv(_NOBLOCK))
                    if contacts is None:
                        fw.counters["stimuli_malformed"] += 1
                    else:
                        # from now on: a sample of an earlier gate still to be computed (a
                        # relay's, at its children's records) sees what pressed at its gate
                        world.set_contacts(contacts, tick / CLOCK_HZ, KEEP_ENDED_S)
                        # the capacitances a new press gives, computed now, about half a
                        # period before its first gate: not in the readout of the frame
                        # that shows it, where every hop's bridge waited for its own
                        world.prepare(tick / CLOCK_HZ)
            if port is not None:
                data = port.read(ready)
                if data:
                    fw.serial_in(data, tick)
                    fed = True
            # Only when something is due or the firmware took a frame or command: a wake for
            # the world's contacts (every bridge at once, twice a second) or a carrier report
            # computes nothing early, so it stays cheap and no herd of wakes forms.
            out = fw.advance(tick) if fed or tick >= next_tick else None
            settings = fw.sampler.settings
            if tick - due > settings.gate_cycles:  # this wake came more than one gate late
                n = fw.counters["samples"] - taken
                late += n
                if tick - due > settings.period_cycles(CLOCK_HZ):
                    behind += n
            want = fw.radio.contending(tick, SHORT_TIMER)
            if out is not None:  # the contention state after it travels with it: one message
                if _send(medium, encode_tx(me, out[1], out[0], want, tick), fw):
                    wanting, told = want, tick
            if port is not None:
                if fw.serial_out:
                    port.write(fw.take_serial())
                port.expire_unread(tick / CLOCK_HZ)
            if want != wanting or tick - told > CLOCK_HZ:  # also once a second: a medium may restart
                if _send(medium, encode_want(me, want), fw):
                    wanting, told = want, tick
            if fw.counters["samples"] > taken:  # the chip just ran, and what was due has gone
                fw.sampler.prefetch(PREFETCH)
    finally:
        fw.power_off()  # what this process still held is lost with it: counted
        counters = fw.counters_snapshot()
        counters["late_gates"] = late
        counters["behind_gates"] = behind
        counters["udp_drops"] = udp.drops(medium)
        counters.update(window.report((late, behind, fw.counters["samples"])))
        if port is not None:
            counters.update(port.counters)
            port.close()
        # one write, so the lines of many bridges sharing a stderr never interleave
        sys.stderr.write(json.dumps({"bridge": br.id, "counters": counters, "gates": planned_gates(fw)}) + "\n")
        sys.stderr.flush()
        medium.close()
        stimuli.close()
        claim.close()
    return 0


def claim_id(ep: Endpoints, bridge: int) -> socket.socket:
    """Hold this bridge id for the medium at ``ep`` while the process lives: an abstract
    Unix socket named after both, which a second process cannot bind (OSError) and the
    kernel releases when this one dies, however it dies."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.bind(f"\0cellbridge-bridge/{ep.host}:{ep.base_port}/{bridge}")
    except OSError:
        s.close()
        raise
    return s


def planned_gates(fw: Firmware) -> dict[str, int]:
    """Sample index -> the tick this bridge will start that sample's C1 gate, for the next
    two multiples of 10 s of global time at least a second ahead; empty without mesh time.
    Every bridge of a skin stopped within the same few seconds names the same indices, so
    the spread of one index's gate starts across the skin is read straight off the
    bridges' last lines: how well mesh time aligns what the chips will do (the plan the
    sampler follows, extrapolated with the skew each bridge measured)."""
    tick = now_tick()
    if not fw.timebase.synced(tick):
        return {}
    rate = fw.sampler.settings.rate_hz
    step = 10 * fw.config.clock_hz
    first = (fw.clock.global_at(fw.crystal.local(tick)) + fw.config.clock_hz) // step + 1
    return {str(k * 10 * rate): fw.timebase.gate_tick(k * 10 * rate, rate) for k in (first, first + 1)}


class Window:
    """The measuring window SIGUSR1 opens and a second SIGUSR1 closes (late, behind and
    samples counted in it). The handler only counts; the loop takes the marks."""

    NAMES = ("late_gates_since_mark", "behind_gates_since_mark", "samples_since_mark")

    def __init__(self) -> None:
        self.asked = 0
        self.marks: list[tuple[int, int, int]] = []

    def ask(self, *_: object) -> None:
        self.asked += 1

    def take(self, now: tuple[int, int, int]) -> None:
        for _ in range(self.asked):
            if len(self.marks) < 2:
                self.marks.append(now)
        self.asked = 0

    def report(self, now: tuple[int, int, int]) -> dict[str, int]:
        if not self.marks:
            return {}
        end = self.marks[1] if len(self.marks) > 1 else now
        return {name: b - a for name, a, b in zip(self.NAMES, self.marks[0], end)}


def _send(medium: socket.socket, msg: bytes, fw: Firmware) -> bool:
    """One datagram to the medium; False (counted) when it cannot go: no medium is
    listening (the transmission is lost, as on a cut cell) or the socket is full."""
    try:
        medium.send(msg)
        return True
    except OSError:
        fw.counters["medium_unreachable"] += 1
        return False
