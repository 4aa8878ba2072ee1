"""The daemon's frame path under a robot's line faults, sans-I/O (daemon/core/domains.py, frames.py).

Run: ``.venv/bin/python bench/bench_frame_attacks.py``. Prints, per scenario, the frames
given out complete, the share of element-frames known (a sample or unchanged), the records
counted late and refused, elements given a sample that is not their frame's (``wrong``),
and how long a frame waited from its host time (on the map of mesh time: its first
record's arrival) to going out, in ms (p50, p99):

1. two gateways of one skin, the second's serial path steadily 0-500 ms slower (a USB
   adapter's buffering), at 100 and 250 Hz: the deadline learns each gateway's lag (at
   most ``MAX_LAG``; ``[frames] max_pending`` frames wait at most, so at 250 Hz a lag past
   ~0.25 s pushes frames out without its records);
2. that second line stalled 2 s, then bursting: its elements unknown for the stall, then
   known again;
3. a noisy line: one record in 200 a copy of an earlier one under an index corrupted up to
   0.25 s ahead.

Each gateway's records name its 8 bridges, all sampled; the first 2 s are left out.
"""

from __future__ import annotations

import random

import numpy as np
from cellbridge.daemon.core.domains import TimeDomains
from cellbridge.protocol import Mode, Readout, ReadoutSample

HZ = 50_000_000
SPAN_US = 4000
SECONDS = 12.0


def record(k: int, rate: int, gw: int) -> Readout:
    bridges = range(gw * 8, gw * 8 + 8)
    return Readout(k, rate, Mode.COUNTER, 1, tuple(ReadoutSample(b, k % 60000, 1, 0) for b in bridges), (), (),
                   SPAN_US, 0, 1, 1)


def scenario(rate: int, lag: float = 0.0, stall: bool = False, corrupt: bool = False) -> dict[str, float]:
    rng = random.Random(1)
    td = TimeDomains(HZ, margin=0.02)
    events: list[tuple[float, int, int, int]] = []  # (arrival, gateway, index, index written)
    for i in range(int(SECONDS * rate)):
        t = 100.0 + i / rate + SPAN_US * 1e-6 + 0.001
        events.append((t, 1, i, i))
        t2 = t + lag
        if stall and 100.0 + 6.0 <= t2 < 100.0 + 8.0:
            t2 = 100.0 + 8.0
        events.append((t2, 2, i, i))
        if corrupt and rng.random() < 1 / 100:
            events.append((t, 1, max(0, i - rng.randrange(50)), i + rng.randrange(1, int(0.25 * rate))))
    events.sort()
    out = []
    for t, gw, i, k in events:
        rec = record(1000 + i, rate, gw)
        if k != i:
            rec = Readout(1000 + k, rate, rec.mode, 1, rec.samples, (), (), SPAN_US, 0, 1, 1)
        td.record(gw, rec, 1, (1000 + k) * HZ // rate, t, 0.001)
        out += [(f, t) for f in td.take(t)]
    skip = 1000 + 2 * rate
    kept = [(f, t) for f, t in out if f.index >= skip]
    lat = np.array([t - f.t for f, t in kept])
    wrong = sum(int(np.count_nonzero(f.c1 != f.index % 60000)) for f, _ in kept)
    c = td.counters(200.0)
    return {"frames": len(kept), "complete": sum(f.complete for f, _ in kept) / max(len(kept), 1),
            "known": sum(f.bridges.size for f, _ in kept) / max(16 * len(kept), 1), "wrong": wrong,
            "late": c["late_records"], "refused": c["rejected_records"],
            "p50": float(np.percentile(lat, 50)) * 1e3, "p99": float(np.percentile(lat, 99)) * 1e3}


def main() -> None:
    print(f"{'scenario':34} {'frames':>6} {'complete':>8} {'known':>6} {'wrong':>5} {'late':>5} {'refused':>7} "
          f"{'wait p50':>8} {'wait p99':>8}")
    rows = [(f"late path {int(lag * 1000)} ms, {rate} Hz", dict(rate=rate, lag=lag))
            for rate in (100, 250) for lag in (0.0, 0.05, 0.2, 0.5)]
    rows += [("line stalled 2 s, 100 Hz", dict(rate=100, stall=True)),
             ("1 % records copied ahead, 100 Hz", dict(rate=100, corrupt=True))]
    for name, kw in rows:
        r = scenario(**kw)  # type: ignore[arg-type]
        print(f"{name:34} {r['frames']:6d} {r['complete']:8.1%} {r['known']:6.1%} {r['wrong']:5d} {r['late']:5d} "
              f"{r['refused']:7d} {r['p50']:8.1f} {r['p99']:8.1f}")


if __name__ == "__main__":
    main()
