"""The frame path through a boot and a failover of the time root, in virtual time.

Run: ``.venv/bin/python bench/bench_root_failover.py``. A 4x4 skin with two gateways, 1 (the
time root) and 16, each on a serial line of its own, periodic at 100 Hz with 1 % frame loss
per hop; gateway 16 is its own root for its first second (its own epoch) until root 1's
time reaches it, and gateway 1 dies at 6 s (16 takes over as root 16, carrying the time
on). The gateway lines go through the daemon's pipeline. Prints, per seed:

- the roots named on gateway 16's line in the order they came, and how many times the
  named root changed (a bridge stamps the root its index counts and switches once);
- records gateway 16 dropped as of a root it did not follow (``readout_other_root``) and
  the daemon's ``rejected_records``, ``root_moves``, ``late_records``, ``frames_missed``;
- the share of element-frames known (a sample or unchanged) in gateway 16's records of
  root 16's last 200 frames (the 15 live elements; the mesh loses 1 % per hop), and the
  element unknown most often there;
- the CPU seconds the virtual mesh took (a bridge woken at every tick shows here).
"""

from __future__ import annotations

import time
from collections import Counter
from typing import Any

from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh
from cellbridge.protocol import FrameType, Readout

T0 = 1_800_000_000.0
SECONDS = 9.0


def scenario(seed: int) -> dict[str, Any]:
    mesh = meshgen.grid(4, 4, gateways=(1, 16), loss=0.01)
    vm = VirtualMesh(mesh, seed=seed, random_epochs=True, settings=Settings(rate_hz=100), readout=True)
    vm.kill(1, at=6.0)
    cpu = time.process_time()
    vm.run(SECONDS)
    cpu = time.process_time() - cpu
    named = [f.payload.root for f in vm.frames[16] if f.type is FrameType.READOUT]  # type: ignore[union-attr]
    order = [r for i, r in enumerate(named) if i == 0 or named[i - 1] != r]
    p = Pipeline(parse_config({"link": [{"name": f"gw{g}", "url": "/dev/null"} for g in (1, 16)]}))
    reads = sorted((t, g, data) for g in (1, 16) for t, data in vm.serial_chunks[g])
    for t, g, data in reads:
        p.feed(f"gw{g}", data, T0 + t / CLOCK_HZ)
    h = p.health_body(T0 + SECONDS)["frames"]
    # element-frames of the last 2 s: known (a sample or unchanged) in gateway 16's records
    known, unknown = 0, Counter[int]()
    records: list[Readout] = [f.payload for f in vm.frames[16] if f.type is FrameType.READOUT]  # type: ignore[misc]
    newest = max((r.index for r in records if r.root == 16), default=0)
    tail = [r for r in records if r.root == 16 and r.index > newest - 200]
    frames = {r.index for r in tail}
    seen: dict[int, set[int]] = {k: set() for k in frames}
    for r in tail:
        seen[r.index].update(s.bridge for s in r.samples)
        seen[r.index].update(r.unchanged)
    for got in seen.values():
        known += len(got - {1})
        unknown.update(set(range(2, 17)) - got)
    worst = unknown.most_common(1)
    return {"order": order, "changes": len(order) - 1, "other_root": vm.nodes[16].counters["readout_other_root"],
            "rejected": h["rejected_records"], "moves": h["root_moves"], "late": h["late_records"],
            "missed": h["frames_missed"], "known": known / max(1, 15 * len(frames)),
            "worst": f"{worst[0][0]}: {worst[0][1]}/{len(frames)}" if worst else "-", "cpu": cpu}


def main() -> None:
    print(f"{'seed':>4} {'roots on 16':>14} {'changes':>7} {'dropped':>7} {'refused':>7} {'moves':>5} {'late':>5} "
          f"{'missed':>6} {'known':>7} {'worst':>10} {'cpu s':>6}")
    for seed in (5, 6, 7):
        r = scenario(seed)
        print(f"{seed:4d} {'>'.join(map(str, r['order'])):>14} {r['changes']:7d} {r['other_root']:7d} "
              f"{r['rejected']:7d} {r['moves']:5d} {r['late']:5d} {r['missed']:6d} {r['known']:7.1%} "
              f"{r['worst']:>10} {r['cpu']:6.1f}")


if __name__ == "__main__":
    main()
