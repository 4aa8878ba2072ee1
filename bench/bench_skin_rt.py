"""The emulated skin's real processes: readout latency, delivery jitter and CPU, one run.

Run: ``.venv/bin/python bench/bench_skin_rt.py [--seconds 20] [--rate 100] [--rt|--no-rt]
[--burners 0] [--reporting periodic]``.

Starts ``cellbridge mesh up`` of a side×side grid (one gateway in a corner), at real-time
priority (``chrt -f 10``, inherited by every process of the skin, the medium one above)
when ``--rt`` and permitted, reads its gateway's pseudo-terminal as the daemon would (this
reader at the skin's priority), and after ``--settle`` s measures for ``--seconds`` s:

1. **readout latency**: each READOUT record part's arrival minus its frame's gate end,
   on the host's monotonic clock. The gate start of frame ``k`` is the gateway's own plan
   (its last line names the ticks it starts two frames' gates 10 s apart; frames between
   follow on a straight line), plus the gates' length: what the skin adds after the sample
   exists (relay hops, slot waits, the pty);
2. **delivery jitter** of every bridge (as ``bench/bench_jitter.py``): its delay above the
   lower envelope of all arrivals; target p99 <= 20 ms for every bridge;
3. **CPU** of every process of the skin over the window (``/proc/<pid>/stat`` user+system
   ticks): per bridge, the medium, the world, and the skin's total (bridges + medium) in %
   of one core; target: the total at most 50 % for a periodic 4x4 at 100 Hz;
4. what the bridges counted in the window's run (late gates, records late at a relay,
   records failed, missing entries), from their last lines.

``--burners N`` runs N busy loops at normal priority beside it (a loaded machine).
``--hold B:MS:EVERY`` holds bridge B's process up (SIGSTOP, then SIGCONT ``MS`` ms later)
every ``EVERY`` ms during the window: a process the host does not run for tens of ms, as
on a loaded machine, but on cue; the jitter table's "not named" column says how many
frames went without its sample. Every process started is stopped (its process group),
also on failure.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import serial
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import mesh_to_toml
from cellbridge.protocol import FrameType, StreamDecoder

from realskin import free_base_port, rt_permitted
from timing import table
from unwind import unwind_on_signals

CLOCK_HZ = 50_000_000
JITTER_TARGET_MS = 20.0
CPU_TARGET = 50.0
CLK_TCK = os.sysconf("SC_CLK_TCK")


def skin_processes(pgid: int) -> dict[int, str]:
    """pid -> role ('bridge N', 'medium', 'world', 'up') of every process in the group."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd = (d / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[2]) != pgid:
            continue
        # forked bridges carry their command line as one title (setproctitle): split on spaces too
        args = " ".join(a.decode(errors="replace") for a in cmd).split()
        if "bridge" in args and "--id" in args:
            out[int(d.name)] = f"bridge {args[args.index('--id') + 1]}"
        elif "medium" in args:
            out[int(d.name)] = "medium"
        elif "world" in args:
            out[int(d.name)] = "world"
        elif "up" in args:
            out[int(d.name)] = "up"
    return out


def cpu_ticks(pid: int) -> tuple[int, int, int]:
    """(user ticks, system ticks, voluntary context switches: its wakes) of a process."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0, 0, 0
    fields = stat[stat.rindex(")") + 2:].split()
    m = re.search(r"^voluntary_ctxt_switches:\s+(\d+)", status, re.M)
    return int(fields[11]), int(fields[12]), int(m.group(1)) if m else 0


Record = tuple[float, int, int, tuple[int, ...], int, dict[int, int]]


def hold_up(pid: int, held: float, every: float, until: float) -> None:
    """SIGSTOP ``pid`` for ``held`` s every ``every`` s until ``until`` (monotonic); always
    leaves it running."""
    try:
        while time.monotonic() < until:
            os.kill(pid, signal.SIGSTOP)
            try:
                time.sleep(held)
            finally:
                os.kill(pid, signal.SIGCONT)
            time.sleep(max(0.0, every - held))
    except ProcessLookupError:
        pass


def read_records(port: serial.Serial, dec: StreamDecoder, seconds: float) -> list[Record]:
    """(arrival, index, rate, bridges with a sample, missing entries, bridge -> c1) of every
    READOUT part read."""
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        chunk = port.read(max(1, port.in_waiting))
        now = time.monotonic()
        for f in dec.feed(chunk):
            if f.type is FrameType.READOUT:
                r = f.payload
                out.append((now, r.index, r.rate, tuple(s.bridge for s in r.samples),  # type: ignore[union-attr]
                            len(r.missing), {s.bridge: s.c1 for s in r.samples}))  # type: ignore[union-attr]
    return out


def press_onsets(port: serial.Serial, dec: StreamDecoder, base: int, mesh, n: int, seed: int,
                 hold: float = 0.4) -> list[tuple[float, int, float]]:
    """``n`` presses at the centre of random elements, one at a time; for each, (s from the
    press's start in the world to the first record read whose sample of the pressed element
    moved half-way from its reading before the press to its reading during it, the frame's
    index, the record's arrival). NaN when no sample showed it."""
    import random

    from realskin import world_press

    rng = random.Random(seed)
    out = []
    for _ in range(n):
        b = rng.choice(list(mesh.ids))
        x, y = mesh.bridge(b).position
        before = [r[5][b] for r in read_records(port, dec, 0.2) if b in r[5]]
        start = world_press(base, x, y, hold)
        during = read_records(port, dec, hold + 0.3)
        vals = [(a, i, r5[b]) for a, i, _, _, _, r5 in during if b in r5 and a >= start]
        steady = [v for a, _, v in vals if start + 0.2 <= a <= start + hold]
        if not before or not steady:
            out.append((float("nan"), -1, float("nan")))
            continue
        b0, b1 = float(np.median(before)), float(np.median(steady))
        hit = next(((a, i) for a, i, v in vals if abs(v - b0) >= 0.5 * abs(b1 - b0)), None)
        out.append((float("nan"), -1, float("nan")) if hit is None else (hit[0] - start, hit[1], hit[0]))
    return out


def pct(v: list[float] | np.ndarray, q: float) -> float:
    return float(np.percentile(np.asarray(v), q)) if len(v) else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="seconds measured (default 20)")
    ap.add_argument("--settle", type=float, default=12.0, help="seconds after start-up before (default 12)")
    ap.add_argument("--rate", type=int, default=100, help="sampling rate in Hz (default 100)")
    ap.add_argument("--side", type=int, default=4, help="grid side (default 4: a 4x4 skin)")
    ap.add_argument("--gateway", type=int, default=None, help="the gateway's bridge id (default: the grid's centre)")
    ap.add_argument("--reporting", default="periodic", help="periodic (default) or event:THRESHOLD")
    ap.add_argument("--rt", action=argparse.BooleanOptionalAction, default=True,
                    help="run the skin at real-time priority (chrt -f 10) when permitted (default on)")
    ap.add_argument("--burners", type=int, default=0, help="busy loops beside the skin (default 0)")
    ap.add_argument("--hold", default=None, metavar="B:MS:EVERY",
                    help="hold bridge B's process up for MS ms every EVERY ms during the window (SIGSTOP/SIGCONT)")
    ap.add_argument("--presses", type=int, default=0,
                    help="after the window, press this many times (0.4 s each) at random elements' centres "
                         "and time each press from the world to its first sample on the pty (default 0)")
    args = ap.parse_args()
    unwind_on_signals()
    mesh = meshgen.grid(args.side, args.side, None if args.gateway is None else (args.gateway,))
    gw = mesh.gateways[0]
    rt = args.rt and rt_permitted()
    gate_s = Settings(rate_hz=args.rate).measure_cycles() / CLOCK_HZ
    burners: list[subprocess.Popen[bytes]] = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "skin.toml"
        path.write_text(mesh_to_toml(mesh))
        base = free_base_port()
        cmd = [sys.executable, "-m", "cellbridge", "mesh", "up", str(path), "--base-port", str(base),
               "--rate", str(args.rate), "--reporting", args.reporting]
        if rt:
            cmd = ["chrt", "-f", "10", *cmd]
        log = open(Path(tmp) / "mesh.log", "w+")
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, start_new_session=True)
        try:
            for _ in range(args.burners):
                burners.append(subprocess.Popen(["sh", "-c", "while :; do :; done"], start_new_session=True))
            assert proc.stdout is not None
            dev = ""
            end = time.monotonic() + 60
            while not dev and time.monotonic() < end:
                line = proc.stdout.readline().decode(errors="replace")
                if not line:
                    raise RuntimeError("mesh up ended before its gateway line")
                if line.startswith("gateway "):
                    dev = line.split()[2]
            if rt:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
            time.sleep(args.settle)
            procs = skin_processes(proc.pid)
            before = {p: cpu_ticks(p) for p in procs}
            t0 = time.monotonic()
            dec = StreamDecoder()
            holder = None
            if args.hold:
                hb, hms, hevery = (int(x) for x in args.hold.split(":"))
                hpid = next(p for p, role in procs.items() if role == f"bridge {hb}")
                holder = threading.Thread(target=hold_up, args=(hpid, hms / 1000, hevery / 1000, t0 + args.seconds),
                                          daemon=True)
                holder.start()
            with serial.Serial(dev, timeout=0.05) as port:
                records = read_records(port, dec, args.seconds)
                wall = time.monotonic() - t0
                after = {p: cpu_ticks(p) for p in procs}
                cpu = {role: 100.0 * (sum(after[p][:2]) - sum(before[p][:2])) / CLK_TCK / wall
                       for p, role in procs.items()}
                sys_cpu = {role: 100.0 * (after[p][1] - before[p][1]) / CLK_TCK / wall for p, role in procs.items()}
                wakes = {role: (after[p][2] - before[p][2]) / wall for p, role in procs.items()}
                onsets = press_onsets(port, dec, base, mesh, args.presses, 1)
        finally:
            for b in burners:
                os.killpg(b.pid, signal.SIGKILL)
                b.wait()
            try:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            except ProcessLookupError:
                pass
        log.seek(0)
        lines = log.read().splitlines()
    last: dict[int, dict] = {}
    for line in lines:
        if line.startswith("{"):
            try:
                d = json.loads(line)
                last[int(d["bridge"])] = d
            except (ValueError, KeyError):
                pass
    load = os.getloadavg()[0]
    print(f"periodic {mesh.name} at {args.rate} Hz ({args.reporting}), gateway {gw}, "
          f"{'real-time priority (SCHED_FIFO 10)' if rt else 'normal priority'}, {args.burners} burners, "
          f"load {load:.1f}; {args.seconds:g} s measured after {args.settle:g} s")
    recs = [r for r in records if r[2] == args.rate]
    # 1. latency: gate end of frame k from the gateway's plan (two gate ticks 10 s apart)
    gates = last.get(gw, {}).get("gates", {})
    if len(gates) == 2 and recs:
        (k0, t0_), (k1, t1_) = sorted((int(k), v / CLOCK_HZ) for k, v in gates.items())
        lat = [1000 * (a - (t0_ + (i - k0) * (t1_ - t0_) / (k1 - k0) + gate_s)) for a, i, *_ in recs]
        # the first part of each frame (a record in parts: the first part's arrival)
        first: dict[int, float] = {}
        for (_a, i, *_), v in zip(recs, lat):
            first.setdefault(i, v)
        fl = list(first.values())
        table("readout: gate end -> record read off the gateway's pty (ms)",
              ["what", "n", "p50", "p90", "p99", "max"],
              [[what, len(v), *(f"{pct(v, q):.1f}" for q in (50, 90, 99)), f"{max(v):.1f}"]
               for what, v in (("first part of a frame", fl), ("every part", lat))])
    else:
        print("readout latency: the gateway's plan of gates was not in its last line")
    if onsets:
        ok = [1000 * o for o, _, _ in onsets if np.isfinite(o)]
        rows = [["press start -> first sample showing it on the pty", len(ok), len(onsets) - len(ok),
                 *(f"{pct(ok, q):.1f}" for q in (50, 90, 99)), f"{max(ok, default=float('nan')):.1f}"]]
        if len(gates) == 2:
            gend = [1000 * (a - (t0_ + (i - k0) * (t1_ - t0_) / (k1 - k0) + gate_s)) for o, i, a in onsets
                    if np.isfinite(o)]
            rows.append(["  of which: that frame's gate end -> on the pty", len(gend), "",
                         *(f"{pct(gend, q):.1f}" for q in (50, 90, 99)), f"{max(gend, default=float('nan')):.1f}"])
        table("presses (the skin's share of a press's latency, no daemon)",
              ["what", "n", "not seen", "p50 ms", "p90 ms", "p99 ms", "max ms"], rows)
    # 2. jitter
    if recs:
        t = np.array([r[0] for r in recs])
        g = np.array([r[1] / args.rate for r in recs])
        d = t - g
        sec = np.floor(g - g[0]).astype(int)
        lo_x, lo_y = [], []
        for s in np.unique(sec):
            in_s = np.flatnonzero(sec == s)
            j = in_s[np.argmin(d[in_s])]
            lo_x.append(g[j])
            lo_y.append(d[j])
        slope, floor = np.polyfit(lo_x, lo_y, 1) if len(lo_x) >= 2 else (0.0, float(min(lo_y)))
        extra = (d - (slope * g + floor)) * 1000
        extra -= min(0.0, float(extra.min()))
        per: dict[int, list[float]] = defaultdict(list)
        for r, e in zip(recs, extra):
            for b_ in r[3]:
                per[b_].append(float(e))
        n_frames = len({r[1] for r in recs})
        worst = max((pct(per.get(b_, []), 99) if per.get(b_) else float("inf")) for b_ in mesh.ids)
        rows = [[b_, len(per.get(b_, [])), n_frames - len(per.get(b_, [])), f"{pct(per.get(b_, []), 50):.2f}",
                 f"{pct(per.get(b_, []), 99):.2f}", f"{max(per.get(b_, [float('nan')])):.2f}"] for b_ in mesh.ids]
        table(f"delivery jitter per bridge (ms above the fastest delivery); target p99 <= {JITTER_TARGET_MS:g}",
              ["bridge", "frames", "not named", "p50", "p99", "max"], rows)
        print(f"worst bridge p99 {worst:.2f} ms: {'ok' if worst <= JITTER_TARGET_MS else 'OVER'}; "
              f"missing entries in the records: {sum(r[4] for r in recs)}")
    else:
        print("no READOUT records read")
    # 3. CPU
    bridges = {int(r.split()[1]): v for r, v in cpu.items() if r.startswith("bridge")}
    total = sum(bridges.values()) + cpu.get("medium", 0.0)
    bv = list(bridges.values())
    table("CPU, % of one core over the window",
          ["bridges (sum)", "bridge min", "bridge p50", "bridge max", "medium", "world", "skin (bridges + medium)",
           "target"],
          [[f"{sum(bv):.1f}", f"{min(bv):.1f}", f"{pct(bv, 50):.1f}", f"{max(bv):.1f}", f"{cpu.get('medium', 0):.1f}",
            f"{cpu.get('world', 0):.1f}", f"{total:.1f}", f"<= {CPU_TARGET:g}"]])
    bw = [v for r, v in wakes.items() if r.startswith("bridge")]
    bs = [v for r, v in sys_cpu.items() if r.startswith("bridge")]
    table("wakes (voluntary context switches) per second, and the kernel's share of the CPU",
          ["bridge min", "bridge p50", "bridge max", "medium", "bridges' system %", "medium's system %"],
          [[f"{min(bw):.0f}", f"{pct(bw, 50):.0f}", f"{max(bw):.0f}", f"{wakes.get('medium', 0):.0f}",
            f"{sum(bs):.1f}", f"{sys_cpu.get('medium', 0):.1f}"]])
    per_bridge = sorted((int(r.split()[1]), v) for r, v in cpu.items() if r.startswith("bridge"))
    table("CPU (% of one core) and wakes per second of each bridge process",
          ["bridge", "CPU %", "wakes/s"],
          [[str(b), f"{v:.1f}", f"{wakes.get(f'bridge {b}', 0):.0f}"] for b, v in per_bridge])
    # 4. counters (whole run)
    keys = ("late_gates", "behind_gates", "readout_late", "readout_failed", "readout_missing", "urgent_expired",
            "udp_drops", "retries")
    table("bridge counters over the whole run (sum over bridges)", list(keys),
          [[sum(int(d["counters"].get(k, 0)) for d in last.values()) for k in keys]])
    if args.hold:
        hb = int(args.hold.split(":")[0])
        print(f"bridge {hb}'s counters (held up): {json.dumps(last.get(hb, {}).get('counters', {}))}")
        print("records late at a relay, per bridge:",
              {b: d["counters"].get("readout_late", 0) for b, d in sorted(last.items()) if d["counters"].get("readout_late")})
    print(f"(bridges that printed their counters: {len(last)} of {len(mesh.ids)}; "
          f"{len([x for x in lines if re.match('medium:', x)])} medium line)")


if __name__ == "__main__":
    main()
