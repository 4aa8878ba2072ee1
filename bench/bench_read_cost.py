"""What one serial read costs the daemon's loop around presses, in-process.

Run: ``.venv/bin/python bench/bench_read_cost.py [--presses N] [--seed S]``.

A look at the skin (the contact scheduler's ``due``, then its ``look``: the frames whose
deadline passed and ``contact_job``, ``cellbridge.daemon.core.contact_schedule``, as the service
and the offline driver make it) follows every read in the daemon, and the loop can do nothing else meanwhile: a press's look, and the result of its
estimate, wait behind the reads in front of them (docs/time.md: 2-4 ms a read on real
processes around a press). The reads come from the emulator's deterministic mesh in
virtual time (4×4, 100 Hz, event-based reporting, random presses): the emulator's bytes,
not the daemon's own model. The figures are CPU time on this machine, one core, no
other process of the skin running; the real daemon adds element publishing.
"""

from __future__ import annotations

import argparse
import random
import time

import numpy as np
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.contact_schedule import ContactScheduler
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, Latency, VirtualMesh
from cellbridge.emulator.realtime.realtime import reporting_arg
from cellbridge.emulator.world.world import Contact, World

from timing import pin_to_one_core, table, warm_daemon_kernels

WARM_S = 60.0  # s of quiet skin first: routes, mesh time and baselines settle


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presses", type=int, default=20, help="presses of 0.3 s, one a second (default 20)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    pin_to_one_core()
    warm_daemon_kernels()
    mesh = meshgen.grid(4, 4)
    rng = random.Random(args.seed)
    presses = [Contact(WARM_S + 2.0 + i, 0.3, rng.uniform(0, 0.12), rng.uniform(0, 0.12), 3.0, 0.02)
               for i in range(args.presses)]
    vm = VirtualMesh(mesh, seed=args.seed, world=World(mesh, presses), latency=Latency(), ack_slack=CLOCK_HZ // 100,
                     random_epochs=True, settings=Settings(rate_hz=100, reporting=reporting_arg("event:40")))
    vm.run(presses[-1].start + 1.3)
    reads = [(t / CLOCK_HZ, data) for t, data in vm.serial_chunks[mesh.gateways[0]]]
    p = Pipeline(parse_config({"link": [{"name": "gw", "url": "/dev/null"}]}))
    p.want({"contact"})
    sched = ContactScheduler(p, p.config.contact.rate)
    split = next(i for i, (t, _) in enumerate(reads) if t > WARM_S)
    for t, d in reads[:split]:
        p.feed("gw", d, t)
    feed, look = [], []
    for t, d in reads[split:]:
        t0 = time.perf_counter()
        p.feed("gw", d, t)
        sched.fed()
        t1 = time.perf_counter()
        sched.due(t, False)
        sched.look(t)
        t2 = time.perf_counter()
        feed.append((t1 - t0) * 1e3)
        look.append((t2 - t1) * 1e3)
    rows = []
    for name, ms in (("feed", feed), ("look (due + job)", look), ("read + look", np.add(feed, look))):
        a = np.asarray(ms)
        rows.append([name, len(a), *(f"{np.percentile(a, q):.3f}" for q in (50, 90, 99)), f"{a.max():.3f}"])
    size = np.mean([len(d) for _, d in reads[split:]])
    table(f"one read of the gateway's line ({size:.0f} bytes on average), 4x4 at 100 Hz event:40, "
          f"{args.presses} presses, in-process, one core",
          ["what", "reads", "p50 ms", "p90 ms", "p99 ms", "max ms"], rows)


if __name__ == "__main__":
    main()
