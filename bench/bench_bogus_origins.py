"""What phantom origins cost the daemon's core: health size, tick time, topology.

Run: ``.venv/bin/python bench/bench_bogus_origins.py [--origins N]``.

A noisy line lets about one corrupt frame in 65 536 past CRC-16, each from a random
origin and a random link-level sender. This feeds one junk DATA frame from each of N
origins (each with its own sender id) into a pipeline that also hears a small real
skin, then prints the size of one ``health`` and one ``topology`` message (msgpack),
the time of the second ``tick`` after the junk (it publishes health and topology) and
the median of the five ticks after it, the log events of those two ticks, and how many
gateway ids and nodes topology holds, while the phantoms are remembered and after
``forget_after``. The skin is steady: a health tick came before the junk, and the real
skin goes on talking (its gateway is the one id that stays). The junk senders include
some placed bridges' ids: they are dropped like the others.
"""

from __future__ import annotations

import argparse
import statistics
import time

import msgpack
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.messages import LogEvent, Publish
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.protocol import Data, Frame, Mode, Sample, encode_stream

from daemon_traffic import GridFrames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--origins", type=int, default=65530)
    args = ap.parse_args()
    p = Pipeline(parse_config({"link": [{"name": "gw", "url": "/dev/null"}], "health": {"forget_after": 600.0}}))
    sk = GridFrames()
    t = 1000.0
    p.feed("gw", sk.hellos() + sk.beacons(), t)
    for k, data in sk.stream(20):
        p.feed("gw", data, t + k / sk.rate)
    p.tick(t + 0.5, force=True)  # a steady skin's health tick: nothing to forget
    t += 1.0
    junk = b"".join(encode_stream(Frame(src=(o * 7919) % 0xFFF0 + 1, dst=0, origin=o, seq=0,
                                        payload=Data(Mode.COUNTER, (Sample(0, 1000, 100, 100, 0),))))
                    for o in range(5, 5 + args.origins))
    p.feed("gw", junk, t)
    print(f"{'when':<28} {'health bytes':>14} {'topology bytes':>15} {'tick ms':>9} {'later ticks ms':>15} "
          f"{'log events':>11} {'gateway ids':>12} {'topology nodes':>15}")
    slot = 20
    for label, now in (("phantoms remembered", t + 10.0), ("after forget_after", t + 601.0)):
        for k, data in sk.stream(20, start=slot):  # the real skin goes on talking
            p.feed("gw", data, now - 6.0 + (k - slot) / sk.rate)
        slot += 20
        events = sum(isinstance(m, LogEvent) for m in p.tick(now - 5.0, force=True))
        t0 = time.perf_counter()
        out = p.tick(now, force=True)
        dt = (time.perf_counter() - t0) * 1e3
        events += sum(isinstance(m, LogEvent) for m in out)
        later = []
        for k in range(1, 6):  # the ticks that follow, a second apart (median)
            t0 = time.perf_counter()
            p.tick(now + k, force=True)
            later.append((time.perf_counter() - t0) * 1e3)
        health = next(m.payload for m in out if isinstance(m, Publish) and m.topic == "health")
        size = len(msgpack.packb(health))
        topo = len(msgpack.packb(p.topology_body(now)))
        gw = sum(len(v) for v in p.topology.gateways.values())
        print(f"{label:<28} {size:>14,} {topo:>15,} {dt:>9.1f} {statistics.median(later):>15.1f} {events:>11,} "
              f"{gw:>12,} {len(p.topology.nodes):>15,}")


if __name__ == "__main__":
    main()
