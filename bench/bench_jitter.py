"""Delivery jitter of every bridge, read off the gateway's pseudo-terminal (real processes).

Run: ``.venv/bin/python bench/bench_jitter.py [--seconds 20] [--rate 100] [--rt|--no-rt]``.
Starts ``cellbridge mesh up`` of a periodic 4x4 grid (the medium, the world and one process
per bridge), at real-time priority (``chrt -f 10``) when the machine permits it (said in
the output, and tried by default), opens the gateway's pty as the daemon would, and decodes
the READOUT records it writes. A bridge's sample of frame ``k`` is *delivered* when the
record holding it is read; its delay is that arrival minus the frame's gate start mapped to
host time. The map (offset and skew of the skin's mesh time against the host's monotonic
clock) is the lower envelope of all arrivals (a line through the earliest arrival of each
second, fitted), so a bridge's *jitter* is its delay above the fastest delivery: the table
gives per bridge the p50, p99 and max of it, frames read and frames that never named it.
Target: every bridge's p99 <= 20 ms. Under real time, this reader runs at the skin's
priority too (it stands for the daemon). Every process is stopped (its process group) at the
end, also on failure.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import serial
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import mesh_to_toml
from cellbridge.protocol import FrameType, StreamDecoder

from realskin import free_base_port, rt_permitted

TARGET_MS = 20.0


def gateway_device(proc: subprocess.Popen[bytes], timeout: float) -> str:
    """The pty mesh up prints for the gateway ('gateway <id> <device>')."""
    assert proc.stdout is not None
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        line = proc.stdout.readline().decode(errors="replace")
        if not line:
            break
        if line.startswith("gateway "):
            return line.split()[2]
    raise RuntimeError("mesh up printed no gateway line")


def read_records(dev: str, seconds: float) -> list[tuple[float, int, int, tuple[int, ...]]]:
    """(arrival, index, rate, bridges with a sample) of every READOUT record part read."""
    out = []
    dec = StreamDecoder()
    with serial.Serial(dev, timeout=0.05) as port:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            chunk = port.read(max(1, port.in_waiting))  # what is there (read(n) waits for n bytes)
            now = time.monotonic()
            for f in dec.feed(chunk):
                if f.type is FrameType.READOUT:
                    r = f.payload
                    out.append((now, r.index, r.rate, tuple(s.bridge for s in r.samples)))  # type: ignore[union-attr]  # a READOUT payload
    return out


def jitter(records: list[tuple[float, int, int, tuple[int, ...]]], rate: int, bridges: list[int]) -> None:
    recs = [r for r in records if r[2] == rate]
    if not recs:
        print("no READOUT records read")
        return
    t = np.array([r[0] for r in recs])
    g = np.array([r[1] / rate for r in recs])  # gate start in mesh seconds
    # lower envelope: the earliest (arrival - gate) of each second, a line through them
    d = t - g
    sec = np.floor(g - g[0]).astype(int)
    lo_x, lo_y = [], []
    for s in np.unique(sec):
        i = np.flatnonzero(sec == s)
        j = i[np.argmin(d[i])]
        lo_x.append(g[j])
        lo_y.append(d[j])
    if len(lo_x) >= 2:
        a, b = np.polyfit(lo_x, lo_y, 1)
    else:
        a, b = 0.0, float(min(lo_y))
    extra = (d - (a * g + b)) * 1000
    extra -= min(0.0, float(extra.min()))
    per: dict[int, list[float]] = defaultdict(list)
    indices = sorted({r[1] for r in recs})
    for (_, _, _, named), e in zip(recs, extra):
        for b_ in named:
            per[b_].append(float(e))
    print(f"{'bridge':>6} {'frames':>7} {'not named':>9} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} {'target':>7} {'ok':>4}")
    worst = 0.0
    for b_ in bridges:
        v = np.array(per.get(b_, [np.nan]))
        p99 = float(np.percentile(v, 99))
        worst = max(worst, p99) if np.isfinite(p99) else float("inf")
        print(f"{b_:>6} {len(per.get(b_, [])):>7} {len(indices) - len(per.get(b_, [])):>9} "
              f"{np.percentile(v, 50):>7.2f} {p99:>7.2f} {np.nanmax(v):>7.2f} {TARGET_MS:>7.0f} "
              f"{'yes' if p99 <= TARGET_MS else 'NO':>4}")
    print(f"worst bridge p99 {worst:.2f} ms (target <= {TARGET_MS:g} ms); mesh time runs "
          f"{a * 1e6:+.1f} ppm against the host's clock")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="seconds measured (default 20)")
    ap.add_argument("--settle", type=float, default=15.0, help="seconds after start-up before (default 15)")
    ap.add_argument("--rate", type=int, default=100, help="sampling rate in Hz (default 100)")
    ap.add_argument("--side", type=int, default=4, help="grid side (default 4: a 4x4 skin)")
    ap.add_argument("--rt", action=argparse.BooleanOptionalAction, default=True,
                    help="run the skin at real-time priority (chrt -f 10) when permitted (default on)")
    args = ap.parse_args()
    mesh = meshgen.grid(args.side, args.side)
    rt = args.rt and rt_permitted()
    print(f"periodic {mesh.name} at {args.rate} Hz, real processes, READOUT records read off the gateway's pty; "
          f"{'real-time priority (SCHED_FIFO 10)' if rt else 'normal priority' + (' (real-time not permitted here)' if args.rt else '')}; "
          f"load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "skin.toml"
        path.write_text(mesh_to_toml(mesh))
        cmd = [sys.executable, "-m", "cellbridge", "mesh", "up", str(path), "--base-port", str(free_base_port()),
               "--rate", str(args.rate)]
        if rt:
            cmd = ["chrt", "-f", "10", *cmd]  # inherited by every process of the skin
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            dev = gateway_device(proc, 60.0)
            if rt:  # this reader stands for the daemon: at the skin's priority, so that what it
                # measures is the skin's delivery, not its own turn for the CPU on a busy machine
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
            time.sleep(args.settle)
            records = read_records(dev, args.seconds)
        finally:
            try:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            except ProcessLookupError:
                pass
    jitter(records, args.rate, list(mesh.ids))


if __name__ == "__main__":
    main()
