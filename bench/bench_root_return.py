"""Mesh time when the root gateway goes and comes back (virtual time, 4x4, gateways 1 and 16,
crystals ±50 ppm, random counter epochs, jitter on).

Gateway 1, the time root, is cut off (its cells cut) or powered off at 8 s; gateway 16
takes the skin's time on (its fit frozen). At 12 s gateway 1 is back: cut off, it stayed
a root of its own and its rounds name a lower root than 16; rebooted, it finds the skin's
root and follows it. Per run: the worst distance of any bridge's global time from the
line of the skin's time (gateway 16's, measured 11.5-11.9 s, a line since its fit is
frozen) from 12 s to 18 s, against its bound (the bridge's and gateway 1's sync bounds:
2 µs at one hop to 10 µs at eight, as in tests/test_emulator_meshtime.py), how many
(bridge, 0.1 s) steps a bridge other than gateway 1 was off mesh time, and the worst error
against gateway 16 while the root was gone (8-11.5 s).

    .venv/bin/python bench/bench_root_return.py [--seeds 5]
"""

from __future__ import annotations

import argparse

from root_return import (  # the scenario tests/test_emulator_meshtime.py asserts on
    HEIR,
    HOWS,
    ROOT,
    US,
    How,
    errors_from_line,
    root_goes_and_returns,
    skin_time_line,
    sync_bound,
)


def run(seed: int, how: How) -> tuple[float, float, float, int, int | None]:
    """(worst failover error µs, worst return error µs, its share of the bound, unsynced steps, root at the end)."""
    mesh, vm = root_goes_and_returns(seed, how)
    vm.run(8.0)
    hops = mesh.hops(HEIR)
    heir = vm.nodes[HEIR]
    failover = 0.0
    for _ in range(35):
        vm.run(0.1)
        g0 = heir.clock.global_at(heir.crystal.local(vm.tick))
        for b, fw in vm.nodes.items():
            if b != ROOT and fw.clock.has_fit():
                failover = max(failover, abs(fw.clock.global_at(fw.crystal.local(vm.tick)) - g0) / US)
    line = skin_time_line(vm)
    worst = share = 0.0
    unsynced = 0
    for _ in range(60):
        vm.run(0.1)
        for b, e in errors_from_line(vm, line).items():
            if e is None:
                unsynced += 1
                continue
            worst = max(worst, e)
            share = max(share, e / (sync_bound(hops[b]) + sync_bound(hops[ROOT])))
    roots = {fw.clock.root for fw in vm.nodes.values()}
    return failover, worst, share, unsynced, roots.pop() if len(roots) == 1 else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5, help="runs per case, seeds 1..N (default 5)")
    args = ap.parse_args()
    print(f"{'case':>8} {'seed':>4} {'failover µs':>11} {'return µs':>9} {'of bound':>8} {'unsynced':>8} {'root':>4}")
    for how in HOWS:
        for seed in range(1, args.seeds + 1):
            f, w, s, u, root = run(seed, how)
            print(f"{how:>8} {seed:>4} {f:>11.2f} {w:>9.2f} {s:>8.2f} {u:>8} {str(root):>4}")


if __name__ == "__main__":
    main()
