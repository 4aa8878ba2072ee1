"""How many bridge processes this machine holds in real time (100 Hz, < 1 % late gates).

Run: ``.venv/bin/python bench/bench_processes.py [--reporting both] [--max 64] [--seconds 8]``.
For growing square meshes (4, 16, 36, 64 bridges) it runs ``cellbridge mesh up``
(medium, world, one process per bridge), waits until every bridge is up and 5 s more
(routes settle), opens a window (SIGUSR1), lets the skin run, closes the window (a
second SIGUSR1, so that stopping every process at once is not measured), stops it with
SIGTERM and adds up the bridges' ``late_gates_since_mark``: samples computed at a wake
that came more than one gate (2 ms) after the firmware asked for it; "a period late" are those more than a whole sampling period late (the process
fell behind). Target: 64 bridges with < 1 % late gates. It prints one table per
reporting mode: periodic (every sample sent: at 64 bridges more than one gateway's
1 Mbit/s link carries) and event-based (``--reporting event:40``, as a large skin runs:
idle elements send a heartbeat a second). The CPU columns are the share of one core
the average bridge process (and the least and most of them) and the medium used while
measured, and "skin CPU" all of them together (target for a periodic 4x4: <= 50 % of a core). The figures depend on
what else the machine is doing: the load average is printed before each size. A
mode stops at its first size that misses the target unless --all is given.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import mesh_to_toml

from realskin import free_base_port

TARGET = 0.01


def pids_of(mesh_path: str, role: bytes) -> list[int]:
    """Processes of this mesh (its file on their command line) in one role (b"bridge", b"medium")."""
    out = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:  # a bridge forked by `mesh up` has its command as one title: split on spaces too
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").split()
            except OSError:
                continue
            if mesh_path.encode() in cmd and role in cmd:
                out.append(int(pid))
    return out


def bridge_pids(mesh_path: str) -> list[int]:
    return pids_of(mesh_path, b"bridge")


def catches_usr1(pid: int) -> bool:
    """Whether the process has installed its SIGUSR1 handler (else the signal would kill it)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return bool(int(line.split()[1], 16) & (1 << (signal.SIGUSR1 - 1)))
    except OSError:
        pass
    return False


def medium_pid(mesh_path: str) -> int | None:
    found = pids_of(mesh_path, b"medium")
    return found[0] if found else None


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (0 when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@dataclass
class Result:
    bridges: int
    measured: int = 0
    samples: int = 0
    late: float = 1.0
    behind: float = 1.0
    bridge_cpu: float = 0.0  #: mean share of one core per bridge process
    bridge_cpu_min: float = 0.0
    bridge_cpu_max: float = 0.0
    medium_cpu: float = 0.0
    load: float = 0.0


def run_one(n_side: int, seconds: float, tmp: str, reporting: str) -> Result:
    mesh = meshgen.grid(n_side, n_side)
    path = os.path.join(tmp, f"grid{n_side}-{reporting.replace(':', '_')}.toml")
    Path(path).write_text(mesh_to_toml(mesh))
    err = open(path + ".err", "a+")
    n = n_side * n_side
    res = Result(n, load=os.getloadavg()[0])
    p = subprocess.Popen([sys.executable, "-m", "cellbridge", "mesh", "up", path, "--base-port",
                          str(free_base_port()), "--reporting", reporting],
                         stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
    try:
        deadline = time.monotonic() + 60 + 2 * n
        while time.monotonic() < deadline:
            pids = bridge_pids(path)
            if len(pids) == n and all(catches_usr1(q) for q in pids):
                break
            time.sleep(0.5)
        time.sleep(5.0)  # the last ones boot and find their routes
        pids = bridge_pids(path)
        med = medium_pid(path)
        t0 = time.monotonic()
        cpu0 = {q: cpu_seconds(q) for q in pids}
        med0 = cpu_seconds(med) if med else 0.0
        for pid in pids:
            os.kill(pid, signal.SIGUSR1)
        time.sleep(seconds)
        for pid in pids:  # closes the window: stopping 64 processes at once is not measured
            os.kill(pid, signal.SIGUSR1)
        dt = time.monotonic() - t0
        if pids:
            shares = [(cpu_seconds(q) - cpu0[q]) / dt for q in pids]
            res.bridge_cpu = sum(shares) / len(shares)
            res.bridge_cpu_min, res.bridge_cpu_max = min(shares), max(shares)
        if med:
            res.medium_cpu = (cpu_seconds(med) - med0) / dt
        time.sleep(0.3)  # every bridge takes the closing mark at its next wake
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
    res.measured, res.samples = reported, samples
    if samples:
        res.late, res.behind = late / samples, behind / samples
    return res


def bench_mode(reporting: str, args: argparse.Namespace, tmp: str) -> None:
    print(f"\nreporting {reporting}")
    print(f"{'bridges':>7} {'load':>5} {'measured':>8} {'samples':>8} {'late gates':>10} {'a period late':>13} "
          f"{'CPU/bridge':>10} {'min-max':>11} {'CPU medium':>10} {'skin CPU':>8} {'ok':>4}")
    best = 0
    for side in (2, 4, 6, 8):
        if side * side > args.max or side * side < args.min:
            continue
        r = run_one(side, args.seconds, tmp, reporting)
        good = r.late < TARGET and r.measured == r.bridges
        print(f"{r.bridges:>7} {r.load:>5.1f} {r.measured:>8} {r.samples:>8} {r.late:>10.2%} {r.behind:>13.2%} "
              f"{r.bridge_cpu:>10.1%} {f'{r.bridge_cpu_min:.1%}-{r.bridge_cpu_max:.1%}':>11} {r.medium_cpu:>10.1%} "
              f"{r.bridge_cpu * r.bridges + r.medium_cpu:>8.0%} {'yes' if good else 'NO':>4}", flush=True)
        if good:
            best = max(best, r.bridges)
        elif not args.all:
            break
    print(f"held in real time with < 1 % late gates ({reporting}): {best} bridges (target 64)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reporting", default="both",
                    help="'periodic', an event mode such as 'event:40' (as 'mesh up --reporting'), "
                         "or 'both' (periodic, then event:40; default)")
    ap.add_argument("--min", type=int, default=1, help="smallest number of bridges to try (default 1: from 4)")
    ap.add_argument("--max", type=int, default=64, help="largest number of bridges to try (default 64)")
    ap.add_argument("--seconds", type=float, default=8.0, help="measured seconds per size (default 8)")
    ap.add_argument("--all", action="store_true", help="try every size even after one misses the target")
    args = ap.parse_args()
    modes = ["periodic", "event:40"] if args.reporting == "both" else [args.reporting]
    print(f"real-time bridge processes at 100 Hz on {os.cpu_count()} cores "
          f"(load average {os.getloadavg()[0]:.1f} before start; target < {TARGET:.0%} late gates)")
    with tempfile.TemporaryDirectory() as tmp:
        for mode in modes:
            bench_mode(mode, args, tmp)


if __name__ == "__main__":
    main()
