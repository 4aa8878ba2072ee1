"""Do routes hold on a static, lossless, idle mesh? Parent changes, route losses, evictions.

Run: ``.venv/bin/python bench/bench_route_stability.py [--size 8] [--seconds 60] [--seed 4]``.

A virtual size×size grid (one gateway in a corner, no loss, event-based reporting with a
heartbeat a second: an idle skin) runs 10 s for its routes to form, then ``--seconds``
more, well past Trickle's long interval (0.5 s) and a neighbour's timeout (2 s). Printed
for the formation and for the time after: parent changes, route losses, neighbour
evictions and bridges without a route at the end. After formation all should be 0: a
live neighbour is never evicted (its beacons go every ``sync_period`` and every frame
it acknowledges proves it alive too).
"""

from __future__ import annotations

import argparse
import time

from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.reporting import ReportingMode
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import VirtualMesh

_KEYS = ("parent_changes", "route_lost", "neighbour_evictions")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=8, help="grid side in bridges (default 8: 64 bridges)")
    ap.add_argument("--seconds", type=float, default=60.0, help="virtual seconds after the routes formed")
    ap.add_argument("--seed", type=int, default=4)
    args = ap.parse_args()
    vm = VirtualMesh(meshgen.grid(args.size, args.size), seed=args.seed,
                     settings=Settings(reporting=ReportingMode(40, 1000)))
    t0 = time.perf_counter()
    formed = vm.run(10.0)
    end = vm.run(args.seconds)
    wall = time.perf_counter() - t0
    print(f"{'window':<26} {'parent changes':>15} {'route losses':>13} {'evictions':>10} {'cut off':>8}")
    print(f"{'formation (0-10 s)':<26} " + " ".join(f"{formed.total(k):>{w}}" for k, w in zip(_KEYS, (15, 13, 10)))
          + f" {len(formed.cut_off):>8}")
    label = f"after (10-{10 + args.seconds:g} s)"
    print(f"{label:<26} " + " ".join(f"{end.total(k) - formed.total(k):>{w}}" for k, w in zip(_KEYS, (15, 13, 10)))
          + f" {len(end.cut_off):>8}")
    print(f"({args.size}x{args.size} grid, seed {args.seed}, {wall:.1f} s of wall time)")


if __name__ == "__main__":
    main()
