"""Where a real-time skin's samples spend their time: gate start → gateway pty, per bridge.

Run: ``.venv/bin/python bench/bench_latency.py [--side 4] [--seconds 25] [--rate 100]``;
``--virtual default|quiet|none`` runs the same skin in virtual time instead, with the
latency model of a real-time mesh (``Latency()``; ``quiet``: 0.1 ms messages; ``none``: no
latency): deterministic, and independent of how busy the machine is.
Starts ``cellbridge mesh up`` (a side×side grid, one gateway), reads the gateway's pty with
pyserial (no daemon), and for every sample computes its delay from the start of its C1 gate
(exact: the bridge's crystal maps its ``cycle`` back to host time) to its bytes on the pty.
Prints, per bridge after a settling time (routes formed): hops, samples delivered / due,
delay p50/p99/max; then the arrival spread of one sample index across the bridges (latest
minus earliest arrival of that index) with when the whole skin frame was there (its last
bridge's sample, gate start to pty: what the daemon's estimate of a frame waits for), and the bridges' link counters that explain delay
(retries, late ACKs, CCA deferrals, queue drops). Targets (issue 13): every bridge ≥ 99.9 %
delivered, spread of one index ≤ 50 ms, delay well within 50 ms p99.
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict
from typing import Any

from cellbridge.emulator.mesh import meshgen

from realskin import Arrival, RealSkin, percentile
from timing import table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=4, help="grid side (default 4: 16 bridges)")
    ap.add_argument("--seconds", type=float, default=25.0, help="seconds measured after settling (default 25)")
    ap.add_argument("--settle", type=float, default=6.0, help="seconds after the last bridge started (default 6)")
    ap.add_argument("--rate", type=int, default=100)
    ap.add_argument("--reporting", default="periodic")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-latency", type=float, default=None,
                    help="ms a periodic sample waits at most for company in a DATA frame (virtual "
                         "time only; default: the firmware's)")
    ap.add_argument("--depth-slot", type=float, default=None,
                    help="ms per hop of the aligned batches' slots (virtual time only; default: the firmware's)")
    ap.add_argument("--slot", type=float, nargs=3, default=None, metavar=("DEPTHS", "MS", "JITTER_MS"),
                    help="aligned batches' slots: depths, ms per depth, ms of jitter (virtual time only)")
    ap.add_argument("--unaligned", action="store_true",
                    help="periodic batches closed at each bridge's own phase (virtual time only)")
    ap.add_argument("--worst", type=int, default=0,
                    help="also print the N indices of largest spread: each bridge's arrival after the first (ms)")
    ap.add_argument("--virtual", choices=["default", "quiet", "none"], default=None,
                    help="virtual time with this latency model instead of real processes")
    args = ap.parse_args()
    mesh = meshgen.grid(args.side, args.side)
    n = len(mesh.bridges)
    if args.virtual:
        arrivals, counters, lo, hi, medium = run_virtual(mesh, args)
        print(f"{mesh.name}: {n} bridges at {args.rate} Hz ({args.reporting}), virtual time, latency model "
              f"{args.virtual}")
    else:
        print(f"{mesh.name}: {n} bridges at {args.rate} Hz ({args.reporting}), {os.cpu_count()} cores, "
              f"load {os.getloadavg()[0]:.1f}")
        with RealSkin(mesh, args.rate, args.reporting, args.seed) as skin:
            boot = n * 0.1 + args.settle
            time.sleep(boot)
            t0 = time.monotonic()
            time.sleep(args.seconds)
            t1 = time.monotonic()
            time.sleep(1.0)  # the last samples of the window arrive
        lo, hi = t0, t1 - 1.0
        arrivals, counters = skin.arrivals, skin.counters
        medium = next((x for x in skin.stderr_lines if x.startswith("medium:")), "")
    per: dict[int, list] = defaultdict(list)
    for a in arrivals:
        if lo <= a.gate < hi:
            per[a.bridge].append(a)
    hops = mesh.hops()
    rows = []
    due = args.rate * (hi - lo)
    worst_share = 1.0
    all_delays: list[float] = []
    for b in mesh.ids:
        xs = per.get(b, [])
        d = [(a.arrived - a.gate) * 1000 for a in xs]
        all_delays += d
        share = len({a.index for a in xs}) / due if args.reporting == "periodic" else float("nan")
        worst_share = min(worst_share, share)
        c = counters.get(b, {})
        rows.append([b, hops.get(b, "?"), len(xs), f"{share:.2%}", f"{percentile(d, 0.5):.1f}",
                     f"{percentile(d, 0.99):.1f}", f"{max(d) if d else float('nan'):.1f}",
                     sum(1 for a in xs if not a.synced), c.get("retries", 0), c.get("late_acks", 0),
                     c.get("cca_busy", 0), c.get("queue_drops", 0), c.get("udp_drops", 0),
                     c.get("late_gates", 0)])
    table(f"gate start -> gateway pty, per bridge ({hi - lo:.1f} s window)",
          ["bridge", "hops", "samples", "delivered", "p50 ms", "p99 ms", "max ms", "unsynced", "retries",
           "late acks", "cca busy", "queue drops", "udp drops", "late gates"], rows)
    by_index: dict[int, list[float]] = defaultdict(list)
    gate_of: dict[int, float] = {}
    for xs in per.values():
        for a in xs:
            if a.synced:
                by_index[a.index].append(a.arrived)
                gate_of[a.index] = a.gate
    whole = {k: v for k, v in by_index.items() if len(v) == n}
    spread = [(max(v) - min(v)) * 1000 for v in whole.values()]
    # when the host has the whole skin frame: its last bridge's sample arrived (what the
    # daemon's estimate of that frame waits for)
    complete = [(max(v) - gate_of[k]) * 1000 for k, v in whole.items()]
    table("arrival spread of one sample index across all bridges (indices every bridge delivered)",
          ["indices", "p50 ms", "p99 ms", "max ms", "frame whole p50 ms", "frame whole p99 ms",
           "all delays p50 ms", "all delays p99 ms"],
          [[len(spread), f"{percentile(spread, 0.5):.1f}", f"{percentile(spread, 0.99):.1f}",
            f"{max(spread) if spread else float('nan'):.1f}", f"{percentile(complete, 0.5):.1f}",
            f"{percentile(complete, 0.99):.1f}", f"{percentile(all_delays, 0.5):.1f}",
            f"{percentile(all_delays, 0.99):.1f}"]])
    if args.worst:
        by_bridge: dict[int, dict[int, float]] = defaultdict(dict)
        for b, xs in per.items():
            for a in xs:
                by_bridge[a.index][b] = a.arrived
        worst = sorted(whole, key=lambda k: max(whole[k]) - min(whole[k]), reverse=True)[:args.worst]
        for k in worst:
            got = sorted(by_bridge[k].items(), key=lambda kv: kv[1])
            first = got[0][1]
            print(f"index {k} (gate +{(first - gate_of[k]) * 1000:.1f} ms to first): "
                  + " ".join(f"{b}@{(t - first) * 1000:.1f}" for b, t in got))
    print(f"\nworst bridge delivered {worst_share:.2%} (target >= 99.9 %)")
    print(f"medium: {medium}")


def run_virtual(mesh, args):
    """The same skin in virtual time: (arrivals, counters, window start, end, medium counters)."""
    from cellbridge.emulator.firmware.commands import Settings
    from cellbridge.emulator.mesh.virtual import CLOCK_HZ, Latency, VirtualMesh
    from cellbridge.emulator.realtime.realtime import reporting_arg
    from cellbridge.protocol import Data, HostReceiver, SampleFlags

    lat = {"default": Latency(), "quiet": Latency(up=0.0001, down=0.0001, floor=0.00005, wake_late=0.0001),
           "none": None}[args.virtual]
    extra: dict[str, Any] = {} if args.max_latency is None else {"max_latency": int(args.max_latency * CLOCK_HZ / 1000)}
    if args.depth_slot is not None:
        extra["depth_slot"] = int(args.depth_slot * CLOCK_HZ / 1000)
    if args.slot is not None:
        extra.update(slot_depths=int(args.slot[0]), depth_slot=int(args.slot[1] * CLOCK_HZ / 1000),
                     slot_jitter=int(args.slot[2] * CLOCK_HZ / 1000))
    if args.unaligned:
        extra["aligned_batches"] = False
    vm = VirtualMesh(mesh, seed=args.seed, latency=lat, ack_slack=CLOCK_HZ // 100 if lat else 0,
                     settings=Settings(rate_hz=args.rate, reporting=reporting_arg(args.reporting)),
                     random_epochs=True, **extra)
    host = HostReceiver()
    arrivals: list[Arrival] = []
    feed = vm._gateway_out

    def out(b: int, data: bytes) -> None:
        n0 = len(vm.frames[b])
        feed(b, data)
        now = vm.tick / CLOCK_HZ
        for fr in vm.frames[b][n0:]:
            for f in host.receive(fr, now):
                if isinstance(f.payload, Data):
                    cr = vm.nodes[f.origin].crystal
                    arrivals.extend(Arrival(f.origin, x.index, x.cycle, x.c1, not x.flags & SampleFlags.NO_MESH_TIME,
                                            cr.tick_at(x.cycle) / CLOCK_HZ, now) for x in f.payload.samples)
    vm._gateway_out = out  # type: ignore[method-assign]
    lo = len(mesh.bridges) * 0.1 + args.settle
    r = vm.run(lo + args.seconds + 1.0)
    return arrivals, r.counters, lo, lo + args.seconds, r.medium


if __name__ == "__main__":
    main()
