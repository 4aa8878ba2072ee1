"""Where the daemon's core spends its CPU on the humanoid skin, stage by stage.

Prints a table; asserts nothing. Run (a minute or two on a loaded machine):

    .venv/bin/python bench/bench_humanoid_stages.py [--reporting event:30] [--idle] [--seconds 8] [--repeat 3]

One recording of the humanoid's traffic (``bench_humanoid.generate``: rounds of 10
simultaneous presses, or none with ``--idle``) goes through the core as
``bench_humanoid.core_capacity`` runs it (every read fed in order of arrival, a tick every
0.1 s, a contact look after every read and an estimate, inline, for each job), subscribed
to ``contact`` and ``health`` as the daemon's subscriber in ``bench_humanoid`` is. Each
stage's entry point on the pipeline's own objects is wrapped to add up the thread CPU of
its calls; the stages do not nest, so they add up to the whole but for ``rest`` (the
pipeline's own glue, and the wrappers' calls). A run to warm up, then ``--repeat`` runs;
each figure is the median over them, in CPU s per recorded s and in microseconds a call.

The stages: ``decode`` (a read's bytes to messages: stream, COBS, CRC, msgpack, the
READOUT's checks, reassembly and duplicates: ``Ingress.feed``), ``routing`` (who was heard
on which link, HELLOs, replies), ``records`` (a readout record teaches the map of mesh time
and joins its skin frame: ``HostTimes.records``), ``heard`` (health's note of the bridges a
record accounts for), ``frames out`` (the skin frames complete or at their deadline, their
columns built: ``TimeDomains.take``), ``element stage`` (a frame's capacitances, channel
health, calibration and readings: ``Batches.frame``), ``contact look`` (whether a frame is
new to estimate: ``LayoutStages.snapshot``), ``estimate`` (the contact estimate and its
message), ``tick`` (health, every 0.1 s of recorded time).
"""

from __future__ import annotations

import argparse
import heapq
import logging
import statistics
import sys
import tempfile
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

from timing import table

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("decode", "routing", "records", "heard", "frames out", "element stage", "contact look", "estimate",
          "tick")


def _timed(fn: Callable[..., Any], stage: str, cpu: defaultdict[str, float], calls: Counter[str]) -> Callable[..., Any]:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            cpu[stage] += time.thread_time() - t0
            calls[stage] += 1
    return wrapper


def run(skin: Any, gen: dict, into: Path) -> tuple[defaultdict[str, float], Counter[str], float]:
    """One run of the core on the recording: CPU s and calls per stage, and the whole."""
    from cellbridge.daemon.core.config import parse_config
    from cellbridge.daemon.core.pipeline import Pipeline
    from cellbridge.daemon.shell.contact_worker import ContactWorker, InlineExecutor
    from cellbridge.daemon.shell.replay_source import read_records

    links = [{"name": f"gw{g}", "url": "/dev/null"} for g in gen["gateways"]]
    p = Pipeline(parse_config({"link": links}), skin.layout())
    p.surface = skin
    p.want({"contact", "health"})
    w = ContactWorker(logging.getLogger("bench_humanoid_stages"), InlineExecutor)
    cpu: defaultdict[str, float] = defaultdict(float)
    calls: Counter[str] = Counter()
    for obj, name, stage in ((p.ingress, "feed", "decode"), (p, "_routing", "routing"),
                             (p.clock, "records", "records"), (p.health, "spoken_for", "heard"),
                             (p.domains, "take", "frames out"), (p.batches, "frame", "element stage"),
                             (p.skin, "snapshot", "contact look"), (p, "tick", "tick")):
        setattr(obj, name, _timed(getattr(obj, name), stage, cpu, calls))
    estimate = _timed(lambda job: p.contact_frame(job, w.estimate_now(job)), "estimate", cpu, calls)
    streams = [((t, g, d) for t, d in read_records(into / f"gw{g}.cbcap", "x")) for g in gen["gateways"]]
    whole = 0.0
    tick = 0.0
    for t, g, data in heapq.merge(*streams):
        t0 = time.thread_time()
        p.feed(f"gw{g}", data, t)
        if t >= tick:
            p.tick(t)
            tick = t + 0.1
        job = p.contact_job(t)
        if job is not None:
            estimate(job)
        whole += time.thread_time() - t0
    return cpu, calls, whole


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reporting", default="event:30", help="event:30 or periodic (default event:30)")
    ap.add_argument("--idle", action="store_true", help="no presses: an idle skin")
    ap.add_argument("--seconds", type=float, default=8.0, help="length of the recording (default 8)")
    ap.add_argument("--repeat", type=int, default=3, help="measured runs after the warm-up (default 3)")
    a = ap.parse_args()
    sys.path.insert(0, str(ROOT / "bench"))
    import bench_humanoid as bh

    skin = bh.load_skin(bh.HUMANOID)
    bh.warm_calibration()  # the calibrator's compiled step, as the daemon has it
    if a.idle:
        bh.presses = lambda skin, seconds, rng: []
    with tempfile.TemporaryDirectory(prefix="bench_humanoid_stages.") as tmp:
        into = Path(tmp)
        gen = bh.generate(skin, a.reporting, a.seconds, into)
        run(skin, gen, into)
        runs = [run(skin, gen, into) for _ in range(a.repeat)]
    secs = gen["seconds"]
    whole = statistics.median(r[2] for r in runs)
    rows = []
    staged = 0.0
    for stage in STAGES:
        cpu = statistics.median(r[0][stage] for r in runs)
        n = runs[0][1][stage]
        staged += cpu
        rows.append([stage, n, f"{cpu / secs:.4f}", f"{cpu / n * 1e6:.1f}" if n else "-", f"{cpu / whole:.0%}"])
    rest = whole - staged
    rows.append(["rest", "", f"{rest / secs:.4f}", "", f"{rest / whole:.0%}"])
    rows.append(["whole", "", f"{whole / secs:.4f}", "", "100%"])
    table(f"The daemon's core on the humanoid skin by stage ({a.reporting}, {'idle' if a.idle else 'presses'}, "
          f"{a.seconds:g} s recording, {gen['counters'].get('samples', 0) / secs:,.0f} samples/s; CPU s of one "
          f"thread per recorded s, median of {a.repeat})", ["stage", "calls", "CPU s/s", "us/call", "share"], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
