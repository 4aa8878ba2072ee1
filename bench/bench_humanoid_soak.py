"""The humanoid's daemon for an hour: does its memory stay flat?

Prints tables; asserts nothing. Run (``--minutes`` of recording, plus its generation,
a few minutes for an hour of event-based skin)::

    .venv/bin/python bench/bench_humanoid_soak.py [--minutes 60] [--reporting event:30] [--interval 60]

A robot runs the daemon for days, so a leak of a few kB per contact or per frame is a
failure that no short bench shows. This one generates ``--minutes`` of the humanoid's
traffic (``cellbridge/skins/humanoid.toml``, 100 Hz, rounds of 10 simultaneous presses
every 3 s: :mod:`bench_humanoid`'s recording, only longer), replays it into the real
daemon at recorded speed (one ``replay:`` link per gateway) and, every ``--interval``
seconds, notes the resident memory (VmRSS) of the daemon's process and of its contact
worker, its CPU and its frame counters from ``health``. Then the growth: a least-squares
slope of each process's RSS over the second half of the run (MiB per hour; the first
half holds the warm-up: caches, numba's compiled code, allocator arenas), and the peak
(VmHWM) against the target of 250 MiB.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from timing import table

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout too
from cellbridge.daemon.shell.skin_file import load_skin  # noqa: E402

from bench_humanoid import HUMANOID, generate, group_processes  # noqa: E402
from daemon_harness import Client, daemon, write_config  # noqa: E402

TARGET_MIB = 250


def group_memory(pgid: int) -> dict[str, tuple[float, float, float]]:
    """``{"daemon" | "worker PID": (VmRSS MiB, VmHWM MiB, CPU s)}`` of the daemon's process group."""
    return {("daemon" if pid == pgid else f"worker {pid}"): v for pid, v in group_processes(pgid).items()}


def slope_mib_per_hour(points: list[tuple[float, float]]) -> float:
    """Least-squares slope of (s, MiB) over the second half of ``points``, in MiB per hour."""
    half = points[len(points) // 2:]
    if len(half) < 2:
        return float("nan")
    t, m = np.array(half).T
    return float(np.polyfit(t, m, 1)[0] * 3600)


def soak(minutes: float, reporting: str, interval: float, into: Path) -> None:
    skin = load_skin(HUMANOID)
    seconds = minutes * 60
    c0 = time.monotonic()
    gen = generate(skin, reporting, seconds, into)
    print(f"{HUMANOID.name}: {skin.n} elements, {len(gen['gateways'])} gateways; {seconds:.0f} s of {reporting} "
          f"generated in {time.monotonic() - c0:.0f} s ({gen['bytes'] / 1e6:.0f} MB)", flush=True)
    links = [{"name": f"gw{g}", "url": f"replay:{into / f'gw{g}.cbcap'}", "replay_speed": 1.0,
              "wait_for_subscriber": True} for g in gen["gateways"]]
    cfg = into / "daemon.toml"
    ep = write_config(cfg, links, layout={"file": str(HUMANOID)}, health={"interval": 1.0})
    client = Client(ep, (b"contact", b"health"))
    rows: list[list[object]] = []
    series: dict[str, list[tuple[float, float]]] = {}
    hwm: dict[str, float] = {}
    health: dict = {}
    messages = 0
    try:
        with daemon(cfg, stderr=into / "daemon.err") as proc:
            start = time.monotonic()
            next_note = start
            cpu_last: dict[str, float] = {}
            t_last = start
            finished = False
            while not finished and time.monotonic() - start < seconds + 60:
                got = client.recv(0.5)
                if got is not None:
                    topic, m = got
                    if topic == "health":
                        health = m
                        lk = m.get("links", {})
                        finished = bool(lk) and all(ln.get("replay_finished") for ln in lk.values())
                    else:
                        messages += 1
                elif proc.poll() is not None:
                    print(f"the daemon exited ({proc.returncode}): see {into / 'daemon.err'}")
                    break
                now = time.monotonic()
                if now < next_note and not finished:
                    continue
                next_note += interval
                mem = group_memory(proc.pid)
                el = now - start
                fr = health.get("frames", {})
                cpu = sum(v[2] for v in mem.values())
                cores = (cpu - sum(cpu_last.values())) / (now - t_last) if cpu_last else float("nan")
                cpu_last, t_last = {k: v[2] for k, v in mem.items()}, now
                for name, (rss, peak, _) in mem.items():
                    series.setdefault(name, []).append((el, rss))
                    hwm[name] = max(hwm.get(name, 0.0), peak)
                rows.append([f"{el / 60:.1f}", *(f"{mem[n][0]:.1f}" for n in sorted(mem)), f"{cores:.2f}",
                             f"{messages:,}", fr.get("frames_complete", "-"), fr.get("frames_by_deadline", "-"),
                             fr.get("frames_missed", "-")])
                print("  ".join(str(v) for v in rows[-1]), flush=True)
    finally:
        client.sub.close()
        client.ctx.term()
    names = sorted(series)
    table(f"The daemon on {minutes:.0f} min of the humanoid ({reporting}), every {interval:.0f} s "
          "(RSS MiB per process; CPU in cores since the row before)",
          ["minute", *(f"{n} RSS" for n in names), "CPU (cores)", "contact messages", "frames complete",
           "by deadline", "missed"], rows)
    table(f"Growth over the second half and peak (target: peak ≤ {TARGET_MIB} MiB, no growth)",
          ["process", "first RSS MiB", "last RSS MiB", "slope MiB/hour (second half)", "peak (VmHWM) MiB"],
          [[n, f"{series[n][0][1]:.1f}", f"{series[n][-1][1]:.1f}", f"{slope_mib_per_hour(series[n]):+.2f}",
            f"{hwm[n]:.1f}"] for n in names])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="length of the recording and the run (default 60)")
    ap.add_argument("--reporting", default="event:30",
                    help="the skin's reporting: periodic or event:THRESHOLD (default event:30)")
    ap.add_argument("--interval", type=float, default=60.0, help="s between memory notes (default 60)")
    a = ap.parse_args()
    if a.minutes <= 0 or a.interval <= 0:
        ap.error("--minutes and --interval must be positive")
    with tempfile.TemporaryDirectory(prefix="bench_humanoid_soak.") as tmp:
        soak(a.minutes, a.reporting, a.interval, Path(tmp))
    return 0


if __name__ == "__main__":
    sys.exit(main())
