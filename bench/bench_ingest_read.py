"""What one read of a gateway's line costs the daemon's core, stage by stage, on the humanoid skin.

Prints a table; asserts nothing. Run (about a minute):

    .venv/bin/python bench/bench_ingest_read.py [--seconds 6] [--reporting event:30] [--repeat 3]

The humanoid's traffic (``bench_humanoid.generate``: 1 144 elements, 22 gateways, 100 Hz,
rounds of 10 presses) is fed read by read to ``Pipeline.feed`` (topics ``contact`` and
``health``, as the daemon's subscriber in ``bench_humanoid``), and a contact job is asked
after every read (``contact_job``: its look at the skin, not the estimate, which is not
run). Each stage of ``feed`` is timed on its own (CPU of this thread, the timer's own cost
taken off): the receive path (``Ingress.feed``: stream, frame and payload decoding,
duplicates), the routing bookkeeping of what a read held (``_routing``: health's frames
seen, topology), the records' host times and frames (``HostTimes.records``), health's
bridges spoken for, the frames taken after the read (``TimeDomains.take``, their
``SkinFrame`` built) and the complete frames' element stages (``_frames_out``: per frame,
not per read). Per read in µs (and per frame for the element stages), best of
``--repeat`` passes over the recording, each on a fresh pipeline.
"""

from __future__ import annotations

import argparse
import heapq
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from timing import pin_to_one_core, table

ROOT = Path(__file__).resolve().parents[1]

#: (row name, object path from the pipeline, method name): the stages timed, in feed's order
STAGES = (
    ("receive (Ingress.feed)", "ingress", "feed"),
    ("routing bookkeeping", "", "_routing"),
    ("record times + frames", "clock", "records"),
    ("bridges spoken for", "health", "spoken_for"),
    ("frames taken", "domains", "take"),
    ("element stages (per frame)", "", "_frames_out"),
)


def timed(spent: dict[str, float], calls: dict[str, int], name: str, fn: Callable[..., Any],
          inside: list[bool]) -> Callable[..., Any]:
    """``fn`` with its CPU added to ``spent[name]`` while ``inside[0]`` (a call from ``feed``)."""
    clock = time.thread_time_ns

    def wrapper(*a: Any, **k: Any) -> Any:
        if not inside[0]:
            return fn(*a, **k)
        t0 = clock()
        try:
            return fn(*a, **k)
        finally:
            spent[name] += clock() - t0
            calls[name] += 1
    return wrapper


def one_pass(skin: Any, reads: list[tuple[float, int, bytes]], gateways: list[int]) -> tuple[dict[str, float], float,
                                                                                              int, int]:
    """One pass over the reads on a fresh pipeline: ns per stage, ns of feed in all, frames, reads."""
    from cellbridge.daemon.core.config import parse_config
    from cellbridge.daemon.core.pipeline import Pipeline

    p = Pipeline(parse_config({"link": [{"name": f"gw{g}", "url": "/dev/null"} for g in gateways]}), skin.layout())
    p.surface = skin
    p.want({"contact", "health"})
    spent = dict.fromkeys((s[0] for s in STAGES), 0.0)
    calls = dict.fromkeys((s[0] for s in STAGES), 0)
    inside = [False]
    for name, path, meth in STAGES:
        obj = getattr(p, path) if path else p
        setattr(obj, meth, timed(spent, calls, name, getattr(obj, meth), inside))
    clock = time.thread_time_ns
    total = 0
    tick = 0.0
    for t, g, data in reads:
        inside[0] = True
        c0 = clock()
        p.feed(f"gw{g}", data, t)
        total += clock() - c0
        inside[0] = False
        if t >= tick:
            p.tick(t)
            tick = t + 0.1
        p.contact_job(t)
    frames = p.frames_given()
    # the timer's own cost, per timed call: measured on an empty function, taken off feed's total
    probe, count = {"x": 0.0}, {"x": 0}
    f = timed(probe, count, "x", lambda: None, [True])
    c0 = clock()
    for _ in range(20000):
        f()
    own = (clock() - c0) / 20000
    return spent, total - own * sum(calls.values()), frames, len(reads)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=6.0, help="length of the recording (default 6)")
    ap.add_argument("--reporting", default="event:30", help="event:30 (default) or periodic")
    ap.add_argument("--repeat", type=int, default=3, help="passes over the recording (default 3)")
    a = ap.parse_args()
    pin_to_one_core()
    sys.path.insert(0, str(ROOT / "bench"))
    from cellbridge.daemon.shell.replay_source import read_records

    import bench_humanoid as bh

    skin = bh.load_skin(bh.HUMANOID)
    with tempfile.TemporaryDirectory(prefix="bench_ingest_read.") as tmp:
        gen = bh.generate(skin, a.reporting, a.seconds, Path(tmp))
        reads = list(heapq.merge(*[((t, g, d) for t, d in read_records(Path(tmp) / f"gw{g}.cbcap", "x"))
                                   for g in gen["gateways"]]))
    bh.warm_calibration()
    one_pass(skin, reads, gen["gateways"])  # warm-up: every path taken once
    runs = [one_pass(skin, reads, gen["gateways"]) for _ in range(a.repeat)]
    best = min(runs, key=lambda r: r[1])
    spent, total, frames, n = best
    rows = []
    for name, _path, _meth in STAGES:
        per = frames if "per frame" in name else n
        rows.append([name, f"{spent[name] / per / 1e3:.1f}", f"{spent[name] / gen['seconds'] / 1e9:.4f}"])
    rows.append(["feed in all (per read)", f"{total / n / 1e3:.1f}", f"{total / gen['seconds'] / 1e9:.4f}"])
    table(f"One read of a gateway's line in the daemon's core: humanoid, {a.reporting}, {a.seconds:g} s, {n} reads, "
          f"{frames} frames; best of {a.repeat} (feed's totals; each stage from that pass)",
          ["stage", "µs per read", "CPU s per s"], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
