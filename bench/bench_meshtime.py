"""Mesh time: how well the skin agrees on one clock, and what it costs.

Run: ``.venv/bin/python bench/bench_meshtime.py [--real] [--real-seconds 20]``. Virtual
parts take a few minutes on one core; ``--real`` adds the real-time rows (``cellbridge
mesh up``: an 8x8 skin for the gate spread, a 4x4 for press latency; a couple of minutes,
and their figures depend on how busy the machine is: the load average is printed).

Tables:

1. sync error against the root per hop, p50/p99 (virtual time, crystals within ±50 ppm,
   counters started at unrelated epochs, oscillator jitter on; line of 9 = 8 hops, 4x4,
   random 32; and the 4x4 again under the real-time latency model). Each bridge's error is
   |its global time − the root's| read every 50 ms after 8 s. Target p99 ≤ 2 µs at one hop,
   ≤ 10 µs at 8 hops.
2. spread (latest − earliest) of the C1 gate starts of one sample index across an 8x8 skin,
   target ≤ 20 µs: virtual time (planned gate ticks of every bridge, 10 indices), and with
   ``--real`` a real ``mesh up`` (each bridge's planned gates of two indices on 10 s
   boundaries, printed in its last line on exit).
3. bytes: a BEACON with and without its mesh time, beacons per second per bridge, bits per
   second per cell, and a sample's bytes in DATA before (v1: no index) and after (v2: index,
   plus the frame's rate).
4. CPU: time in mesh-time code (the clock's regression, stamping, conversions) per bridge
   per second, from a profile of a 4x4 in virtual time, and as a share of the firmware's.
5. press onset (the world's start of the press) → the first sample that shows it at the
   gateway, 4x4 at 100 Hz, p50/p99 over 40 presses: virtual time with the latency model of
   a real-time mesh (quiet machine: 0.1 ms messages; default model: 0.5 ms), periodic and
   event-based; with ``--real``, real processes read off the pty.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import time
from collections import defaultdict
from typing import Any

import msgpack
import numpy as np
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.reporting import ReportingMode
from cellbridge.emulator.firmware.transceiver import PREAMBLE_BITS
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, Latency, VirtualMesh
from cellbridge.protocol import ADDR_BROADCAST, Beacon, Data, Frame, MeshTime, Mode, Sample, encode

from timing import pin_to_one_core, table

US = CLOCK_HZ // 1_000_000  #: cycles per microsecond
EVENTS = ReportingMode(40, 1000)  #: as a large skin runs (mesh time does not depend on it)


def sync_error() -> None:
    rows = []
    cases = [("line of 9", meshgen.line(9), None), ("4x4", meshgen.grid(4, 4), None),
             ("random 32", meshgen.random_mesh(32, seed=3), None),
             ("4x4, latency model", meshgen.grid(4, 4), Latency(seed=3))]
    for name, mesh, lat in cases:
        kw: dict[str, Any] = {"ack_slack": CLOCK_HZ // 100} if lat else {}
        vm = VirtualMesh(mesh, seed=2, random_epochs=True, latency=lat, settings=Settings(reporting=EVENTS), **kw)
        root = min(mesh.gateways)
        hops = mesh.hops(root)
        vm.run(8.0)
        errs: dict[int, list[float]] = defaultdict(list)
        for _ in range(80):
            vm.run(0.05)
            for b, e in vm.time_errors(root).items():
                errs[hops[b]].append(e)
        for h in sorted(errs):
            target = 2.0 + max(0, h - 1) * 8.0 / 7.0
            p99 = float(np.percentile(errs[h], 99))
            rows.append([name, h, len({b for b in hops if hops[b] == h}), f"{np.percentile(errs[h], 50):.2f}",
                         f"{p99:.2f}", f"{target:.1f}", "yes" if p99 <= target else "NO"])
    table("1. mesh-time error against the root per hop (virtual, ±50 ppm, random epochs), µs",
          ["mesh", "hops", "bridges", "p50 µs", "p99 µs", "target µs", "ok"], rows)


def gate_spread_virtual() -> list[list[object]]:
    mesh = meshgen.grid(8, 8)
    vm = VirtualMesh(mesh, seed=7, random_epochs=True, settings=Settings(reporting=EVENTS))
    vm.run(14.0)
    rate = 100
    spreads = []
    for _ in range(10):
        vm.run(0.5)
        k = vm.nodes[1].timebase.first_index(vm.tick, rate) + 10
        starts = [fw.timebase.gate_tick(k, rate) for fw in vm.nodes.values() if fw.timebase.synced(vm.tick)]
        spreads.append(((max(starts) - min(starts)) / US, len(starts)))
    worst = max(s for s, _ in spreads)
    return [["8x8 virtual", min(n for _, n in spreads), len(spreads), f"{np.median([s for s, _ in spreads]):.2f}",
             f"{worst:.2f}", "20", "yes" if worst <= 20 else "NO"]]


def gate_spread_real(seconds: float) -> list[list[object]]:
    from realskin import RealSkin

    mesh = meshgen.grid(8, 8)
    load = os.getloadavg()[0]
    with RealSkin(mesh, 100, "event:40") as skin:
        time.sleep(len(mesh.bridges) * 0.1 + 2 * seconds)  # 14 hops to sync under load
    k, n, spread = skin.gate_spread_us()
    synced = sum(1 for g in skin.gates.values() if g)
    late = sum(c.get("late_gates", 0) for c in skin.counters.values())
    samples = sum(c.get("samples", 0) for c in skin.counters.values())
    return [[f"8x8 real (mesh up, load {load:.1f}, {synced}/64 synced, late gates {late / max(1, samples):.0%})",
             n, 1, f"{spread:.2f}", f"{spread:.2f}", "20", "yes" if n == 64 and spread <= 20 else "NO"]]


def costs() -> None:
    b_with = len(encode(Frame(7, ADDR_BROADCAST, 7, 1000, Beacon(3, 25, 2, MeshTime(1, 40000, 2**40 + 12345)))))
    b_without = len(encode(Frame(7, ADDR_BROADCAST, 7, 1000, Beacon(3, 25, 2))))
    mesh = meshgen.grid(4, 4)
    vm = VirtualMesh(mesh, seed=2, random_epochs=True, settings=Settings(reporting=EVENTS))
    vm.run(4.0)
    before = {b: fw.counters["beacons"] for b, fw in vm.nodes.items()}
    secs = 10.0
    vm.run(secs)
    rate = {b: (fw.counters["beacons"] - before[b]) / secs for b, fw in vm.nodes.items()}
    per_bridge = sum(rate.values()) / len(rate)
    cell_bits = []
    for c in mesh.cells:
        on = [b.id for b in mesh.bridges if c.id in b.cells]
        cell_bits.append(sum(rate[b] for b in on) * ((b_with * 8) + PREAMBLE_BITS))
    rows: list[list[object]] = [["BEACON frame bytes", b_without, b_with, f"+{b_with - b_without}"],
            ["beacons/s per bridge (4x4, stable routes)", "-", f"{per_bridge:.2f}", "sync_period 0.5 s"],
            ["beacon bits/s per cell, mean (max)", "-", f"{np.mean(cell_bits):.0f} ({max(cell_bits):.0f})",
             f"{np.mean(cell_bits) / 1e6:.2%} of 1 Mbit/s"]]
    s1 = len(msgpack.packb([0, 2**33 + 17, 19600, 15800, 0]))
    s2 = len(msgpack.packb(Sample(0, 2**33 + 17, 19600, 15800, 0, 123456)))
    batch = 5  # samples per DATA frame at 100 Hz with max_latency 50 ms
    d2 = Data(Mode.COUNTER, tuple(Sample(0, 2**33 + 17 + i, 19600, 15800, 0, 123456 + i) for i in range(batch)), 1, 100)
    rows.append(["DATA bytes per sample (v1 -> v2: index)", s1, s2, f"+{s2 - s1}"])
    v2_payload = [int(d2.mode), d2.oversampling, [list(x) for x in d2.samples], d2.rate]  # v3 packs them
    rows.append([f"DATA payload bytes, {batch} samples + rate (v2)", "-", len(msgpack.packb(v2_payload)),
                 "rate: +3 per frame"])
    table("3. bytes mesh time costs", ["what", "without", "with", "note"], rows)
    # CPU: profile a 4x4 in virtual time; mesh-time code is meshtime.py and the stamping
    vm = VirtualMesh(mesh, seed=2, random_epochs=True)
    vm.run(2.0)
    prof = cProfile.Profile(time.process_time)  # CPU time: other processes do not count
    secs = 5.0
    prof.enable()
    vm.run(secs)
    prof.disable()
    st = pstats.Stats(prof)
    mesh_time = firmware = 0.0
    for (path, _line, fn), (_cc, _nc, tt, _ct, _callers) in st.stats.items():  # type: ignore[attr-defined]  # pstats keeps its table in an undocumented attribute
        if path.endswith("meshtime.py") or fn in ("_stamp", "_beacon_message"):
            mesh_time += tt
        if "/emulator/" in path and not path.endswith(("virtual.py", "medium.py", "world.py")):
            firmware += tt
    n = len(mesh.bridges)
    table("4. CPU mesh time costs (4x4, 100 Hz periodic, virtual time, profiled)",
          ["what", "per bridge per second", "share of the firmware's CPU"],
          [["mesh-time code (meshtime.py, beacon stamping)", f"{mesh_time / n / secs * 1e6:.0f} µs",
            f"{mesh_time / firmware:.1%}"],
           ["all firmware code (chip, sampling, link, routing, ...)", f"{firmware / n / secs * 1e6:.0f} µs", "100%"]])
    print("  (profiled times are inflated by cProfile alike for both rows; the share is the figure to read)")


QUIET = Latency(up=0.0001, down=0.0001, floor=0.00005, wake_late=0.0001)  #: messages of a quiet machine


def first_showing(xs: list[tuple[float, float, int]], start: float) -> float | None:
    """Arrival of the first sample (gate, arrival, c1; sorted by gate) whose gate is at or
    after ``start`` and whose C1 count moved > 200 from the samples before (the press)."""
    before = [c for g, _, c in xs if start - 0.3 <= g < start] or [c for g, _, c in xs if g < start][-1:]
    if not before:
        return None
    ref = float(np.median(before))
    return next((a for g, a, c in xs if g >= start and abs(c - ref) > 200), None)


def press_latency_virtual() -> list[list[object]]:
    """Press onset -> the first sample showing it at the gateway's serial line, virtual
    time with the latency model of a real-time mesh (deterministic)."""
    from cellbridge.emulator.world.world import Contact
    from cellbridge.protocol import HostReceiver

    rows = []
    for label, lat, mode in (("periodic, quiet-machine latency", QUIET, ReportingMode()),
                             ("event:40, quiet-machine latency", QUIET, EVENTS),
                             ("event:40, default latency model", Latency(), EVENTS)):
        mesh = meshgen.grid(4, 4)
        vm = VirtualMesh(mesh, seed=0, latency=lat, settings=Settings(reporting=mode), ack_slack=CLOCK_HZ // 100)
        host = HostReceiver()
        arr: dict[int, list[tuple[float, float, int]]] = defaultdict(list)
        feed = vm._gateway_out

        def out(b: int, data: bytes, feed=feed, vm=vm, host=host, arr=arr) -> None:
            n0 = len(vm.frames[b])
            feed(b, data)
            for fr in vm.frames[b][n0:]:
                for f in host.receive(fr, vm.tick / CLOCK_HZ):
                    if isinstance(f.payload, Data):
                        cr = vm.nodes[f.origin].crystal
                        arr[f.origin] += [(cr.tick_at(x.cycle) / CLOCK_HZ, vm.tick / CLOCK_HZ, x.c1)
                                          for x in f.payload.samples]
        vm._gateway_out = out  # type: ignore[method-assign]  # the benchmark taps the gateway's output
        presses = []
        for i in range(40):
            b = mesh.bridges[(i * 7) % len(mesh.bridges)]
            t = 4.0 + i * 0.5123
            vm.press(Contact(t, 0.3, b.position[0], b.position[1], 3.0, 0.02))
            presses.append((t, b.id))
        vm.run(4.0 + 40 * 0.52 + 1.0)
        d = [(a - t) * 1000 for t, b in presses if (a := first_showing(sorted(arr[b]), t)) is not None]
        rows.append([f"4x4 virtual, {label}", len(presses), len(d), f"{np.percentile(d, 50):.1f}",
                     f"{np.percentile(d, 99):.1f}", f"{max(d):.1f}"])
    return rows


def press_latency(seconds: float, reporting: str) -> list[list[object]]:
    from realskin import RealSkin

    mesh = meshgen.grid(4, 4)
    load = os.getloadavg()[0]
    onsets: list[tuple[float, tuple[float, float]]] = []
    centres = [b.position for b in mesh.bridges]
    with RealSkin(mesh, 100, reporting) as skin:
        time.sleep(len(mesh.bridges) * 0.1 + 6.0)
        end = time.monotonic() + seconds
        i = 0
        while time.monotonic() < end:
            pos = centres[(i * 7) % len(centres)]
            onsets.append((skin.press(pos[0], pos[1], duration=0.3, force=3.0, diameter=0.02), pos))
            i += 1
            time.sleep(1.0)
        time.sleep(1.5)
    under = {b.position: b.id for b in mesh.bridges}
    by_bridge: dict[int, list[tuple[float, float, int]]] = defaultdict(list)
    for a in skin.arrivals:
        by_bridge[a.bridge].append((a.gate, a.arrived, a.c1))
    d = [(seen - start) * 1000 for start, pos in onsets
         if (seen := first_showing(sorted(by_bridge[under[pos]]), start)) is not None]
    if not d:
        return [[f"4x4 real, {reporting} (load {load:.1f})", len(onsets), 0, "nan", "nan", "nan"]]
    return [[f"4x4 real, {reporting} (load {load:.1f})", len(onsets), len(d), f"{np.percentile(d, 50):.1f}",
             f"{np.percentile(d, 99):.1f}", f"{max(d):.1f}"]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", action="store_true", help="also run the real-time rows (mesh up)")
    ap.add_argument("--real-seconds", type=float, default=20.0, help="seconds each real run measures (default 20)")
    ap.add_argument("--only", choices=["sync", "spread", "costs", "press"], help="one table only")
    args = ap.parse_args()
    if not args.real:
        pin_to_one_core()
    if args.only in (None, "sync"):
        sync_error()
    if args.only in (None, "spread"):
        rows = gate_spread_virtual()
        if args.real:
            rows += gate_spread_real(args.real_seconds)
        table("2. spread of the C1 gate starts of one sample index across the skin",
              ["skin", "bridges", "indices", "median µs", "worst µs", "target µs", "ok"], rows)
    if args.only in (None, "costs"):
        costs()
    if args.only in (None, "press"):
        rows = press_latency_virtual()
        if args.real:
            for mode in ("periodic", "event:40"):
                rows += press_latency(args.real_seconds, mode)
        table("5. press onset (the world's start of the press) -> first sample showing it at the gateway",
              ["skin", "presses", "seen", "p50 ms", "p99 ms", "max ms"], rows)


if __name__ == "__main__":
    main()
