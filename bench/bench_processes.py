"""How many bridge processes this machine holds in real time (100 Hz, < 1 % late gates).

Run: ``.venv/bin/python bench/bench_processes.py [--max 64] [--seconds 8]``.
For growing square meshes it runs ``cellbridge mesh up`` (medium, world, one process
per bridge), waits until every bridge is up, marks that moment (SIGUSR1), lets the
skin run, stops it with SIGTERM and adds up the bridges' ``late_gates_since_mark``:
samples computed more than one gate (2 ms) after they were due; "a period late" are
those more than a whole sampling period late (the process fell behind). Target: 64
bridges with < 1 % late gates. The figure depends on what else the machine is doing.
It stops at the first size that misses the target unless --all is given.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cellbridge.emulator import meshgen
from cellbridge.emulator.mesh import mesh_to_toml

TARGET = 0.01


def free_base_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return min(s.getsockname()[1], 60000)


def bridge_pids(mesh_path: str) -> list[int]:
    out = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if mesh_path.encode() in cmd and b"bridge" in cmd:
                out.append(int(pid))
    return out


def catches_usr1(pid: int) -> bool:
    """Whether the process has installed its SIGUSR1 handler (else the signal would kill it)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return bool(int(line.split()[1], 16) & (1 << (signal.SIGUSR1 - 1)))
    except OSError:
        pass
    return False


def run_one(n_side: int, seconds: float, tmp: str) -> tuple[int, int, int, float, float]:
    mesh = meshgen.grid(n_side, n_side)
    path = os.path.join(tmp, f"grid{n_side}.toml")
    Path(path).write_text(mesh_to_toml(mesh))
    err = open(os.path.join(tmp, f"grid{n_side}.err"), "a+")
    p = subprocess.Popen([sys.executable, "-m", "cellbridge", "mesh", "up", path, "--base-port",
                          str(free_base_port())], stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
    n = n_side * n_side
    try:
        deadline = time.monotonic() + 60 + 2 * n
        while time.monotonic() < deadline:
            pids = bridge_pids(path)
            if len(pids) == n and all(catches_usr1(q) for q in pids):
                break
            time.sleep(0.5)
        time.sleep(2.0)  # the last ones finish booting
        for pid in bridge_pids(path):
            os.kill(pid, signal.SIGUSR1)
        time.sleep(seconds)
    finally:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    err.seek(0)
    late = behind = samples = reported = 0
    for line in err:
        if line.startswith("{"):
            c = json.loads(line)["counters"]
            late += c.get("late_gates_since_mark", 0)
            behind += c.get("behind_gates_since_mark", 0)
            samples += c.get("samples_since_mark", 0)
            reported += "samples_since_mark" in c
    if not samples:
        return n, reported, 0, 1.0, 1.0
    return n, reported, samples, late / samples, behind / samples


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max", type=int, default=64, help="largest number of bridges to try (default 64)")
    ap.add_argument("--seconds", type=float, default=8.0, help="measured seconds per size (default 8)")
    ap.add_argument("--all", action="store_true", help="try every size even after one misses the target")
    args = ap.parse_args()
    print(f"real-time bridge processes at 100 Hz on {os.cpu_count()} cores "
          f"(load average {os.getloadavg()[0]:.1f} before start)")
    print(f"{'bridges':>7} {'measured':>8} {'samples':>8} {'late gates':>10} {'a period late':>13} "
          f"{'target':>7} {'ok':>4}")
    best = 0
    with tempfile.TemporaryDirectory() as tmp:
        for side in (2, 4, 6, 8):
            if side * side > args.max:
                break
            n, reported, samples, late, behind = run_one(side, args.seconds, tmp)
            good = late < TARGET and reported == n
            print(f"{n:>7} {reported:>8} {samples:>8} {late:>10.2%} {behind:>13.2%} {'<1%':>7} "
                  f"{'yes' if good else 'NO':>4}", flush=True)
            if not good and not args.all:
                break
            if good:
                best = max(best, n)
    print(f"held in real time with < 1 % late gates: {best} bridges (target 64)")


if __name__ == "__main__":
    main()
