"""How often ``cellbridge demo --check`` tells the truth: seam and corner presses, N runs each.

Run: ``.venv/bin/python bench/bench_demo.py [--runs 20] [--burn] [--cases seam,corner]``.
Each run starts the whole chain as a user would (an emulated 4×4 skin in real processes,
the daemon on its gateway's pty), presses, and checks the published contact: within 1 mm
and 5 % of the press, with exactly one contact id. ``--burn`` keeps every core busy with a
CPU-burning process per core for the whole measurement (the loaded-robot case). Prints a
table per case: runs, passed, the worst position and force errors, and the runs with more
than one id. The burners are stopped on exit, also on Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from timing import table

CLI = shutil.which("cellbridge", path=str(Path(sys.executable).parent)) or "cellbridge"
CASES = {"seam": (0.057, 0.040), "corner": (0.0585, 0.0625)}
BURN = "while True: pass"


def one_run(x: float, y: float) -> dict:
    """One ``demo --check --json`` run: its JSON result, plus ``ok`` and ``error`` keys."""
    try:
        r = subprocess.run([CLI, "demo", "--check", "--json", "--x", str(x), "--y", str(y)],
                           capture_output=True, text=True, timeout=280)
    except subprocess.TimeoutExpired:
        return {"ok": False, "error": "timeout"}
    try:
        res = json.loads(r.stdout)
    except json.JSONDecodeError:
        return {"ok": False, "error": (r.stderr.strip().splitlines() or ["no output"])[-1]}
    got = res.get("reported") or {}
    ok = (r.returncode == 0 and bool(got) and abs(got["x"] - x) <= 1e-3 and abs(got["y"] - y) <= 1e-3
          and abs(got["force"] - 3.0) <= 0.15 and len(res.get("ids", [])) == 1)
    res.update(ok=ok, error="" if ok else f"rc {r.returncode}")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20, help="runs per case (default 20)")
    ap.add_argument("--burn", action="store_true", help="keep every core busy while measuring")
    ap.add_argument("--cases", default="seam,corner", help="comma-separated: seam, corner")
    args = ap.parse_args()
    # SIGTERM (a kill, a timeout) unwinds like Ctrl-C, so every process started is stopped
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    burners: list[subprocess.Popen] = []
    if args.burn:
        burners = [subprocess.Popen([sys.executable, "-c", BURN], start_new_session=True)
                   for _ in range(os.cpu_count() or 2)]
    try:
        print(f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}, burners {len(burners)}")
        rows = []
        for name in args.cases.split(","):
            x, y = CASES[name]
            results = []
            for i in range(args.runs):
                t0 = time.monotonic()
                res = one_run(x, y)
                results.append(res)
                print(f"  {name} {i + 1}/{args.runs}: {'ok ' if res['ok'] else 'BAD'} ids {res.get('ids')} "
                      f"pos {res.get('position_error_mm', float('nan')):.3f} mm "
                      f"force {res.get('force_error_pct', float('nan')):.2f} % {res['error']} "
                      f"({time.monotonic() - t0:.0f} s)", flush=True)
            pos = [r["position_error_mm"] for r in results if "position_error_mm" in r]
            frc = [r["force_error_pct"] for r in results if "force_error_pct" in r]
            rows.append([name, len(results), sum(r["ok"] for r in results),
                         f"{max(pos):.3f}" if pos else "-", f"{max(frc):.2f}" if frc else "-",
                         sum(1 for r in results if len(r.get("ids", [])) > 1),
                         sum(1 for r in results if not r.get("reported"))])
        table(f"demo --check, {'both cores busy' if burners else 'quiet machine'}",
              ["case", "runs", "passed", "worst pos mm", "worst force %", "runs >1 id", "runs no contact"], rows)
    finally:
        for p in burners:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


if __name__ == "__main__":
    main()
