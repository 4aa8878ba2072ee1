"""Two fingers on one element's neighbours: does each get its own contact, and when?

Run: ``.venv/bin/python bench/bench_finger_pairs.py [--seeds 1 2 3 4 5 6] [--geometry diagonal]``
(about a minute and a half a seed on one core).

A virtual event-based 4x4 skin (``VirtualMesh`` with the real-time latency model, 100 Hz,
``event:40`` as ``cellbridge demo`` runs it) is pressed by ``--pairs`` pairs of fingers, one
pair every 2 s from 10 s: two 3 N, 20 mm presses of 0.8 s each, 55-57 mm apart, their middle
within 3 mm of element 6's centre, the second 9-20 ms after the first, both footprints on
element 6 (``diagonal``: along one of its diagonals, each finger over the corner of four
elements; ``any``: at any angle). The gateway's bytes go through the daemon offline (its pipeline and
its contact loop's schedule in virtual time, the production contact path inline, as
``bench_press_latency.py --virtual``). A finger's contacts are those published during its press within 30 mm of it and
at least 10 mm nearer to it than to the other finger (a contact between the two, e.g. one
failed fit of both, is neither's). Per seed: pairs where a finger got no contact at all,
fingers whose first contact came 100 ms or more after their onset, fingers with more than one
id, and the median position and force errors from 0.3 s on. ``--verbose``: one line per pair.
"""

from __future__ import annotations

import argparse
import math
import random

from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.shell.offline import OfflineDaemon
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, Latency, VirtualMesh
from cellbridge.emulator.realtime.realtime import reporting_arg
from cellbridge.emulator.world.world import Contact, World

from timing import table

E6 = (0.04, 0.04)  # element 6's centre; elements are 40 mm squares
LATE_S = 0.1


def on_e6(c: Contact) -> bool:
    dx, dy = max(abs(c.x - E6[0]) - 0.02, 0.0), max(abs(c.y - E6[1]) - 0.02, 0.0)
    return math.hypot(dx, dy) < c.diameter / 2


def finger_pairs(seed: int, n: int, geometry: str, hold: float) -> list[tuple[Contact, Contact]]:
    rng = random.Random(seed)
    out = []
    for k in range(n):
        while True:
            th = (rng.choice((1, 3, 5, 7)) * math.pi / 4 + rng.uniform(-0.05, 0.05) if geometry == "diagonal"
                  else rng.uniform(0, 2 * math.pi))
            mx, my = E6[0] + rng.uniform(-0.003, 0.003), E6[1] + rng.uniform(-0.003, 0.003)
            half = 0.5 * rng.uniform(0.055, 0.057)
            t0 = 10.0 + 2.0 * k + rng.uniform(0, 0.01)
            dt = rng.uniform(0.009, 0.020)
            pair = (Contact(t0, hold, mx - half * math.cos(th), my - half * math.sin(th), 3.0, 0.02),
                    Contact(t0 + dt, hold, mx + half * math.cos(th), my + half * math.sin(th), 3.0, 0.02))
            if all(on_e6(c) for c in pair):
                out.append(pair)
                break
    return out


def published(seed: int, presses: list[Contact]) -> list[tuple[float, list[dict]]]:
    """(host time, contacts) of every contact message, the daemon's schedule in virtual time
    (the daemon offline: cellbridge.daemon.shell.offline)."""
    mesh = meshgen.grid(4, 4)
    vm = VirtualMesh(mesh, seed=seed, world=World(mesh, presses), latency=Latency(), ack_slack=CLOCK_HZ // 100,
                     random_epochs=True, settings=Settings(rate_hz=100, reporting=reporting_arg("event:40")))
    vm.run(max(c.start + c.duration for c in presses) + 1.0)
    reads = [(t / CLOCK_HZ, "gw", data) for t, data in vm.serial_chunks[mesh.gateways[0]]]
    d = OfflineDaemon(parse_config({"link": [{"name": "gw", "url": "/dev/null"}], "calibration": {"n_baseline": 3}}),
                      topics={"contact"})
    return [(t, m["contacts"]) for t, topic, m in d.run(reads, start=0.0) if topic == "contact"]


def judge(pair: tuple[Contact, Contact], run: list[tuple[float, list[dict]]]) -> list[dict]:
    """Per finger: its contacts' ids, its first contact's latency (s), median errors."""
    got: list[list[tuple[float, dict]]] = [[], []]
    for t, cs in run:
        for d in cs:
            if d["missed"]:
                continue
            dist = [math.hypot(d["x"] - c.x, d["y"] - c.y) if c.start <= t < c.start + c.duration else math.inf
                    for c in pair]
            j = 0 if dist[0] <= dist[1] else 1
            if dist[j] < 0.03 and dist[1 - j] - dist[j] >= 0.01:
                got[j].append((t, d))
    out = []
    for c, mine in zip(pair, got):
        steady = [d for t, d in mine if t > c.start + 0.3 and d["fit_ok"]]

        def median(xs: list[float]) -> float:
            return sorted(xs)[len(xs) // 2] if xs else math.nan

        out.append({"ids": sorted({d["id"] for _, d in mine}), "first": mine[0][0] - c.start if mine else math.nan,
                    "pos": median([1e3 * math.hypot(d["x"] - c.x, d["y"] - c.y) for d in steady]),
                    "force": median([100 * abs(d["force"] - c.force) / c.force for d in steady])})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--pairs", type=int, default=16)
    ap.add_argument("--geometry", choices=("diagonal", "any"), default="diagonal")
    ap.add_argument("--hold", type=float, default=0.8, help="s each finger presses (default 0.8)")
    ap.add_argument("--verbose", action="store_true", help="one line per pair")
    args = ap.parse_args()
    rows, total = [], [0, 0, 0, 0]
    for seed in args.seeds:
        pairs = finger_pairs(seed, args.pairs, args.geometry, args.hold)
        run = published(seed, [c for pair in pairs for c in pair])
        lost = late = multi = 0
        pos: list[float] = []
        force: list[float] = []
        for k, pair in enumerate(pairs):
            fingers = judge(pair, run)
            lost += any(not f["ids"] for f in fingers)
            late += sum(f["first"] >= LATE_S for f in fingers)
            multi += sum(len(f["ids"]) > 1 for f in fingers)
            pos += [f["pos"] for f in fingers if math.isfinite(f["pos"])]
            force += [f["force"] for f in fingers if math.isfinite(f["force"])]
            if args.verbose:
                print(f"seed {seed} pair {k:2d} at {pair[0].start:.4f} s: " + " | ".join(
                    f"({c.x:.4f}, {c.y:.4f}) ids {f['ids']} first {1e3 * f['first']:.1f} ms, "
                    f"{f['pos']:.2f} mm, {f['force']:.1f} %" for c, f in zip(pair, fingers)))
        pos.sort()
        force.sort()
        rows.append([seed, len(pairs), lost, late, multi, f"{pos[len(pos) // 2]:.2f}" if pos else "nan",
                     f"{pos[int(0.9 * len(pos))]:.2f}" if pos else "nan", f"{force[int(0.9 * len(force))]:.1f}" if force else "nan"])
        for j, v in enumerate((len(pairs), lost, late, multi)):
            total[j] += v
    rows.append(["all", *total, "", "", ""])
    table(f"two fingers on element 6's neighbours ({args.geometry}), virtual event-based 4x4 skin, "
          f"{args.hold} s presses", ["seed", "pairs", "a finger lost", f"fingers >= {1e3 * LATE_S:.0f} ms",
                                   "fingers > 1 id", "pos p50 mm", "pos p90 mm", "force p90 %"], rows)


if __name__ == "__main__":
    main()
