"""Bridge firmware, sans-I/O: fed the chip's events and a cycle time, returns transmissions.

One :class:`Firmware` is one bridge. Its owner (the virtual-time mesh or a real-time
process shell) calls:

* ``receive(data, tick, cell, sof)`` with bytes the medium delivered from the cell (``sof``:
  the tick the transmission started, for mesh time; by default its end minus its airtime),
* ``carrier(until)`` when the medium reports another bridge transmitting,
* ``serial_in(data, tick)`` (gateways) with bytes the host wrote to the serial line,
* ``advance(tick)`` at or after ``next_tick``; it runs every timer due and returns the
  bytes whose cell transmission starts at ``tick`` (or None),
* ``take_serial()`` (gateways) for the bytes to write to the host.

Everything the bridge does — mesh time, sampling (C1 gate then C2 gate), reporting,
routing, forwarding, commands — happens inside those calls; the owner supplies only time,
bytes and the element's capacitance (``sense(tick) -> (C1, C2)`` in farads).
"""

from __future__ import annotations

import random
from bisect import insort
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from importlib import metadata

import msgpack
from cellbridge.emulator.firmware.commands import MAX_GATE, Settings, execute
from cellbridge.emulator.firmware.linklayer import LinkLayer
from cellbridge.emulator.firmware.meshtime import Crystal, MeshClock, MeshClockConfig, Timebase
from cellbridge.emulator.firmware.readout import AGE_ROOM, FrameReadout, ReadoutConfig, State
from cellbridge.emulator.firmware.readout import stagger as _stagger
from cellbridge.emulator.firmware.routing import INFINITE, PERFECT_LINK, Router, Trickle
from cellbridge.emulator.firmware.sampling import Sampler
from cellbridge.emulator.firmware.transceiver import Transceiver, TransceiverConfig
from cellbridge.protocol import (
    ADDR_BROADCAST,
    ADDR_HOST,
    Beacon,
    BridgeStatus,
    Command,
    DuplicateFilter,
    Flags,
    Fragment,
    Frame,
    FrameType,
    Hello,
    LinkAck,
    Message,
    Mode,
    Neighbour,
    Op,
    ProtocolError,
    Raw,
    Readout,
    ReadoutSame,
    ReadoutSample,
    RecentFrames,
    Sample,
    StreamDecoder,
    addressed_to,
    decode,
    encode,
    own,
    to_serial,
    unpack_payload,
)
from cellbridge.protocol import peek as parse
from cellbridge.protocol import reframe as build
from cellbridge.tactile.transfer import max_gate_cycles


def _package_version() -> str:
    """The installed distribution's version, read from its metadata: the emulator does not
    import the top package (the layers below it never do)."""
    try:
        return " " + metadata.version("cellbridge")
    except metadata.PackageNotFoundError:  # run from a source tree that was never installed
        return ""


FIRMWARE_VERSION = "cellbridge-emu" + _package_version()  #: HELLO's firmware string unless configured
_ACK = int(Flags.ACK_REQUEST)
_FRAGMENT = int(Flags.FRAGMENT)
_HELLO = int(FrameType.HELLO)
_MS = 50_000  # cycles per millisecond at 50 MHz
_PARSED = frozenset({int(FrameType.BEACON), int(FrameType.CMD), int(FrameType.LINK_ACK)})  # acted on here
_BUNDLE = int(FrameType.BUNDLE)
_READOUT = int(FrameType.READOUT)
_READOUT_SAME = int(FrameType.READOUT_SAME)
_OVERFLOWS = 0x03  # the sample flags a readout record carries (its state says the rest)
#: A relay takes a frame it forwarded this recently for a copy (a retransmission, a detour,
#: a loop's return: all within the retries of a hop or the few hops of a loop); an older
#: one goes on, and the host's duplicate filter judges it.
_COPY_AGE = 1000 * _MS
_COPY_MEMORY = 1024  # frames remembered at most (per bridge, all origins)
# A frame that went round a loop through us comes back with as many more hops as the loop
# has bridges. A loop of two (our parent took us as its parent) is broken as soon as the
# parent sends us a frame (Router.child_sent), before its copy is looked at here; so a
# loop seen here has at least three. A copy one or two hops longer is the same frame sent
# up two paths (a sender whose acknowledgement was late or lost sent it again via another
# neighbour): the common case under message latency, and not evidence of a loop. Taking
# it for one dropped a good parent, which made more frames go up two paths.
_LOOP_MIN_HOPS = 3
_FLOOD_REPEATS = ((0, 2 * _MS), (10 * _MS, 30 * _MS), (40 * _MS, 80 * _MS))  # windows of the copies
_FLOOD_MAX = 16 * len(_FLOOD_REPEATS)  # copies waiting at most: 16 commands being flooded
_FORWARD_MIN, _FORWARD_SPREAD = 2 * _MS, 20 * _MS  # a new round of mesh time goes on 2-22 ms after it came
_LINK_GUARD = 64  # link numbers stay this far from the host numbering (see Firmware._link_candidate)
_RESET_WAIT = 3000 * _MS  # a RESET waits at most this long for its reply and flood copies to leave


def _hello_boots(f: Raw) -> int | None:
    """The boot counter of a relayed HELLO (None: a version 1 HELLO, or not readable): the
    copy filter's evidence of a restart."""
    if f.flags & _FRAGMENT:
        return None
    try:
        hello = unpack_payload(_HELLO, f.body)
    except ProtocolError:
        return None
    return hello.boots or None  # type: ignore[union-attr]  # unpacked as a HELLO: a Hello


def _when(item: tuple[int, bytes]) -> int:
    return item[0]


@dataclass(frozen=True)
class FirmwareConfig:
    """Firmware parameters; times in chip cycles (50 MHz)."""

    bridge: int
    cells: tuple[int, ...] = (1,)
    gateway: bool = False
    position: tuple[float, float] = (0.0, 0.0)
    side: float = 0.040
    clock_hz: int = 50_000_000
    settings: Settings = field(default_factory=Settings)
    batch_max: int = 16  #: samples per DATA frame at most (also bounded by the frame size)
    #: A sample waits at most this long for company in a DATA frame (periodic reporting).
    #: The trade-off of latency against air time: a shorter wait sends more, shorter frames,
    #: each with its header, acknowledgement and gaps, and leaves less of a saturated cell
    #: for samples (bench/bench_emulator.py, bench/bench_latency.py; docs/emulator.md).
    max_latency: int = 50 * _MS
    #: The same under event-based reporting: 1 ms, a sample goes almost as soon as it is
    #: taken. Few samples travel, so a longer wait puts few of them together while the
    #: host sees every press that much later (bench/bench_press_latency.py --virtual).
    event_latency: int = 1 * _MS
    #: An aligned batch (periodic, on mesh time: emulator/firmware/sampling.py) leaves in its
    #: bridge's *slot* after the batch closes: the deepest bridges first, one ``depth_slot``
    #: per hop, so a far bridge's batch has crossed the hops below it by the time those
    #: bridges send theirs, and the batches of one index meet at the relays instead of all
    #: contending for the gateway's cells at once. A bridge ``d`` hops from the gateway
    #: sends ``(slot_depths - d) * depth_slot`` after the close (deeper than ``slot_depths``:
    #: at once), plus its own offset up to ``slot_jitter`` (a hash of its id), so the bridges
    #: of one depth do not start together. ``depth_slot`` is what one hop takes in the
    #: real-time shells (a frame, its LINK_ACK and the processes' message delays: ~3 ms)
    #: with the jitter on top, so a relay's slot comes after its children's frames reached it.
    depth_slot: int = 3 * _MS
    slot_jitter: int = 1 * _MS
    slot_depths: int = 6
    #: Aligned batches (above): one index reaches the host from every bridge within the
    #: relay delays of each other.
    aligned_batches: bool = True
    queue_len: int = 64
    max_retries: int = 5
    trickle_imin: int = 50 * _MS
    trickle_imax: int = 500 * _MS  #: the beacon period once routes are stable
    status_period: int = 2000 * _MS
    hello_period: int = 10_000 * _MS
    max_hops: int = 32
    ack_slack: int = 0  #: extra wait for a LINK_ACK (real-time shells: message latency)
    lazy_sampling: bool = True  #: compute periodic samples when their frame is due (False: at each gate)
    #: A beacon at least this often (routing and mesh time): neighbours stay fresh, and the
    #: mesh clock gets a reference point per period (docs/time.md).
    sync_period: int = 500 * _MS
    mesh_clock: MeshClockConfig = field(default_factory=MeshClockConfig)
    clock_epoch: int = 0  #: the chip's cycle counter at tick 0 (its crystal's own origin)
    #: Start-of-frame detection jitter of the receiver, cycles (uniform 0..n): the limit of
    #: MAC-layer timestamps (a quarter of a bit at 1 Mbit/s)
    sof_jitter: int = 12
    transceiver: TransceiverConfig = field(default_factory=TransceiverConfig)
    firmware: str = FIRMWARE_VERSION  #: the version string HELLO announces
    #: The scheduled readout (emulator/firmware/readout.py, docs/time.md): samples on mesh time are
    #: read out frame by frame along the routing tree, every element accounted for; samples
    #: without mesh time still go in DATA frames; the daemon reads the records as skin
    #: frames (docs/time.md). False: every sample in DATA frames (the daemon's fallback).
    readout: bool = True
    #: Levels of the readout schedule (a bridge deeper sends in the deepest slot): the
    #: skin's depth from its gateways; the mesh builders set it from the mesh file.
    readout_depths: int = 8
    #: Cycles per level of the schedule: a full frame, its acknowledgement and a retry in
    #: virtual time (the real-time shells add their message latency).
    readout_window: int = 6 * _MS
    #: 0: the levels' slots evenly spread; else packed at the span's end this many cycles
    #: apart, for hosts whose processes may be held up (:attr:`ReadoutConfig.hop`)
    readout_hop: int = 0
    #: A child whose records stopped this long ago is no longer expected (nor its subtree).
    readout_forget: int = 2000 * _MS
    #: A child whose records stopped this long ago (and the schedule's span and a frame
    #: period ago) is no longer waited for, only listed missing, until it is heard again
    #: (:attr:`ReadoutConfig.quiet`)
    readout_quiet: int = 100 * _MS
    #: Records ask for a per-hop acknowledgement and are retried while a retry can still
    #: reach the parent by its slot (False: sent once; a lost one is listed missing above
    #: all the same)
    readout_acks: bool = True
    #: Event-based, a bridge on the readout sends a sample at least every this many frames
    #: (at its own phase, spread by its id), not only at its heartbeat: the host reads
    #: "unchanged" only after a frame it knew, so an element whose record was lost on the
    #: way is unknown until its next sample. Losses on the cells are covered by the samples
    #: the relays keep (expanded after a failed record, sent for an element listed missing)
    #: and losses on the serial line by the gateway's ``serial_refresh``; this covers what
    #: no kept sample can (a relay or gateway that restarted, a new parent that keeps none
    #: of an element it then loses a record of): rarer, as it costs every
    #: bridge a sample on the cells (0: heartbeat only). None: 50 frames with
    #: ``readout_acks``, 10 without (then no bridge learns that its record was lost, nothing
    #: is expanded after a loss, and only this brings the elements back)
    readout_refresh: int | None = None
    #: A gateway writes every element it keeps a sample of as that sample once every this
    #: many frames (at the element's phase) where its bridge said *unchanged*: a record lost
    #: on the serial line leaves an element unknown this many frames at most, at no cost on
    #: the cells (0: never; emulator/firmware/readout.py). The gateway's own element samples
    #: afresh at this refresh instead (it has none on the cells)
    serial_refresh: int = 10

    @property
    def cell_refresh(self) -> int:
        """The refresh on the cells in frames (:attr:`readout_refresh`, its default resolved)."""
        if self.readout_refresh is not None:
            return self.readout_refresh
        return 50 if self.readout_acks else 10


def _rest(_tick: int) -> tuple[float, float]:
    return 15.67e-12, 19.44e-12


class Firmware:
    def __init__(self, config: FirmwareConfig, chip: object, sense: Callable[[int], tuple[float, float]] = _rest,
                 seed: int = 0, boot_tick: int = 0, resets: int = 0) -> None:
        config.settings.check(config.clock_hz)
        self.config = config
        self.me = config.bridge
        self.chip = chip
        self.sense = sense
        self.rng = random.Random(seed * 1_000_003 + config.bridge * 7919 + resets)
        self.counters: Counter[str] = Counter()
        self.resets = resets
        # the chip's crystal: its own rate (from the chip's configuration) and origin
        ppm = getattr(getattr(chip, "config", None), "crystal_ppm", 0.0)
        self.crystal = Crystal(float(ppm), config.clock_epoch)
        self._sof_rng = random.Random(seed * 1_000_033 + config.bridge * 104_729 + resets)
        self._clock_past: Counter[str] = Counter()
        self.serial_out = bytearray()
        self._serial_in = StreamDecoder()
        # Commands seen survive a RESET command (kept in memory a reset does not clear), so
        # the flood's repeated copies of that RESET do not reset the bridge again.
        self.seen_cmd = DuplicateFilter()
        self._max_gate: int | None = None
        # Totals of the parts a RESET command rebuilds (link, radio, router, reporter),
        # from earlier lives, so a counter never goes back.
        self._past: Counter[str] = Counter()
        self._power_on(boot_tick)

    # -- state ----------------------------------------------------------------------
    def _power_on(self, tick: int) -> None:
        c = self.config
        self.boot_tick = tick
        # A boot numbers from 0 and its first frame is the HELLO (seq 0): the protocol's
        # evidence of a restart, without which the host and the relays would drop the new
        # numbering as stale or duplicate (docs/protocol.md, duplicate filter).
        self.seq = 0
        self.link_seq = 0  # frames that end at the next hop: beacons, link acks, bundles
        self.radio = Transceiver(self.rng, c.transceiver)
        self.radio.stamper = self._stamp
        # mesh time is in RAM: a reset starts it again (the crystal runs on)
        self.clock = MeshClock(self.me, c.gateway, c.mesh_clock, self.crystal.local(tick))
        self.timebase = Timebase(self.crystal, self.clock, c.clock_hz)
        self.time_beacon_at = tick + self.rng.randrange(c.sync_period)
        self.link = LinkLayer(self.me, c.cells, self.radio, c.queue_len, c.max_retries, ack_slack=c.ack_slack)
        self.link.urgent_acks = c.readout_acks
        self.router = Router(self.me, c.gateway, max_hops=c.max_hops,
                             neighbour_timeout=4 * c.trickle_imax)
        self.trickle = Trickle(self.rng, c.trickle_imin, c.trickle_imax)
        self.trickle.start(tick)
        # Upward frames forwarded lately, with their hop counts (copies and loop returns).
        # Not a numbering window: a new boot's HELLO may have gone another way (protocol/copies.py).
        self.seen = RecentFrames(_COPY_AGE, _COPY_MEMORY)
        self.readout = (FrameReadout(self.me, ReadoutConfig(c.readout_depths, c.readout_window, c.readout_forget,
                                                            c.readout_hop, c.readout_quiet), self.counters,
                                     AGE_ROOM if c.gateway else 0, c.serial_refresh if c.gateway else 0)
                        if c.readout else None)
        self._readout_at = -1  # a child's record may have completed a frame: look at this tick
        self.sampler = Sampler(c.settings, self.chip, self.sense,
                               tick + self.rng.randrange(c.settings.period_cycles(c.clock_hz)), c.clock_hz,
                               c.batch_max, c.max_latency, c.lazy_sampling, self.counters, self.timebase,
                               c.event_latency, self._batch_slot, c.aligned_batches,
                               _stagger(c.bridge, 1 << 16) / (1 << 16),
                               self._readout_sample if c.readout else None, self._readout_wait)
        self.status_at = tick + c.status_period
        self._say_hello()  # queued until there is a route
        self.hello_at = tick + c.hello_period
        self.reset_at = -1
        self._reset_by = -1
        self._reset_flood: bytes | None = None  # the RESET's flood copies a reset waits for
        self._last_flood: bytes | None = None
        self.floods: list[tuple[int, bytes]] = []  # (when, frame) command copies still to send

    @property
    def max_gate(self) -> int:
        """Longest gate SET_GATE accepts: what the host can still unwrap on this chip.
        Computed on first use (it costs milliseconds; a mesh boots thousands of bridges)."""
        if self._max_gate is None:
            params = getattr(self.chip, "params", None)  # the chip as tactile.transfer describes it
            self._max_gate = MAX_GATE if params is None else min(MAX_GATE, max_gate_cycles(chip=params))
        return self._max_gate

    @property
    def next_tick(self) -> int:
        # (asked after every wake: comparisons in line rather than min() over a tuple)
        t = self.sampler.next_tick
        x = self.trickle.next_tick
        if x < t:
            t = x
        x = self.status_at
        if x < t:
            t = x
        x = self.time_beacon_at
        if x < t:
            t = x
        if self.floods and self.floods[0][0] < t:
            t = self.floods[0][0]
        x = self.hello_at
        if 0 <= x < t:
            t = x
        x = self.reset_at
        if 0 <= x < t:
            t = x
        lt = self.link.next_tick
        if lt is not None and lt < t:
            t = lt
        r = self.readout
        if r is not None:
            rt = r.next_tick
            if rt is not None and rt < t:
                t = rt
            if 0 <= self._readout_at < t:
                t = self._readout_at
        return t

    def _next_seq(self) -> int:
        """The next number of a frame for the host (DATA, HELLO, STATUS, CMD_REPLY): these
        alone share one numbering, so a gap the host sees is a frame lost (health's loss)."""
        s = self.seq
        self.seq = (s + 1) & 0xFFFF
        return s

    def _link_candidate(self) -> int:
        """The number the next frame that ends at the next hop would take (docs/protocol.md §1).

        Kept clear of the host numbering's neighbourhood: a bundle is acknowledged by
        (origin, seq) like our own frames, and a late LINK_ACK for our frame n must not
        end the transmission of a bundle numbered n."""
        x = self.link_seq
        if (x - self.seq + _LINK_GUARD) & 0xFFFF < 2 * _LINK_GUARD:
            x = (self.seq + _LINK_GUARD) & 0xFFFF
        return x

    def _next_link_seq(self) -> int:
        x = self._link_candidate()
        self.link_seq = (x + 1) & 0xFFFF
        return x


    def _life_totals(self) -> Counter[str]:
        """Totals kept by the parts a reset rebuilds, for this life only."""
        c = Counter(self.link.counters)
        c.update(self.clock.counters)
        c.update(cca_busy=self.radio.cca_busy, transmissions=self.radio.transmissions,
                 acks_dropped=self.radio.acks_dropped,
                 bits_sent=self.radio.bits_sent, parent_changes=self.router.parent_changes,
                 neighbour_evictions=self.router.evictions,
                 evictions_failed=self.router.evictions_failed, evictions_silent=self.router.evictions_silent,
                 evictions_loop=self.router.evictions_loop, suppressed=self.sampler.reporter.suppressed,
                 copies_forgotten=self.seen.forgotten)
        return c

    def power_off(self) -> None:
        """Count what a power-off or reset discards: queued, in-flight and pending broadcast
        frames (``power_off_frames``) and samples batched but not yet in a DATA frame
        (``power_off_samples``). Nothing is lost without a count."""
        link = self.link
        frames = len(link.queue) + len(link.broadcasts) + len(self.floods) + len(link.urgent)
        if link.inflight is not None:
            frames += len(link.inflight.frames)
        self.counters["power_off_frames"] += frames
        self.counters["power_off_samples"] += self.sampler.unsent
        if self.readout is not None:
            self.counters["power_off_readouts"] += self.readout.waiting()

    def counters_snapshot(self) -> dict[str, int]:
        out = dict(self.counters)
        totals = Counter(self._past)
        totals.update(self._life_totals())
        out.update(totals)
        out.update(resets=self.resets, queue_len=len(self.link.queue), has_route=int(self.router.has_route),
                   mesh_time=int(self.clock.has_fit()), time_root=int(self.clock.is_root))
        if self.config.gateway:  # what the host wrote that was not a frame: counted by cause
            dec = self._serial_in
            out["serial_rx_bytes_dropped"] = sum(dec.bytes_dropped.values())
            for cause, n in dec.frames_dropped.items():
                out[f"serial_rx_{cause}"] = n
        return out

    # -- inputs ---------------------------------------------------------------------
    def carrier(self, cell: int, start: int, until: int) -> None:
        self.radio.carrier(cell, start, until)

    def serial_in(self, data: bytes, tick: int) -> None:
        """Bytes the host wrote to the gateway's serial line (COBS frames)."""
        for f in self._serial_in.feed(data):
            if isinstance(f.payload, Fragment):  # the host never fragments a command
                self.counters["serial_fragmented_control"] += 1
            elif f.type is FrameType.CMD:
                self._command(f, tick)
            else:
                self.counters["serial_ignored"] += 1

    def take_serial(self) -> bytes:
        out = bytes(self.serial_out)
        self.serial_out.clear()
        return out

    def receive(self, data: bytes, tick: int, cell: int, sof: int | None = None) -> bool:
        """A frame from ``cell``, its transmission started at ``sof`` (default: ``tick``
        minus its airtime, ``tick`` being its end); False when the bridge ignored it."""
        # Address filter before any decoding, as a radio does: unicasts for other bridges
        # are dropped from the header bytes alone (type at 2, dst at 5-6).
        if not addressed_to(data, self.me):
            self.counters["overheard"] += 1
            return False
        if len(data) > 7 and data[2] in _PARSED:
            return self._receive_parsed(data, tick, tick - self.radio.airtime(len(data)) if sof is None else sof)
        got = parse(data)
        if got is None:
            self.counters["rx_crc"] += 1
            return False
        src, _, f = got
        if f.flags & _ACK:
            self.radio.send_ack(build(own(LinkAck(f.origin, f.seq), self.me, self._next_link_seq()), self.me, src),
                                self.config.cells, tick)
        if self.router.child_sent(src):  # our parent sent it: a loop of two, broken now
            self.counters["loops_broken"] += 1
            self.trickle.reset(tick)
        elif self.router.inconsistent(src):
            self.counters["inconsistencies"] += 1
            self.trickle.reset(tick)
        if f.type == _READOUT and self.readout is not None and not f.flags & _FRAGMENT:
            try:
                record: Readout = unpack_payload(_READOUT, f.body)  # type: ignore[assignment]  # a READOUT payload
            except ProtocolError:
                self.counters["rx_bad_readout"] += 1
                self.readout.unreadable(src)
                return False
            self.readout.child(src, record, tick, f.seq)
            self._readout_at = tick
            return True
        if f.type == _READOUT_SAME:
            if self.readout is None or f.flags & _FRAGMENT:
                # a bridge-to-parent frame that is never fragmented, read only on the schedule:
                # relayed, it marked its (origin, seq) seen up the tree (a real frame of that
                # number then a duplicate) and reached the host, which has no use for it
                self.counters["rx_readout_same"] += 1
                return False
            try:
                same: ReadoutSame = unpack_payload(_READOUT_SAME, f.body)  # type: ignore[assignment]  # its payload
            except ProtocolError:
                self.counters["rx_bad_readout"] += 1
                return False
            if self.readout.child_same(src, same, tick):
                self._readout_at = tick
            return True
        if f.type == _BUNDLE:
            try:
                inner = [parse(b) for b in msgpack.unpackb(f.body)]
            except Exception:  # malformed msgpack: the whole bundle is bad
                inner = [None]
            for g in inner:
                if g is None:
                    self.counters["rx_bad_bundle"] += 1
                elif g[2].type == _READOUT_SAME:  # (never bundled: see above)
                    self.counters["rx_readout_same"] += 1
                else:
                    self._upward(g[2], tick, src)
        else:
            self._upward(f, tick, src)
        return True

    def _receive_parsed(self, data: bytes, tick: int, sof: int) -> bool:
        try:
            f = decode(data)
        except ProtocolError as exc:
            self.counters[f"rx_{exc.cause}"] += 1
            return False
        if isinstance(f.payload, Fragment):  # control frames always fit one frame: a forgery
            self.counters["rx_fragmented_control"] += 1
            return False
        t = f.type
        if t is FrameType.LINK_ACK:
            ack: LinkAck = f.payload  # type: ignore[assignment]  # a LINK_ACK frame's payload is a LinkAck
            return f.dst == self.me and self.link.acked(ack.origin, ack.seq, f.src, tick)
        if t is FrameType.BEACON:
            self._beacon(f, tick, sof)
        else:
            self._command(f, tick)
        return True

    # -- routing --------------------------------------------------------------------
    def _beacon(self, f: Frame, tick: int, sof: int) -> None:
        b: Beacon = f.payload  # type: ignore[assignment]  # a BEACON frame's payload is a Beacon
        if b.time is not None:
            # samples due before the clock moves are taken with the clock as it was (their
            # gates were planned with it): lazy sampling stays gate-by-gate exact
            for data in self.sampler.advance(tick):
                self._own(data)
            if self.clock.heard(b.time, self.crystal.local(sof) + self._sof_rng.randint(0, self.config.sof_jitter)):
                # a new round: pass it on soon (a flood crosses the skin in tens of
                # milliseconds instead of a beacon period per hop), still once per round
                soon = tick + _FORWARD_MIN + self.rng.randrange(_FORWARD_SPREAD)
                if soon < self.time_beacon_at:
                    self.time_beacon_at = soon
        self.router.on_beacon(f.src, b.parent, b.path_etx, b.hops, tick)
        self.radio.contenders = len(self.router.table)
        if b.parent == self.me and b.path_etx < INFINITE and b.path_etx <= self.router.path_etx:
            self.trickle.reset(tick)  # a child thinks it is closer than us: our cost is stale
        elif b.path_etx >= INFINITE and self.router.has_route:
            self.trickle.reset(tick)  # a neighbour without a route asks for fresh beacons
        else:
            self.trickle.heard_consistent()
        self._reroute(tick)

    def _reroute(self, tick: int) -> None:
        had = self.router.has_route
        if self.router.select():
            self.trickle.reset(tick)
        if had and not self.router.has_route:
            self.counters["route_lost"] += 1

    def _beacon_message(self, tick: int) -> Beacon:
        r = self.router
        return Beacon(0 if r.gateway or r.parent is None else r.parent, r.path_etx, r.hops,
                      self.clock.stamp(self.crystal.local(tick)))

    def _send_beacon(self, tick: int) -> None:
        # The seq comes from the link numbering: a beacon never reaches the host, and a
        # number it took from the host's numbering would look lost there (health's loss).
        frame = Frame(self.me, ADDR_BROADCAST, self.me, self._next_link_seq(), self._beacon_message(tick))
        self.link.broadcast(encode(frame))
        self.counters["beacons"] += 1

    def _stamp(self, data: bytes, tick: int) -> bytes:
        """MAC-layer timestamp: a beacon of ours gets the routing state and mesh time of
        the cycle its transmission starts (the transceiver calls this then)."""
        try:
            f = decode(data)
        except ProtocolError:
            return data
        if f.origin != self.me:
            return data
        return encode(Frame(f.src, f.dst, f.origin, f.seq, self._beacon_message(tick), f.hops, f.cost, f.flags))

    # -- upward traffic -------------------------------------------------------------
    def _upward(self, f: Raw, tick: int, src: int = -1) -> None:
        """Forward an upward frame that neighbour ``src`` sent us."""
        if f.origin == self.me:
            # our own frame came back (a parent change raced with a neighbour's): send it on
            # once more; the copy filter stops a second return
            self.counters["own_returned"] += 1
        boot = _hello_boots(f) if f.type == _HELLO else None
        first = self.seen.first(f.origin, f.seq, f.hops, tick, boot)
        if first is not None:
            self.counters["duplicates"] += 1
            if f.hops >= first + _LOOP_MIN_HOPS and not self.config.gateway:
                # the same frame again with at least three hops more: it went round a loop
                # through us (a copy only one or two hops longer took a detour: see _LOOP_MIN_HOPS)
                self.counters["loops_detected"] += 1
                self.router.loop_detected()
                self.trickle.reset(tick)
                self._reroute(tick)
                self._loop_return(f, tick)
            elif f.hops > first and self.link.handed.get((f.origin, f.seq)) == src and not self.config.gateway:
                # back from the neighbour that acknowledged it: round a loop of two (which
                # Router.child_sent breaks), not a detour's copy (that comes from elsewhere)
                self._loop_return(f, tick)
            return
        if f.hops + 1 > self.config.max_hops:
            self.counters["loop_drops"] += 1
            return
        self.counters["forwarded"] += 1
        self._emit(f._replace(hops=f.hops + 1, flags=f.flags & ~_ACK))

    def _loop_return(self, f: Raw, tick: int) -> None:
        """Send a frame that came back round a loop on once more, on the route chosen now.

        It is the frame's only copy: we handed it on with an acknowledgement and it went
        round instead of up (routes churn while a skin reboots after a broadcast RESET, and
        a boot's HELLO lost this way left the host unaware of the restart). CTP does the
        same (a looping packet is no duplicate). It goes on only once we have a parent again
        (else the loop would take it straight back: it waits in the queue like any frame),
        and the copy filter now holds its new hop count, so a second return needs another
        full loop; ``max_hops`` ends any circling."""
        self.seen.remember(f.origin, f.seq, f.hops, tick)
        if f.hops + 1 > self.config.max_hops:
            self.counters["loop_drops"] += 1
            return
        self.counters["loop_returns_forwarded"] += 1
        self._emit(f._replace(hops=f.hops + 1, flags=f.flags & ~_ACK))

    def _batch_slot(self) -> int:
        """When this bridge's aligned batch leaves after its close (cycles): its depth's slot
        (the deepest first) and its own offset within it (FirmwareConfig.depth_slot)."""
        c = self.config
        depth = min(self.router.hops, c.slot_depths) if self.router.has_route or c.gateway else c.slot_depths
        return (c.slot_depths - depth) * c.depth_slot + _stagger(c.bridge, c.slot_jitter)

    def _readout_sample(self, s: Sample, kept: bool, start: int) -> None:
        """A sample on mesh time (the sampler's readout hook): its state goes into the
        frame's record, due at this bridge's slot (its depth's: deepest first)."""
        c = self.config
        r = self.readout
        assert r is not None
        if not (c.gateway or self.router.has_route):
            self.counters["readout_no_route"] += 1  # nowhere to send it: the host sees no record of it
            if kept:  # (the reporter took it for sent: the frames after it would be unchanged from it)
                self.sampler.reporter.lost()
            return
        st = self.sampler.settings
        # a gateway's own element goes straight onto its line: it samples afresh at its line's
        # refresh, at no cost on the cells (its readout's refresh writes only a sample it
        # keeps as the reference of the frame's root and rate: none after a rate or root
        # change, and the element stayed unknown until its heartbeat)
        refresh = c.serial_refresh if c.gateway else c.cell_refresh
        if not kept and refresh > 0 and s.index % refresh == _stagger(self.me, refresh):
            kept = True
            self.sampler.reporter.sent(s)
            self.counters["readout_refreshed"] += 1
        state: State = ReadoutSample(self.me, s.c1, s.c2, s.flags & _OVERFLOWS) if kept else "u"
        depth = 0 if c.gateway else self.router.hops
        gates = st.measure_cycles()
        span = gates + r.slot(0)
        r.own(s.index, st.rate_hz, st.mode, st.oversampling if st.mode is Mode.ADC else 1, state,
              start + gates + r.slot(depth), span, self.sampler.root)

    def _readout_wait(self) -> int:
        """Cycles after its gate end this bridge's sample on the readout schedule may wait
        to be computed (the sampler's ``readout_wait``): 0 when its record goes at once (no
        child expected), else its depth's slot, the latest its record goes; a child's record
        coming earlier wakes the bridge, and the sample is computed then. The sample's
        values are the same whenever it is computed (the chip's noise is keyed by the gate's
        cycle, the capacitance is the one at the gate). 0 too when a child's record of the
        sample's frame came before its gate end (a child with a shorter gate): no later
        record need come, and the frame's record would wait for the next wake, whatever
        it is for."""
        r = self.readout
        s = self.sampler
        if r is None or not r.expects_children(s.settings.rate_hz):
            return 0
        if r.child_came_first(s.index, s.settings.rate_hz):
            return 0
        return r.slot(0 if self.config.gateway else self.router.hops)

    def _readout_rank(self) -> int:
        """The slots this bridge's records wait after the cell goes idle: twice its place
        among the neighbours it hears at its own depth (by id), so those neighbours' records
        of one frame follow each other instead of colliding, plus its depth's parity, so a
        parent and its child never take the same slot. (With the rank alone, a relay's
        record of frame k and its child's record of frame k + 1, both waiting for the same
        transmission's end at 250 Hz, started together: the child's was lost to the relay's
        half duplex, 54 of 65 such losses in 2 s of a 4x4.)"""
        me, hops = self.me, self.router.hops
        return 2 * sum(1 for n in self.router.table.values() if n.hops == hops and n.id < me) + (hops & 1)

    def _say_hello(self) -> None:
        c = self.config
        self._own(Hello(self.me, c.firmware, c.position[0], c.position[1], c.side, c.clock_hz, 3,
                        self.boots))

    @property
    def boots(self) -> int:
        """Power-ons and resets of this chip, this one included (kept in its non-volatile
        memory: ``resets`` at construction counts the lives before this one)."""
        return self.resets + 1

    def _own(self, message: Message) -> None:
        self._emit(own(message, self.me, self._next_seq()))

    def _emit(self, f: Raw) -> None:
        if self.config.gateway:
            self.serial_out += to_serial(build(f, self.me, ADDR_HOST))
            self.counters["serial_frames"] += 1
        elif not self.link.enqueue(f):
            self.counters["queue_full"] += 1

    # -- commands -------------------------------------------------------------------
    def _command(self, f: Frame, tick: int) -> None:
        if self.seen_cmd.is_duplicate(f.origin, f.seq):
            return
        target = f.dst
        if target != self.me:
            # controlled flooding: every bridge repeats a new command a few times at random
            # moments (a broadcast has no ACK; one lost copy must not cut a branch off)
            if len(self.floods) + len(_FLOOD_REPEATS) > _FLOOD_MAX:
                self.counters["flood_drops"] += 1  # a host flooding commands: bounded memory
            else:
                data = encode(Frame(self.me, target, f.origin, f.seq, f.payload, f.hops + 1, f.cost))
                self._last_flood = data
                for lo, hi in _FLOOD_REPEATS:
                    insort(self.floods, (tick + lo + self.rng.randrange(hi - lo), data), key=_when)
                self.counters["flooded"] += 1
        if target in (self.me, ADDR_BROADCAST):
            cmd: Command = f.payload  # type: ignore[assignment]  # the control frames that reach here are COMMANDs
            self.counters["commands"] += 1
            limit = self.max_gate if cmd.op is Op.SET_GATE else MAX_GATE
            reply, new = execute(cmd, self.sampler.settings, self.config.clock_hz, self.crystal.local(tick), limit)
            self._own(reply)
            if new is not None:
                for sample in self.sampler.apply(new, tick):
                    self._own(sample)
            if reply.op.name == "RESET" and reply.status == 0 and self.reset_at < 0:
                # reset once the reply has left (acknowledged by the next hop) and the
                # command's flood copies are sent, so the host hears the RESET was taken
                # and the rest of the mesh hears the command; at most _RESET_WAIT later
                self.reset_at = tick
                self._reset_by = tick + _RESET_WAIT
                self._reset_flood = self._last_flood if target != self.me else None

    # -- time -----------------------------------------------------------------------
    def advance(self, tick: int) -> tuple[bytes, tuple[int, ...]] | None:
        """Run every timer due at ``tick``; the (bytes, cells) to transmit now, if any."""
        # (runs at every wake of every bridge: the parts kept in locals, each asked in turn)
        readout = self.readout
        sampler = self.sampler
        if readout is not None:
            readout.at(tick)  # (the sampler asks it whether a sample waits for children)
        for data in sampler.advance(tick):
            self._own(data)
        if readout is not None:
            self._readout_at = -1
            # each record names the root its index counts (taken with the sample, or the
            # child's): stamped with the root followed now, a gateway at boot (its own root,
            # its children already on another's time) named their frames with its own root.
            # The root followed is its own sampling's while that is on the schedule: its
            # clock may follow a new root while its next gate is still planned on the old
            # one, and a frame of its children alone on the new root, passed on before that
            # gate's own frame, switched its line to the new root and back.
            for record in readout.take(tick, sampler.root if sampler.on_time and sampler.root else self.clock.root or 0):
                if self.config.gateway:
                    self._own(self._aged(record, tick))
                else:
                    self.link.enqueue_urgent(own(record, self.me, self._next_link_seq()), tick, self._readout_rank(),
                                             readout.until(record), (record.root, record.rate, record.index),
                                             record)
        while self.floods and self.floods[0][0] <= tick:
            self.link.broadcast(self.floods.pop(0)[1])
        beacon = False
        trickle = self.trickle
        if trickle.next_tick <= tick:
            beacon = trickle.advance(tick, force=not self.router.has_route)
        if self.time_beacon_at <= tick:
            local = self.crystal.local(tick)
            self.clock.tick(local)
            self.clock.next_round(local)
            self.time_beacon_at = tick + self.config.sync_period
            beacon = True
        if beacon:
            self.router.expire(tick)
            self._reroute(tick)
            self._send_beacon(tick)
        if 0 <= self.hello_at <= tick:
            if self.seq == 0:
                # the numbering wrapped: a HELLO numbered 0 is the evidence of a restart
                # (docs/protocol.md §7), so a periodic one waits for the next number
                self.hello_at = tick + _MS
            else:
                self._say_hello()
                self.hello_at = tick + self.config.hello_period
        if self.status_at <= tick:
            self._status(tick)
            self.status_at = tick + self.config.status_period
        if 0 <= self.reset_at <= tick and tick < self._reset_by and self._reset_pending():
            self.reset_at = tick + _MS  # look again soon
        elif 0 <= self.reset_at <= tick:
            self.resets += 1
            self.counters["command_resets"] += 1
            self.power_off()
            self._past += self._life_totals()
            self._power_on(tick)
            readout = self.readout
        r = self.router
        link = self.link
        p = r.table.get(r.parent) if r.parent is not None else None
        if p is not None:
            out, used = link.advance(tick, p.id, self._link_candidate(), int(round(p.link_etx)), r.table)
        else:
            out, used = link.advance(tick, None, self._link_candidate(), PERFECT_LINK, r.table)
        if used:  # a bundle took the link number
            self._next_link_seq()
        if link.urgent_results:
            if readout is not None:
                for ok in link.urgent_results:
                    readout.sent(ok)
            link.urgent_results.clear()
        if link.results:
            for nbr, attempts, ok in link.results:
                r.on_link_result(nbr, attempts, ok, tick)
            link.results.clear()
            self._reroute(tick)
        return out

    def _aged(self, record: Readout, tick: int) -> Readout:
        """A gateway's record as it goes on the serial line, with its age: mesh time since
        its frame's gate start (the host times the frame by it, not by how long the whole
        readout took). Left unsaid without mesh time, or when the record counts another
        root's time than the one this bridge follows."""
        root = self.clock.root or 0
        if not self.timebase.synced(tick) or record.root != root:
            return record
        now = self.clock.global_at(self.crystal.local(tick))
        age = (now - record.index * self.config.clock_hz // record.rate) * 1_000_000 // self.config.clock_hz
        return replace(record, age_us=age) if 0 < age <= 0xFFFF_FFFF else record

    def _reset_pending(self) -> bool:
        """Whether frames (the RESET's reply among them) or the RESET's flood copies are
        still waiting to leave."""
        flood = self._reset_flood
        link = self.link
        if link.queue or link.inflight is not None:
            return True
        if flood is not None and (any(d is flood for _, d in self.floods)
                                  or any(d is flood for d in link.broadcasts)):
            return True
        return False

    def _status(self, tick: int) -> None:
        r = self.router
        if not r.gateway and r.parent is None:
            return
        nbrs = tuple(Neighbour(n.id, min(0xFFFF, int(round(n.link_etx)))) for n in list(r.table.values())[:32])
        self._own(BridgeStatus(0 if r.parent is None else r.parent, min(r.path_etx, 0xFFFF), nbrs,
                               self.link.counters["queue_drops"], self.link.counters["retries"],
                               self.resets, tick - self.boot_tick))


__all__ = ["FIRMWARE_VERSION", "Firmware", "FirmwareConfig"]
