"""``cellbridge daemon`` with a per-press timing trace: what a press's contact waited for.

Run by ``bench/bench_press_latency.py --trace`` in place of ``cellbridge daemon``:
``python bench/press_trace.py --config FILE --trace OUT``. The daemon is the production
one (same service, pipeline, contact worker process); this script wraps a few of its
methods, in this process only, to note on the host monotonic clock:

* ``s``: every reading that reaches the skin frames (arrival, bridge, sample time,
  touched, held): a DATA reading, or an element a complete skin frame says something of;
* ``l``: every contact look (``LayoutStages.snapshot``): its time and the frame it took
  (or none);
* ``e``: every estimate (start, end, the frame, its unknown elements);
* ``p``: every ``contact`` message handed to ZeroMQ (time, frame, contacts);
* ``b``: what kept the loop busy: each read, each tick, each run of the cyclic garbage
  collector (``gc0``-``gc2``), each callback of the event loop that ran over 1 ms (``cb``
  and what it ran: a task's step names the task's method);
* ``w``: every wait of the event loop in its selector (entered, left, the thread's CPU
  time at both, the timeout, events ready);
* ``k``: every skin frame the layout took: when, its host time, its global cycle (the
  gate start on the skin's own plan: mesh time, which the bridges' last lines map to host
  ticks);
* ``r``: every gateway record part 0 the daemon took: when it was read, its frame's index
  and rate, and its age (µs of mesh time from the frame's gate start to when its gateway
  began writing it; 0: not said);
* ``x``: every job handed to the contact worker: when it was submitted, when the worker
  began and ended it (the worker process notes these in a file), and when its future was
  done in the daemon (the executor's result thread), all on the one monotonic clock.

The trace is written as msgpack when the daemon stops (SIGTERM). Nothing here runs in a
daemon started the ordinary way: the diagnostic costs the production path nothing.

``--light`` notes only what a frame's way to its contact message needs (``k``, ``l`` without
the elements, ``e``, ``x``, ``p``, and ``b`` without the event loop's callbacks; no ``s``,
``d`` or ``w``): a skin of a thousand elements at 100 Hz would otherwise note 10⁵ readings a
second and be slowed by its own trace (``bench/bench_humanoid.py --trace``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import math
import sys
import time
from typing import Any

import msgpack
from cellbridge.daemon.core.contacts import EstimateRequest
from cellbridge.daemon.core.domains import TimeDomains
from cellbridge.daemon.core.layout import LayoutStages
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.daemon.shell.cli import _load
from cellbridge.daemon.shell.publisher import Publisher
from cellbridge.daemon.shell.service import Service, run_service

TRACE: dict[str, list[Any]] = {"s": [], "l": [], "e": [], "p": [], "d": [], "b": [], "x": [], "w": [], "k": [], "r": []}
WORKER_TRACE = "CB_PRESS_TRACE_WORKER"  #: env: the file the contact worker notes its jobs in


def timed_estimate(req: EstimateRequest) -> list[dict[str, Any]]:
    """The worker's estimate, its start and end appended to the file $CB_PRESS_TRACE_WORKER
    names (the worker imports this module by name: bench/ is on its sys.path)."""
    import os

    from cellbridge.daemon.core.contacts import estimate

    t0, c0 = time.monotonic(), time.thread_time()
    out = estimate(req)
    with open(os.environ[WORKER_TRACE], "a") as f:
        f.write(f"{t0!r} {time.monotonic()!r} {time.thread_time() - c0!r}\n")
    return out


def _f(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _instrument(light: bool = False) -> None:
    step, snapshot, frame = LayoutStages.step, LayoutStages.snapshot, LayoutStages.frame
    contact_once, publish = Service._contact_once, Publisher.publish
    on_data, tick_once, contact_due = Service._on_data, Service._tick_once, Pipeline.contact_due

    def traced_on_data(self: Service, link: str, data: bytes, now: float) -> None:
        t0 = time.monotonic()
        on_data(self, link, data, now)
        TRACE["b"].append(("read", t0, time.monotonic()))

    def traced_tick_once(self: Service, next_status: float) -> float:
        t0 = time.monotonic()
        out = tick_once(self, next_status)
        TRACE["b"].append(("tick", t0, time.monotonic()))
        return out

    def traced_contact_due(self: Pipeline, now: float, idle: bool = False) -> float:
        due = contact_due(self, now, idle)
        if not light:
            TRACE["d"].append((now, _f(due)))
        return due

    def traced_step(self: LayoutStages, rows, raw, saturated, caps, t_sample, cycle,
                    now, held, on_time, period, inverse=True):
        res = step(self, rows, raw, saturated, caps, t_sample, cycle, now, held, on_time, period, inverse)
        if light:
            return res
        r, layout = self.readings, self.layout
        assert r is not None and layout is not None  # a frame: the layout's readings are there
        ids = layout.ids
        for row, t, h in zip(rows.tolist(), t_sample.tolist(), held.tolist()):
            slot = r.t[row] == t  # the reading's slot among the DATA readings: its touch flag as they hold it
            TRACE["s"].append((now, int(ids[row]), t, bool(slot.any() and r.touched[row, slot.argmax()]), bool(h)))
        return res

    def traced_frame(self: LayoutStages, t, cycle, sampled, raw, saturated, caps, unchanged,
                     now, inverse=True, **kw):
        got = frame(self, t, cycle, sampled, raw, saturated, caps, unchanged, now, inverse, **kw)
        # the frame's global cycle (its gate on the skin's own plan), and the monotonic clock
        # now: a paced replay's read carries its due time as ``now`` even when it came later
        TRACE["k"].append((now, t, int(cycle), time.monotonic()))
        if light:
            return got
        r, layout = self.readings, self.layout
        assert r is not None and layout is not None  # a frame: the layout's readings are there
        ids = layout.ids
        for row in sampled.tolist() + unchanged.tolist():  # every element the frame says something of
            TRACE["s"].append((now, int(ids[row]), t, bool(r.last_touched[row]), False))
        return got

    def traced_snapshot(self: LayoutStages, now: float, bridge_timeout: float, scheduled: bool):
        got = snapshot(self, now, bridge_timeout, scheduled)
        if light:
            TRACE["l"].append((now, _f(got.t_frame) if got is not None else None))
        elif self.layout is not None:
            n = self.layout.n  # (no holds: a frame is estimable once its records are in, or at its deadline)
            TRACE["l"].append((now, _f(got.t_frame) if got is not None else None, [None] * n,
                               self.layout.ids.tolist(), [], [False] * n, None))
        return got

    async def traced_contact_once(self: Service, limit: float = math.inf) -> bool:
        t0 = time.monotonic()
        n = len(TRACE["l"])
        did = await contact_once(self, limit)
        if did:
            looks = TRACE["l"][n:]
            frame = next((lk[1] for lk in looks if lk[1] is not None), None)
            TRACE["e"].append((t0, time.monotonic(), frame))
        return did

    def traced_publish(self: Publisher, topic: str, payload: dict[str, Any]) -> Any:
        out = publish(self, topic, payload)
        if topic == "contact":
            TRACE["p"].append((time.monotonic(), payload.get("t_sample"), payload.get("unknown"),
                               [(c.get("id"), c.get("x"), c.get("y"), c.get("force")) for c in payload["contacts"]]))
        return out

    from cellbridge.daemon.shell import contact_worker
    from cellbridge.daemon.shell.worker_process import WorkerProcess

    submit = WorkerProcess.submit

    def traced_submit(self: Any, fn: Any, /, *args: Any, **kwargs: Any) -> Any:
        t0 = time.monotonic()
        fut = submit(self, fn, *args, **kwargs)
        if fn is timed_estimate:
            fut.add_done_callback(lambda _: TRACE["x"].append((t0, time.monotonic())))
        return fut

    gc_began = [0.0]

    def traced_gc(phase: str, info: dict[str, Any]) -> None:
        # the interpreter's cyclic collector stops the loop too: noted as busy "gc<generation>"
        if phase == "start":
            gc_began[0] = time.monotonic()
        else:
            TRACE["b"].append((f"gc{info['generation']}", gc_began[0], time.monotonic()))

    gc.callbacks.append(traced_gc)

    run_handle = asyncio.events.Handle._run

    def traced_run(self: asyncio.events.Handle) -> None:
        # every callback of the loop that held it for more than 1 ms, by what it ran
        t0 = time.monotonic()
        run_handle(self)
        t1 = time.monotonic()
        if t1 - t0 > 0.001:
            cb = self._callback  # type: ignore[attr-defined]  # the handle's callback (private)
            task = getattr(cb, "__self__", None)
            what = (getattr(task.get_coro(), "__qualname__", "?") if isinstance(task, asyncio.Task)
                    else getattr(cb, "__qualname__", type(cb).__name__))
            TRACE["b"].append((f"cb {what}"[:80], t0, t1))

    run_once = asyncio.BaseEventLoop._run_once  # type: ignore[attr-defined]

    def traced_run_once(self: asyncio.BaseEventLoop) -> None:
        # each turn of the loop that waited in its selector, and the thread's CPU time then:
        # a turn whose wait was short, yet the wall time passed, was the thread not scheduled
        sel = self._selector  # type: ignore[attr-defined]
        if not hasattr(sel, "_cb_traced"):
            select = sel.select

            def traced_select(timeout: float | None = None) -> Any:
                t0, c0 = time.monotonic(), time.thread_time()
                out = select(timeout)
                TRACE["w"].append((t0, time.monotonic(), c0, time.thread_time(), -1.0 if timeout is None else timeout, len(out)))
                return out

            sel.select = traced_select
            sel._cb_traced = True
        run_once(self)

    if not light:
        asyncio.events.Handle._run = traced_run  # type: ignore[method-assign]
        asyncio.BaseEventLoop._run_once = traced_run_once  # type: ignore[attr-defined]

    WorkerProcess.submit = traced_submit  # type: ignore[method-assign]
    contact_worker.estimate = timed_estimate
    Service._on_data = traced_on_data  # type: ignore[method-assign]
    Service._tick_once = traced_tick_once  # type: ignore[method-assign]
    Pipeline.contact_due = traced_contact_due  # type: ignore[method-assign]
    record = TimeDomains.record

    def traced_record(self: TimeDomains, gateway: int, rec: Any, root: int, g: int, now: float,
                      serial: float) -> Any:
        if rec.part == 0:
            TRACE["r"].append((now, int(rec.index), int(rec.rate), int(rec.age_us)))
        return record(self, gateway, rec, root, g, now, serial)

    TimeDomains.record = traced_record  # type: ignore[method-assign]
    LayoutStages.step = traced_step  # type: ignore[method-assign]
    LayoutStages.snapshot = traced_snapshot  # type: ignore[method-assign]
    LayoutStages.frame = traced_frame  # type: ignore[assignment]  # its keywords passed on
    Service._contact_once = traced_contact_once  # type: ignore[method-assign]
    Publisher.publish = traced_publish  # type: ignore[method-assign]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--trace", required=True, help="msgpack file the trace is written to at the stop")
    ap.add_argument("--light", action="store_true", help="only what a frame's way to its contact needs (see the module)")
    args = ap.parse_args()
    config = _load(argparse.Namespace(config=args.config))
    import os

    worker_file = args.trace + ".worker"
    open(worker_file, "w").close()  # (a trace of an earlier run in the same place: its jobs are not this one's)
    os.environ[WORKER_TRACE] = worker_file
    _instrument(args.light)
    try:
        return run_service(args.config, config)
    finally:
        TRACE["wall_offset"] = [time.time() - time.monotonic()]
        with contextlib.suppress(OSError):
            ran = [tuple(map(float, line.split())) for line in open(worker_file)]
            # each submitted job with the worker's start and end of it (jobs run one at a time, in order)
            TRACE["x"] = [(a, s, e, b, c) for (a, b), (s, e, c) in zip(sorted(TRACE["x"]), ran)]
        with open(args.trace, "wb") as f:
            msgpack.pack(TRACE, f)


if __name__ == "__main__":
    sys.exit(main())


# -- reading a trace ---------------------------------------------------------------------
NEAR_M = 0.040  #: a contact this close to a press is its contact (bench_press_latency)


def breakdown(trace: dict[str, list[Any]], presses: list[tuple[float, float, float, float | None]],
              period: float, hold: float) -> list[dict[str, Any]]:
    """One dict per press ``(start, x, y, latency ms or None)``: the times (ms after the
    press's first touched frame ``tk``, or after the start) of each step its contact went
    through. See :func:`print_breakdown` for the columns."""
    samples = sorted(trace["s"], key=lambda r: r[0])
    looks, pubs, ests = trace["l"], trace["p"], trace["e"]
    off = trace["wall_offset"][0]
    out = []
    for start, x, y, lat in presses:
        row: dict[str, Any] = {"start": start, "lat": lat}
        out.append(row)
        during = [r for r in samples if start <= r[0] < start + hold and r[3] and r[2] >= start - period]
        if not during:
            continue
        tk = min(r[2] for r in during)
        row["gate"] = 1e3 * (tk - start)
        a1 = min(r[0] for r in during if abs(r[2] - tk) < 1e-6)
        row["first"] = 1e3 * (a1 - tk)
        of_k = [r for r in samples if abs(r[2] - tk) < 1e-6 and r[0] >= start]
        row["sent_k"] = sorted((r[1], round(1e3 * (r[0] - tk), 1), r[3]) for r in of_k)
        row["last_k"] = 1e3 * (max(r[0] for r in of_k) - tk)
        before = [lk for lk in looks if lk[0] <= a1]
        lk = before[-1] if before else looks[0]
        ids, bounds, held = lk[3], lk[2], lk[5]
        ends = []
        for j, b in enumerate(ids):
            got = next((r for r in samples if r[1] == b and r[2] >= tk - 1e-6 and r[0] >= start), None)
            end = got[0] if got else math.inf
            if held[j] and bounds[j] is not None:
                end = min(end, tk + bounds[j])
            ends.append((end, b, bounds[j]))
        e_end, e_b, e_bound = max(ends)
        row["hold"] = 1e3 * (e_end - tk)
        row["holder"] = (e_b, None if e_bound is None else round(1e3 * e_bound, 1))
        look = next((lk for lk in looks if lk[0] >= start and lk[1] is not None and lk[1] >= tk - 1e-6), None)
        if look is not None:
            row["look"] = 1e3 * (look[0] - tk)
        pub = next((p for p in pubs if p[0] >= start and any(
            (c[1] - x) ** 2 + (c[2] - y) ** 2 <= NEAR_M ** 2 for c in p[3])), None)
        if pub is None:
            continue
        tp = pub[1] - off
        row["pub"] = 1e3 * (pub[0] - tk)
        row["frames_after"] = round((tp - tk) / period)
        job = next((j for j in reversed(trace.get("x", [])) if j[0] <= pub[0] and j[3] <= pub[0]), None)
        if job is not None and "look" in row and job[0] >= tk + row["look"] / 1e3 - 1e-4:
            # the contact's job: submitted → worker began → worker ended → future done → published
            row["job"] = tuple(round(1e3 * v, 2) for v in (job[1] - job[0], job[2] - job[1], job[3] - job[2],
                                                            pub[0] - job[3], job[4]))
        est = next((e for e in ests if e[2] is not None and abs(e[2] - tp) < 1e-6), None)
        if est is not None:
            row["est"] = (1e3 * (est[0] - tk), 1e3 * (est[1] - tk))
        if lat is not None:
            row["recv"] = lat - 1e3 * (pub[0] - start)
        # what the frames between the first touched one and the contact's said
        why = []
        for p in pubs:
            t = p[1] - off if p[1] is not None else math.nan
            if p[0] >= start and tk - 1e-6 <= t < tp - 1e-6:
                why.append((round((t - tk) / period), [(c[0], round(1e3 * c[1], 1), round(1e3 * c[2], 1))
                                                       for c in p[3]], p[2]))
        row["between"] = why
        row["looked"] = [round((lk[1] - tk) / period) for lk in looks
                         if lk[1] is not None and start <= lk[0] <= pub[0] and lk[1] >= tk - 1e-6]
        # every look from the first touched reading to the contact: (ms after tk, frame it could
        # take, frame it took), frames counted from tk
        row["looks"] = [(round(1e3 * (lk[0] - tk), 1), None if lk[6] is None else round((lk[6] - tk) / period),
                         None if lk[1] is None else round((lk[1] - tk) / period))
                        for lk in looks if a1 <= lk[0] <= pub[0]]
        row["dues"] = [(round(1e3 * (d[0] - tk), 1), None if d[1] is None else round(1e3 * (d[1] - tk), 1))
                       for d in trace["d"] if a1 <= d[0] <= pub[0]]
        row["busy"] = [(b[0], round(1e3 * (b[1] - tk), 1), round(1e3 * (b[2] - b[1]), 1))
                       for b in trace["b"] if a1 <= b[2] and b[1] <= pub[0] and b[2] - b[1] > 0.001]
    return out


def print_breakdown(rows: list[dict[str, Any]], share: float = 0.1) -> None:
    """The slowest ``share`` of presses, and the median press, step by step (ms)."""
    seen = sorted((r for r in rows if r.get("lat") is not None), key=lambda r: r["lat"])
    if not seen:
        print("no press seen")
        return
    slow = seen[-max(1, round(share * len(seen))):]
    cols = ["lat", "gate", "first", "last_k", "hold", "look", "pub", "recv", "frames_after"]
    print("\nper press, ms: gate = first touched frame's gate after the press start; first/last_k = "
          "its first touched / last reading of that frame at the daemon; hold = when that frame "
          "became estimable (its records in, or its deadline); look = the first "
          "look that took it; pub = its contact handed to ZeroMQ; (all after the frame's gate); "
          "recv = ZeroMQ to the subscriber; frames_after = frames between the first touched one "
          "and the first contact's")
    print("  " + "  ".join(f"{c:>12}" for c in cols) + "  holder(bound)  looked frames")

    def fmt(v: Any) -> str:
        return f"{v:12.1f}" if isinstance(v, float) else f"{v!s:>12}"

    for q in (0.5, 0.9):  # each column's own quantile over every press seen
        cells = []
        for c in cols:
            xs = sorted(r[c] for r in seen if isinstance(r.get(c), (int, float)))
            cells.append(fmt(float(xs[min(len(xs) - 1, int(q * len(xs)))])) if xs else fmt("-"))
        print(f" p{round(100 * q)} of each column:\n  " + "  ".join(cells))
    jobs = [r["job"] for r in seen if r.get("job")]
    if jobs:
        print(f" the contact's job in the worker ({len(jobs)} presses), ms, p50/p90/p99/max:")
        for i, what in enumerate(("submitted -> worker began", "worker's estimate", "worker ended -> future done",
                                  "future done -> published", "(the estimate's CPU)")):
            xs = sorted(j[i] for j in jobs)
            qs = [xs[min(len(xs) - 1, int(q * len(xs)))] for q in (0.5, 0.9, 0.99)] + [xs[-1]]
            print(f"   {what:<28}" + "".join(f"{v:8.2f}" for v in qs))
    late = [r for r in seen if r.get("frames_after")]
    print(f" presses whose first contact was not on their first touched frame: {len(late)} of {len(seen)}")
    # the usual reason: the frame's holds ran out before its first touched reading came, so
    # it was estimated with the pressed elements' held (untouched) readings
    early = [r for r in late if isinstance(r.get("first"), float) and isinstance(r.get("hold"), float)
             and r["first"] > r["hold"]]
    print(f"   of which the frame was estimable before its first touched reading arrived (an onset "
          f"later than the holds): {len(early)}, by {sorted(round(r['first'] - r['hold'], 1) for r in early)} ms")
    for label, rs in (("median press", [seen[len(seen) // 2]]), ("slowest", slow)):
        print(f" {label}:")
        for r in rs:
            print("  " + "  ".join(fmt(r.get(c, "-")) for c in cols) + f"  {r.get('holder')}  {r.get('looked')}")
            if r.get("frames_after"):
                print(f"      frames before the contact's: {r.get('between')}")
            if label == "slowest":
                print(f"      looks (ms after tk, frame it could take, frame taken): {r.get('looks')}")
                print(f"      contact_due (ms after tk: asked, due): {r.get('dues')}")
                print(f"      loop busy > 1 ms (what, ms after tk, ms): {r.get('busy')}")
            print(f"      readings of the first touched frame (bridge, ms after its gate, touched): {r.get('sent_k')}")
