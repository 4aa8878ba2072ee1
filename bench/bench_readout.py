"""The scheduled readout in virtual time: schedule, latency, completeness, traffic.

Run: ``.venv/bin/python bench/bench_readout.py [--quick]`` (or ``make bench``). Prints:

1. the schedule (``FirmwareConfig.readout_depths`` levels of ``readout_window`` after the
   gates) for 4x4 and 8x8 grids at 100 and 250 Hz, and what a frame took from its gate
   start to its gateway's record on the serial line (p50, p99; records go on as soon as
   they are complete, the slots bound them);
2. frames complete at the gateways (every element a sample or unchanged) and element-frames
   known, on a periodic 8x8 at 250 Hz with four gateways (one per quadrant), lossless and
   with 1 % frame loss on every hop, measured once every bridge is on the schedule; with the
   losses that matter on the cells (``collision_at_addressee``, ``half_duplex_at_addressee``:
   a record spoilt for the bridge it was sent to), records that failed after their retries,
   and records a gateway wrote after a later frame's ("behind": the host reads them as lost);
   before it, the cells' capacity: the airtime the busiest relay needs per frame (its
   subtree's samples in and out, half duplex) for one gateway and for four;
3. event-based traffic against periodic on a 4x4 at 100 Hz, idle and with four moving
   presses: bits put on the cells, and record bytes on the gateway's serial line; and what
   a leaf's record of one frame costs on its cell with a sample, unchanged, and unchanged as
   a READOUT_SAME (no acknowledgement, three payload bytes: every frame has one record from
   every bridge either way, so the frame's fixed cost bounds the ratio);
4. delivered sample bits at the gateway over the raw bitrate of one of its cells, at
   250 Hz on grids with the gateway in a corner (two cells) and in the middle (four), and
   the ceiling of that share for full frames (the header, the record's own fields, the
   preamble, DIFS and the acknowledgement cost what they cost).

The readings are the emulator's own (its chip and world models); no figure here depends on
the daemon.
"""

from __future__ import annotations

import argparse
import math
import time
from collections import Counter, defaultdict

import numpy as np
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.readout import _split
from cellbridge.emulator.firmware.reporting import ReportingMode
from cellbridge.emulator.firmware.transceiver import PREAMBLE_BITS, TransceiverConfig
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh
from cellbridge.emulator.world.world import Contact, World
from cellbridge.protocol import (
    CRC_LEN,
    HEADER_LEN,
    FrameType,
    Mode,
    Readout,
    ReadoutSame,
    ReadoutSample,
    StreamDecoder,
)
from cellbridge.protocol.messages import pack_payload

WINDOW = 6 * CLOCK_HZ // 1000  # FirmwareConfig.readout_window's default
SAMPLE_BYTES = 13  # a sample in a READOUT record: [bridge, c1, c2, flags] (c1, c2 uint32)


def records(vm: VirtualMesh, gateway: int) -> list[tuple[int, Readout]]:
    """(tick written, record) of every READOUT the gateway wrote on its serial line."""
    dec = StreamDecoder()
    out = []
    for tick, chunk in vm.serial_chunks[gateway]:
        for f in dec.feed(chunk):
            if isinstance(f.payload, Readout):
                out.append((tick, f.payload))
    return out


def schedule(quick: bool) -> None:
    print("1. readout schedule and gate start -> gateway serial (virtual time, periodic, the grid's default gateway)")
    print(f"{'skin':<9} {'Hz':>4} {'levels':>6} {'window ms':>9} {'span ms':>8} {'p50 ms':>7} {'p99 ms':>7} "
          f"{'max ms':>7}")
    for n in (4, 8):
        mesh = meshgen.grid(n, n)
        for rate in (100, 250):
            secs = 4.0 if quick else 8.0
            vm = VirtualMesh(mesh, seed=1, settings=Settings(rate_hz=rate), readout=True)
            vm.run(secs)
            g = mesh.gateways[0]  # (the grid's default gateway: its centre bridge)
            gw = vm.nodes[g]
            depths = mesh.readout_depths()
            span = (4 * CLOCK_HZ // 1000 + depths * WINDOW) / CLOCK_HZ * 1000
            lat = [(t - gw.timebase.gate_tick(r.index, rate)) / CLOCK_HZ * 1000 for t, r in records(vm, g)
                   if r.index >= rate * secs / 2]
            a = np.array(lat) if lat else np.array([np.nan])
            print(f"{mesh.name:<9} {rate:>4} {depths:>6} {WINDOW / CLOCK_HZ * 1000:>9.1f} {span:>8.1f} "
                  f"{np.percentile(a, 50):>7.2f} {np.percentile(a, 99):>7.2f} {a.max():>7.2f}")


def capacity() -> None:
    print("\n2a. airtime the busiest relay needs per frame at least, 8x8 at 250 Hz: a gateway's neighbours "
          "share its other bridges, at best evenly;\n    a relay (half duplex) takes its subtree's samples in and "
          "sends them and its own on (13 bytes each; no headers, acknowledgements or gaps)")
    print(f"{'gateways':<16} {'neighbours':>10} {'subtree >=':>10} {'ms per frame >=':>15} {'period ms':>9} {'fits':>5}")
    for gws in ((1,), (28,), (10, 14, 42, 46)):
        mesh = meshgen.grid(8, 8, gateways=gws)
        nbrs = {x for g in gws for c in mesh.bridge(g).cells for x in mesh.members()[c]} - set(gws)
        sub = math.ceil((len(mesh.bridges) - len(gws)) / len(nbrs))
        need = (2 * sub - 1) * SAMPLE_BYTES * 8 / mesh.bitrate * 1000
        print(f"{','.join(map(str, gws)):<16} {len(nbrs):>10} {sub:>10} {need:>15.2f} {1000 / 250:>9.1f} "
              f"{'yes' if need < 4.0 else 'NO':>5}")


def completeness(quick: bool) -> None:
    gws = (10, 14, 42, 46)
    print(f"\n2b. frames complete at the gateways, periodic 8x8 at 250 Hz, gateways {gws} (one per quadrant), "
          "once every bridge is on the schedule")
    print(f"{'loss/hop':>8} {'frames':>7} {'complete':>9} {'element-frames':>14} {'known':>8} {'missing':>8} "
          f"{'coll.@addr':>10} {'h-dup@addr':>10} {'failed':>7} {'behind':>6} {'target':>7}")
    for loss in (0.0, 0.01):
        mesh = meshgen.grid(8, 8, gateways=gws, loss=loss)
        warm, secs = (12.0, 2.0) if quick else (14.0, 5.0)  # mesh time reaches the last bridges in ~10 s
        vm = VirtualMesh(mesh, seed=2, settings=Settings(rate_hz=250), readout=True)
        t0 = time.perf_counter()
        vm.run(warm)
        n0 = {g: len(vm.serial_chunks[g]) for g in gws}
        m0 = Counter(vm.medium.counters)
        f0 = sum(fw.counters.get("readout_failed", 0) for fw in vm.nodes.values())
        vm.run(secs)
        wall = time.perf_counter() - t0
        by: dict[int, Counter[str]] = defaultdict(Counter)
        behind = 0  # records written after a later frame's on the same line: the host takes them for lost
        for g in gws:
            dec = StreamDecoder()
            newest = -1
            for _, chunk in vm.serial_chunks[g][n0[g]:]:
                for f in dec.feed(chunk):
                    if f.type is FrameType.READOUT:
                        r: Readout = f.payload  # type: ignore[assignment]  # a READOUT frame's payload
                        by[r.index].update(s=len(r.samples), u=len(r.unchanged), m=len(r.missing))
                        if r.part == 0:
                            behind += r.index <= newest
                            newest = max(newest, r.index)
        ks = sorted(by)[2:-30]  # whole frames of the window (the first ones began before it)
        total = len(ks) * 64
        known = sum(min(64, by[k]["s"] + by[k]["u"]) for k in ks)
        full = sum(1 for k in ks if by[k]["s"] + by[k]["u"] >= 64)
        med = {k: vm.medium.counters.get(k, 0) - m0.get(k, 0) for k in ("collision_at_addressee",
                                                                          "half_duplex_at_addressee")}
        failed = sum(fw.counters.get("readout_failed", 0) for fw in vm.nodes.values()) - f0
        print(f"{loss:>8.0%} {len(ks):>7} {full / max(1, len(ks)):>9.2%} {total:>14} {known / max(1, total):>8.3%} "
              f"{total - known:>8} {med['collision_at_addressee']:>10} {med['half_duplex_at_addressee']:>10} "
              f"{failed:>7} {behind:>6} {'99.9%':>7}   ({warm:g}+{secs:g} s virtual in {wall:.0f} s)")


def traffic(quick: bool) -> None:
    print("\n3. event-based against periodic, 4x4 at 100 Hz (virtual time, 5 s after 3 s; corner gateway 1)")
    print(f"{'skin':<8} {'cell kbit/s per.':>16} {'event':>8} {'ratio':>6} {'serial B/s per.':>15} {'event':>8} "
          f"{'ratio':>6}")
    mesh = meshgen.grid(4, 4, gateways=(1,))  # (the figures before the grid's default gateway moved to its centre)
    moving = [Contact(0.0, 100.0, 0.0, 0.02 * k + 0.01, 2.0, 0.02, vx=0.03, vy=0.0) for k in range(4)]
    for label, contacts in (("idle", []), ("pressed", moving)):
        bits, serial = {}, {}
        for periodic in (True, False):
            mode = ReportingMode() if periodic else ReportingMode(40, 1000)
            vm = VirtualMesh(mesh, seed=3, world=World(mesh, list(contacts)), settings=Settings(reporting=mode), readout=True)
            vm.run(3.0)
            b0 = vm.medium.counters.get("bits", 0)
            n0 = len(vm.serial_chunks[1])
            vm.run(5.0 if not quick else 2.0)
            secs = 5.0 if not quick else 2.0
            bits[periodic] = (vm.medium.counters.get("bits", 0) - b0) / secs / 1000
            serial[periodic] = sum(len(c) for _, c in vm.serial_chunks[1][n0:]) / secs
        print(f"{label:<8} {bits[True]:>16.0f} {bits[False]:>8.0f} {bits[False] / bits[True]:>6.1%} "
              f"{serial[True]:>15.0f} {serial[False]:>8.0f} {serial[False] / serial[True]:>6.1%}")
    # What bounds the ratio: every frame, each leaf sends a record either way. A whole one
    # costs its header, its own fields and an acknowledgement beside the sample or id it
    # carries; one in which nothing changed goes as a READOUT_SAME (the parent acknowledged
    # the record it repeats): a header, three payload bytes, no acknowledgement.
    tc = TransceiverConfig()
    ack = 8 * 24 + PREAMBLE_BITS + tc.sifs_bits

    def airtime(r: Readout | ReadoutSame, acked: bool = True) -> int:
        return 8 * (HEADER_LEN + CRC_LEN + len(pack_payload(r))) + PREAMBLE_BITS + tc.difs_bits + (ack if acked else 0)

    sampled = airtime(Readout(10**5, 100, Mode.COUNTER, 1, (ReadoutSample(7, 19_600, 15_800, 0),), (), (), 52_000))
    unchanged = airtime(Readout(10**5, 100, Mode.COUNTER, 1, (), (7,), (), 52_000))
    same = airtime(ReadoutSame(1, 0), acked=False)
    print(f"a leaf's record of one frame, with its acknowledgement and gaps: {sampled} bits with its sample, "
          f"{unchanged} unchanged ({unchanged / sampled:.0%}); header, CRC, record fields, preamble, DIFS and "
          f"acknowledgement {airtime(Readout(10**5, 100, Mode.COUNTER, 1, ()))} bits of either; unchanged as a "
          f"READOUT_SAME, with its gaps, {same} ({same / sampled:.0%})")


def efficiency(quick: bool) -> None:
    print("\n4. sample bits delivered at the gateway, 250 Hz, over one of its cells' raw bitrate")
    print(f"{'skin':<12} {'gateway cells':>13} {'sample kbit/s':>13} {'share of one cell':>17} {'target':>7}")
    for mesh, gw in ((meshgen.grid(8, 8, gateways=(1,)), 1), (meshgen.grid(8, 8, gateways=(28,)), 28)):
        vm = VirtualMesh(mesh, seed=4, settings=Settings(rate_hz=250), readout=True)
        vm.run(6.0)
        n0 = len(vm.serial_chunks[gw])
        secs = 2.0 if quick else 4.0
        vm.run(secs)
        dec = StreamDecoder()
        sample_bits = 0
        for _, chunk in vm.serial_chunks[gw][n0:]:
            for f in dec.feed(chunk):
                if f.type is FrameType.READOUT and f.origin == gw:
                    r: Readout = f.payload  # type: ignore[assignment]  # a READOUT frame's payload
                    # the bits of the samples that crossed the gateway's cells (not its own)
                    own = Readout(r.index, r.rate, r.mode, r.oversampling,
                                  tuple(s for s in r.samples if s.bridge != gw))
                    empty = Readout(r.index, r.rate, r.mode, r.oversampling, ())
                    sample_bits += 8 * (len(pack_payload(own)) - len(pack_payload(empty)))
        cells = len(mesh.bridge(gw).cells)
        rate = sample_bits / secs
        print(f"{mesh.name + ('/' + str(gw)):<12} {cells:>13} {rate / 1000:>13.0f} {rate / mesh.bitrate:>17.1%} "
              f"{'90%':>7}")
    # the ceiling: a record part filled with samples, its acknowledgement, DIFS and SIFS
    big = Readout(10**6, 250, Mode.COUNTER, 1, tuple(ReadoutSample(b, 10**6, 2 * 10**6, 0) for b in range(1, 65)),
                  (), (), 100_000)
    first = _split(big)[0]
    n = len(first.samples)
    empty = Readout(first.index, first.rate, first.mode, first.oversampling, ())
    payload = 8 * (len(pack_payload(first)) - len(pack_payload(empty)))
    tc = TransceiverConfig()
    frame_bits = 8 * (HEADER_LEN + CRC_LEN + len(pack_payload(first))) + PREAMBLE_BITS
    ack_bits = 8 * 24 + PREAMBLE_BITS + tc.sifs_bits
    print(f"{'ceiling':<12} {'-':>13} {'-':>13} {payload / (frame_bits + tc.difs_bits + ack_bits):>17.1%} {'90%':>7}"
          f"   (a full part: {n} samples; {payload / (frame_bits + tc.difs_bits):.1%} without its acknowledgement)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="shorter runs")
    args = ap.parse_args()
    schedule(args.quick)
    capacity()
    completeness(args.quick)
    traffic(args.quick)
    efficiency(args.quick)


if __name__ == "__main__":
    main()



