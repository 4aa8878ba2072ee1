"""A press held for an hour beside an element drifting by itself, on an emulated skin.

Run: ``.venv/bin/python bench/bench_held_press.py [--seconds 3600] [--rate 10]``.

A 3x3 virtual mesh (one process, virtual time) samples at ``--rate`` Hz; the world
presses the centre element (3 N, 20 mm) from 10 s on and holds it, while the C2
parasitic of a corner element nothing touches drifts by itself (``--drift`` F/s, twice
the fastest drift the calibrator's tracker follows by default) for the whole run. The
gateway's bytes go through the daemon offline (its pipeline and its contact loop's
schedule, cellbridge.daemon.shell.offline) at their virtual times with the daemon's default
configuration (``max_touch`` 600 s, unless ``--max-touch``). Printed: what the ``contact`` topic said of the
press over the hold (ids, gaps, force error against the pressed force), the
calibrator's health (re-baselines, touches kept past max_touch), and whether the
drifting element was ever touched or part of a contact. A lower sample rate keeps an
hour short to emulate; the calibration logic does not depend on it.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.shell.offline import OfflineDaemon
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh
from cellbridge.emulator.world.world import Contact, Drift, World

T0 = 1_800_000_000.0  # host time of virtual time 0

PRESSED, DRIFTING = 5, 9  # the centre and a corner of a 3x3 grid
PRESS_AT, FORCE, DIAMETER = 10.0, 3.0, 0.020


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=3600.0, help="how long the press is held (virtual s)")
    ap.add_argument("--rate", type=int, default=10, help="sampling rate of the bridges (Hz)")
    ap.add_argument("--drift", type=float, default=2e-15, help="F/s the corner's C2 drifts by itself")
    ap.add_argument("--max-touch", type=float, default=None, help="calibration.max_touch (default: the daemon's)")
    args = ap.parse_args()
    seconds = PRESS_AT + args.seconds + 2.0
    started = time.process_time()
    mesh = meshgen.grid(3, 3, gateways=(1,))  # (a corner gateway: the press is on the centre bridge)
    world = World(mesh, [Contact(PRESS_AT, 1e9, 0.04, 0.04, FORCE, DIAMETER)],
                  drifts=[Drift(DRIFTING, 0.0, 0.0, args.drift)])
    vm = VirtualMesh(mesh, seed=3, world=world, settings=Settings(rate_hz=args.rate), random_epochs=True)
    vm.run(seconds)
    reads = [(T0 + t / CLOCK_HZ, "gw", data) for t, data in vm.serial_chunks[1]]
    emulated = time.process_time() - started
    sections = {} if args.max_touch is None else {"calibration": {"max_touch": args.max_touch}}
    ids: set[int] = set()
    forces, first, last, gaps, said = [], None, None, 0, []
    drift_touched = drift_in_contact = 0
    health = None
    daemon = OfflineDaemon(parse_config({"link": [{"name": "gw", "url": "/dev/null"}], **sections}))
    for t, topic, m in daemon.run(reads, T0 + seconds, start=T0):
        if topic == "element":
            drift_touched += sum(1 for b, x in zip(m["bridge"], m["touched"]) if b == DRIFTING and x)
        elif topic == "health":
            health = m["layout"]["calibration"]
        elif topic == "contact":
            said += m.get("rebaselined", [])
            drift_in_contact += sum(1 for c in m["contacts"] if DRIFTING in c["elements"])
            ids |= {c["id"] for c in m["contacts"] if PRESSED in c["elements"]}
            if any(PRESSED in c["elements"] for c in m["contacts"]):
                first = t - T0 if first is None else first
                last = t - T0
                forces += [c["force"] for c in m["contacts"] if c["missed"] == 0 and t - T0 > PRESS_AT + 1.0]
            elif first is not None:
                gaps += 1
    f = np.asarray(forces)
    err = np.abs(f / FORCE - 1.0) * 100 if f.size else np.array([np.nan])
    held = (last - first) if first is not None and last is not None else 0.0
    rows = [
        ("press held (virtual s)", f"{args.seconds:.0f}"),
        ("sampling rate (Hz)", f"{args.rate}"),
        ("max_touch (s)", "daemon default (600)" if args.max_touch is None else f"{args.max_touch:g}"),
        ("contact on the topic from .. to (s)", f"{first if first is not None else float('nan'):.1f} .. "
                                                f"{last if last is not None else float('nan'):.1f} ({held:.0f} s)"),
        ("contact ids of the press", f"{sorted(ids)}"),
        ("contact messages without the press after its birth", f"{gaps}"),
        ("force reports", f"{f.size}"),
        ("force error median / p99 / max (%)",
         f"{np.median(err):.2f} / {np.percentile(err, 99):.2f} / {err.max():.2f}"),
        ("re-baselines (health) / named on contact", f"{(health or {}).get('rebaselines_total')} / {said}"),
        ("touches kept past max_touch (health holds_total)", f"{(health or {}).get('holds_total')}"),
        (f"drifting element: C2 drift total (pF) at {args.drift * 1e15:g} fF/s", f"{args.drift * seconds * 1e12:.2f}"),
        ("drifting element: samples touched / in a contact", f"{drift_touched} / {drift_in_contact}"),
        ("CPU s: emulate / whole run", f"{emulated:.1f} / {time.process_time() - started:.1f}"),
    ]
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k:<{width}}  {v}")


if __name__ == "__main__":
    main()
