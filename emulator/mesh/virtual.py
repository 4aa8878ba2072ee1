"""Virtual time: every chip, the medium and the world in one process, one event queue.

Events are ordered by (tick, priority, seq): transmissions end before faults apply,
faults before firmware timers, and ``seq`` breaks the remaining ties in the order
events were made, so a run is a pure function of the mesh, the scenario and the
seed. ``run`` returns what reached each gateway's serial line and every counter.

By default the bridges and the medium talk without delay, as one chip's wire would.
``latency=Latency(...)`` models what a real-time mesh (one process per bridge, the medium
relaying datagrams) adds, still deterministically from its own seed: a transmission
reaches the medium a little after the bridge started it, carrier reports and deliveries
reach a bridge a little after the medium made them (the medium starts a transmission its
sender began on a cell already busy when the cell is free, as the real-time medium's
carrier arbiter does), and a bridge wakes for a timer at the next millisecond at best
(``poll`` takes milliseconds; a shorter wait is slept exactly) and later still under load.
It exists so that what the real-time mesh does can be reproduced and tested here, including
a bridge process the host holds up (:meth:`VirtualMesh.hold`, as ``SIGSTOP``/``SIGCONT`` do).
"""

from __future__ import annotations

import heapq
import math
import random
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from cellbridge.emulator.chip.chip import Chip, ChipConfig
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.firmware import Firmware, FirmwareConfig
from cellbridge.emulator.firmware.transceiver import TransceiverConfig
from cellbridge.emulator.medium.carrier_arbiter import CarrierArbiter
from cellbridge.emulator.medium.medium import Medium, Transmission
from cellbridge.emulator.mesh.mesh import Mesh
from cellbridge.emulator.world.world import Contact, World
from cellbridge.protocol import Data, Frame, FrameType, Readout, Sample, StreamDecoder, encode_stream

CLOCK_HZ = 50_000_000
_STATES = frozenset({"has_route", "queue_len", "resets"})  # counters that are states, not totals
_FINISH, _FAULT, _MSG, _WAKE = 0, 1, 2, 3


@dataclass(frozen=True)
class Latency:
    """Delays of a real-time mesh, in seconds (each drawn from an exponential with this
    mean on top of ``floor``). Messages between one bridge and the medium keep their
    order, as on one socket."""

    up: float = 0.0005  #: a transmission's message, bridge -> medium
    down: float = 0.0005  #: a carrier report or delivery, medium -> bridge
    floor: float = 0.0001  #: least delay of any message
    #: a timer's wait is rounded up to this (poll's milliseconds); a shorter one is slept
    #: for exactly, as the bridge process does
    wake_grain: float = 0.001
    wake_late: float = 0.0003  #: mean extra lateness of a wake (scheduling)
    seed: int = 0


def default_chip(bridge: int, seed: int) -> Chip:
    """The bridge's cycle-exact chip, its crystal offset drawn from the mesh seed."""
    chip_seed = seed * 65_537 + bridge
    return Chip(ChipConfig().with_random_crystal(chip_seed), seed=chip_seed)


@dataclass
class MeshResult:
    """What a run produced: frames per gateway (as the host would read them) and counters."""

    gateway_frames: dict[int, list[Frame]]
    counters: dict[int, dict[str, int]]
    medium: dict[str, int]
    cut_off: list[int]  #: live bridges without a route at the end
    parents: dict[int, int | None]
    seconds: float
    serial_bytes: dict[int, int] = field(default_factory=dict)

    def delivered(self) -> list[tuple[int, int, int, Frame]]:
        """(origin, boot, seq, frame) of every frame at every gateway, in each gateway's order.

        A bridge numbers from 0 again after a reset and says so with a HELLO numbered 0, so
        (origin, seq) repeats across boots; ``boot`` counts those HELLOs per origin. In a
        long run the numbering also wraps from 65535 to 0: ``seq`` is counted on past the
        wrap (serial-number arithmetic against the highest seen), so (origin, boot, seq)
        names one frame however long the run."""
        out = []
        for frames in self.gateway_frames.values():
            boots: dict[int, int] = {}
            highest: dict[int, int] = {}  # origin -> highest extended seq of this boot
            for f in frames:
                o = f.origin
                if f.type is FrameType.HELLO and f.seq == 0:
                    boots[o] = boots.get(o, -1) + 1
                    highest[o] = 0
                top = highest.get(o, f.seq)
                ahead = (f.seq - top) & 0xFFFF
                seq = top + ahead if ahead < 0x8000 else top - (0x10000 - ahead)
                highest[o] = max(top, seq)
                out.append((o, boots.get(o, 0), seq, f))
        return out

    def samples(self) -> dict[int, list]:
        """origin -> every sample delivered to any gateway (duplicates across gateways removed).

        A sample is named by (origin, element, cycle): in virtual time a chip's cycle counter
        runs on across restarts, so this holds where (origin, boot, seq) cannot (a bridge
        that restarted while routed to one gateway and then moved to another: the second
        gateway never saw the HELLO, and its boot count lags)."""
        seen: set[tuple[int, int, int]] = set()
        out: dict[int, list] = {}
        for frames in self.gateway_frames.values():
            for f in frames:
                if isinstance(f.payload, Data):
                    for x in f.payload.samples:
                        key = (f.origin, x.element, x.cycle)
                        if key not in seen:
                            seen.add(key)
                            out.setdefault(f.origin, []).append(x)
                elif f.type is FrameType.READOUT:
                    r: Readout = f.payload  # type: ignore[assignment]  # a READOUT frame's payload
                    cycle = r.index * CLOCK_HZ // r.rate  # the frame's global gate start: a record has no cycles
                    for y in r.samples:
                        key = (y.bridge, -1 - r.rate, r.index)  # readout samples are named by their frame
                        if key not in seen:
                            seen.add(key)
                            out.setdefault(y.bridge, []).append(Sample(0, cycle, y.c1, y.c2, y.flags, r.index))
        return out

    def total(self, name: str) -> int:
        return sum(c.get(name, 0) for c in self.counters.values())


class VirtualMesh:
    def __init__(self, mesh: Mesh, seed: int = 0, world: World | None = None,
                 settings: Settings = Settings(), chip: Callable[[int, int], object] = default_chip,
                 latency: Latency | None = None, random_epochs: bool = False, prefetch: int = 0,
                 **firmware: object) -> None:
        self.mesh = mesh
        #: After a wake that took a sample, the chip computes the next ``prefetch`` samples'
        #: counts at once, as a real-time bridge process does (``PREFETCH`` in
        #: emulator/realtime/process_bridge.py): the same counts, so the same skin, at what
        #: the bridge processes' chip work costs (0: each count when its sample is taken)
        self.prefetch = prefetch
        #: chips whose cycle counters started at unrelated moments (as after separate power-ons):
        #: sample cycles are then far from the virtual ticks, and mesh time must find the offsets
        self.random_epochs = random_epochs
        self.seed = seed
        self.world = world or World(mesh)
        self.settings = settings
        self._chip = chip
        self._fw_kw = firmware
        self.medium = Medium(mesh, seed)
        self.tick = 0
        # (tick, prio, seq, item): item is a bridge id (_WAKE), a Transmission (_FINISH) or
        # (bridge, action) (_MSG)
        self._heap: list[tuple[int, int, int, Any]] = []
        self._seq = 0
        self._wake: dict[int, int] = {}
        self.latency = latency
        if latency is not None:
            self._lat_rng = random.Random(latency.seed * 7_919 + seed)
            self._wanted: dict[int, int] = {}  # bridge -> timer tick its pending wake is for
            self._up_last: dict[int, int] = {}  # bridge -> arrival of its last message at the medium
            self._down_last: dict[int, int] = {}  # bridge -> arrival of its last message from it
            self._arbiter = CarrierArbiter(self.medium.bit_cycles)
            self._arbiter.counters = self.medium.counters
        self._holds: dict[int, list[tuple[int, int]]] = {}  # bridge -> (start, end) ticks it is held up
        self.nodes: dict[int, Firmware] = {}
        self.resets: Counter[int] = Counter()
        self.serial: dict[int, bytearray] = {g: bytearray() for g in mesh.gateways}
        #: what each gateway wrote to its serial line, as (tick, bytes) in order: a host's reads
        self.serial_chunks: dict[int, list[tuple[int, bytes]]] = {g: [] for g in mesh.gateways}
        self.decoders: dict[int, StreamDecoder] = {g: StreamDecoder() for g in mesh.gateways}
        self.frames: dict[int, list[Frame]] = {g: [] for g in mesh.gateways}
        self.dead: set[int] = set()
        self._retired: dict[int, Counter[str]] = {b: Counter() for b in mesh.ids}
        for b in mesh.ids:
            self._boot(b, 0)

    # -- set-up and faults ----------------------------------------------------------
    def _config(self, b: int) -> FirmwareConfig:
        br = self.mesh.bridge(b)
        kw = dict(self._fw_kw)
        kw.setdefault("readout_depths", self.mesh.readout_depths())
        if self.random_epochs:
            kw.setdefault("clock_epoch", random.Random(self.seed * 131_071 + b).randrange(1 << 40))
        return FirmwareConfig(b, br.cells, br.gateway, br.position, self.mesh.side, settings=self.settings,
                              transceiver=TransceiverConfig(bit_cycles=CLOCK_HZ // self.mesh.bitrate),
                              **kw)  # type: ignore[arg-type]  # VirtualMesh's firmware keywords, checked by FirmwareConfig

    def _boot(self, b: int, tick: int) -> None:
        self.nodes[b] = Firmware(self._config(b), self._chip(b, self.seed), self.world.sense_for(b),
                                 self.seed, tick, self.resets[b])
        fw = self.nodes[b]
        # a gateway's power-on HELLO is on its serial line at once, not at its first timer
        self._schedule(b, tick if fw.serial_out else fw.next_tick)

    def _push(self, tick: int, prio: int, item: object) -> None:
        self._seq += 1
        heapq.heappush(self._heap, (tick, prio, self._seq, item))

    def _delay(self, mean: float) -> int:
        lat = self.latency
        assert lat is not None
        return int((lat.floor + (self._lat_rng.expovariate(1.0 / mean) if mean > 0 else 0.0)) * CLOCK_HZ)

    def _schedule(self, b: int, t: int) -> None:
        if t < self.tick:
            t = self.tick
        lat = self.latency
        if lat is not None:  # woken at the next poll granule after the timer, and a bit later
            if self._wanted.get(b) == t and b in self._wake:
                return
            self._wanted[b] = t
            wait = t - self.tick
            if wait > 0:
                grain = int(lat.wake_grain * CLOCK_HZ)
                if wait >= grain > 0:  # a shorter wait is slept for exactly (the shell does)
                    wait = math.ceil(wait / grain) * grain
                if lat.wake_late > 0:
                    wait += int(self._lat_rng.expovariate(1.0 / lat.wake_late) * CLOCK_HZ)
            t = self.tick + wait
            if self._holds:
                t = self._held_until(b, t)
        if self._wake.get(b) != t:
            self._wake[b] = t
            self._push(t, _WAKE, b)

    def at(self, seconds: float, action: Callable[[], None]) -> None:
        """Run ``action`` at a virtual time (faults, commands, presses); at the current
        tick if the mesh has already passed it (virtual time does not run backwards: run
        at its own tick, the action would stamp what it makes the gateways send before
        what they have sent, and :meth:`next_event` would name a tick in the past)."""
        self._push(max(int(seconds * CLOCK_HZ), self.tick), _FAULT, action)

    def kill(self, bridge: int, at: float) -> None:
        def do() -> None:
            self.dead.add(bridge)
            self.medium.kill(bridge)
            if self.latency is not None:
                self._wanted.pop(bridge, None)
            old = self.nodes.pop(bridge)
            old.power_off()
            self._retired[bridge].update(old.counters_snapshot())
            self._wake.pop(bridge, None)
        self.at(at, do)

    def restart(self, bridge: int, at: float) -> None:
        def do() -> None:
            if bridge in self.nodes:  # a running bridge is power-cycled
                self.nodes[bridge].power_off()
                self._retired[bridge].update(self.nodes[bridge].counters_snapshot())
            self.dead.discard(bridge)
            self.medium.revive(bridge)
            self.resets[bridge] += 1
            self._boot(bridge, self.tick)
        self.at(at, do)

    def hold(self, bridge: int, at: float, seconds: float) -> None:
        """Hold ``bridge``'s process up from ``at`` for ``seconds`` of virtual time, as a
        loaded host (or ``SIGSTOP`` then ``SIGCONT``) does to a real-time shell's bridge: it
        runs nothing meanwhile, and its timers and the medium's messages to it wait for the
        end, in order. Only with ``latency`` (without it the bridges are chips, not processes)."""
        if self.latency is None:
            raise ValueError("a bridge is held up only in a real-time model (latency=Latency(...))")
        start = int(at * CLOCK_HZ)
        self._holds.setdefault(bridge, []).append((start, start + int(seconds * CLOCK_HZ)))

    def _held_until(self, bridge: int, tick: int) -> int:
        """The end of a hold of ``bridge`` that ``tick`` falls in (else ``tick``)."""
        for start, end in self._holds.get(bridge, ()):
            if start <= tick < end:
                return end
        return tick

    def cut(self, cell: int, at: float) -> None:
        self.at(at, lambda: self.medium.cut_cell(cell))

    def press(self, contact: Contact) -> None:
        self.world.press(contact)

    def host_write(self, gateway: int, frame: Frame, at: float) -> None:
        """The host writes ``frame`` (e.g. a CMD) to a gateway's serial line at ``at``."""
        data = encode_stream(frame)

        def do() -> None:
            if gateway in self.nodes:
                self.nodes[gateway].serial_in(data, self.tick)
                self._run(gateway)
        self.at(at, do)

    # -- the loop -------------------------------------------------------------------
    def _run(self, b: int) -> None:
        fw = self.nodes[b]
        tick = self.tick
        taken = fw.counters["samples"]
        out = fw.advance(tick)
        if self.prefetch and fw.counters["samples"] > taken:
            fw.sampler.prefetch(self.prefetch)
        if out is not None:
            if self.latency is None:
                self._start(b, out[0], out[1])
            else:  # the medium starts it when the message arrives
                at = max(tick + self._delay(self.latency.up), self._up_last.get(b, 0))
                self._up_last[b] = at
                data, cells = out
                self._push(at, _FAULT, lambda: self._heard(b, data, cells, tick))
        if fw.serial_out:
            self._gateway_out(b, fw.take_serial())
        nt = fw.next_tick
        self._schedule(b, nt if nt > tick else tick + 1)

    def _heard(self, b: int, data: bytes, cells: tuple[int, ...], sent: int) -> None:
        """The medium hears of a transmission ``b`` started at ``sent`` (as the real-time
        medium does: its carrier arbiter starts it now or when the cells are free)."""
        at = self._arbiter.admit(cells, sent, self.tick, self.medium.airtime(len(data)))
        if at > self.tick:
            self._push(at, _FAULT, lambda: self._start(b, data, cells, sent))
        else:
            self._start(b, data, cells, sent)

    def _start(self, b: int, data: bytes, cells: tuple[int, ...], sent: int = -1) -> None:
        tick = self.tick
        tx = self.medium.start(b, data, cells, tick, sent)
        self._push(tx.end, _FINISH, tx)
        for r, cell in tx.receivers:
            if self.latency is None:
                self.nodes[r].carrier(cell, tick, tx.end)
            else:
                self._down(r, lambda fw, cell=cell: fw.carrier(cell, tick, tx.end))

    def _down(self, b: int, action: Callable[..., object]) -> None:
        """A message from the medium reaches ``b`` later (in order); ``b`` then wakes."""
        assert self.latency is not None
        at = max(self.tick + self._delay(self.latency.down), self._down_last.get(b, 0))
        if self._holds:
            at = self._held_until(b, at)
        self._down_last[b] = at
        self._push(at, _MSG, (b, action))

    def _gateway_out(self, b: int, data: bytes) -> None:
        self.serial[b] += data
        self.serial_chunks[b].append((self.tick, data))
        self.frames[b].extend(self.decoders[b].feed(data))

    def next_event(self) -> int | None:
        """The tick of the next thing the mesh does (a bridge's wake, a transmission's end,
        a message), None when nothing is planned: a caller that paces the mesh to a clock
        sleeps until then and :meth:`advance_to` it (``bench/bench_skin_cpu_split.py``)."""
        return self._heap[0][0] if self._heap else None

    def run(self, seconds: float) -> MeshResult:
        """Advance virtual time by ``seconds``; the result covers the whole run so far."""
        self.advance_to(self.tick + int(seconds * CLOCK_HZ))
        return self.result()

    def advance_to(self, end: int) -> None:
        """Run everything due up to tick ``end`` (at or after the current tick), without
        building a result: for a caller that advances the mesh in many small steps (the
        result copies every frame each gateway sent so far).

        Raises ValueError for an ``end`` before the current tick: virtual time does not
        run backwards (the mesh would stamp what it sends next before what it has sent)."""
        if end < self.tick:
            raise ValueError(f"tick {end} is before the mesh's current tick {self.tick}: virtual time does not run backwards")
        heap = self._heap
        nodes = self.nodes
        while heap and heap[0][0] <= end:
            tick, prio, _, item = heapq.heappop(heap)
            self.tick = tick
            if prio == _WAKE:
                if self._holds and self._held_until(item, tick) != tick:  # (planned before the hold was)
                    if self._wake.get(item) == tick:
                        self._wake[item] = self._held_until(item, tick)
                        self._push(self._wake[item], _WAKE, item)
                    continue
                if self._wake.get(item) == tick and item in nodes:
                    del self._wake[item]
                    if self.latency is not None:
                        self._wanted.pop(item, None)
                    self._run(item)
            elif prio == _FINISH:
                tx: Transmission = item
                for r, cell, data in self.medium.finish(tx):
                    if self.latency is not None:
                        self._down(r, lambda fw, data=data, cell=cell, sof=tx.sent:
                                   fw.receive(data, self.tick, cell, sof))
                        continue
                    fw = nodes.get(r)
                    if fw is not None and fw.receive(data, tick, cell):
                        self._run(r)
            elif prio == _MSG:
                r, action = item
                if self._holds and self._held_until(r, tick) != tick:  # (sent before the hold was planned)
                    self._push(self._held_until(r, tick), _MSG, item)
                    continue
                fw = nodes.get(r)
                if fw is not None:  # a real-time bridge runs its timers at every wake
                    action(fw)
                    self._run(r)
            else:
                item()
        self.tick = end

    def time_errors(self, root: int) -> dict[int, float]:
        """Each bridge with a mesh-time fit: |its global time − ``root``'s| now, in µs."""
        r = self.nodes[root]
        g0 = r.clock.global_at(r.crystal.local(self.tick))
        return {b: abs(fw.clock.global_at(fw.crystal.local(self.tick)) - g0) * 1e6 / CLOCK_HZ
                for b, fw in self.nodes.items() if b != root and fw.clock.has_fit()}

    def parents(self) -> dict[int, int | None]:
        """Each live bridge's parent on its route now (None: a gateway, or no route)."""
        return {b: fw.router.parent for b, fw in self.nodes.items()}

    def children(self) -> dict[int, set[int]]:
        """Each live bridge's children on the routes now (a leaf: an empty set)."""
        out: dict[int, set[int]] = {b: set() for b in self.nodes}
        for b, p in self.parents().items():
            if p is not None and p in out:
                out[p].add(b)
        return out

    def result(self) -> MeshResult:
        counters = {}
        for b in self.mesh.ids:
            # events add up over a bridge's lives; states are those of the live one (or none)
            c = Counter({k: v for k, v in self._retired[b].items() if k not in _STATES})
            c.update(self.nodes[b].counters_snapshot() if b in self.nodes else
                     {"has_route": 0, "queue_len": 0, "resets": self.resets[b]})
            c["alive"] = int(b in self.nodes)
            counters[b] = dict(c)
        parents = self.parents()
        cut_off = sorted(b for b, fw in self.nodes.items() if not fw.router.has_route)
        return MeshResult({g: list(f) for g, f in self.frames.items()}, counters, dict(self.medium.counters),
                          cut_off, parents, self.tick / CLOCK_HZ,
                          {g: len(s) for g, s in self.serial.items()})


__all__ = ["CLOCK_HZ", "Latency", "MeshResult", "VirtualMesh", "default_chip"]
