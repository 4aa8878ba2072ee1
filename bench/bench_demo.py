"""How often ``cellbridge demo --check`` tells the truth: seam and corner presses, N runs each.

Run: ``.venv/bin/python bench/bench_demo.py [--runs 20] [--burn [--burners 4] [--burners-apart]]
[--second-skin] [--cases seam,corner] [--keep-failed]``.
Each run starts the whole chain as a user would (an emulated 4×4 skin in real processes,
the daemon on its gateway's pty), presses, and checks the published contact: within 1 mm
and 5 % of the press, with exactly one contact id. ``--burn`` keeps every core busy with a
CPU-burning process per core (or ``--burners N``) for the whole measurement (the
loaded-robot case), all in one session as a shell starts them, or each in a session of
its own (``--burners-apart``): where the kernel shares the CPU between sessions first
(autogroups, the header says), the emulated skin, one session of 17 processes, then gets
a sixth of two cores beside four burners, less than it needs to hold real time; ``--second-skin`` runs a second emulated 4×4 (``mesh up``, its own
ports) on the same cores the whole time. Prints a
table per case: runs, passed, the worst position and force errors, the runs with more
than one id, and over every report of every run those that stated a position off by more
than 1 mm and 3 σ without listing an unknown element (``untrue`` positions), and the
steady reports (the press's second half) that stated a force off by more than 5 % and 3 σ
without (``untrue`` forces): a run with one fails. The burners are stopped on exit, also on Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from daemon_harness import free_port
from timing import table
from unwind import unwind_on_signals

CLI = shutil.which("cellbridge", path=str(Path(sys.executable).parent)) or "cellbridge"
CASES = {"seam": (0.057, 0.040), "corner": (0.0585, 0.0625)}
BURN = "while True: pass"
#: ``n`` burners in one process group and session: the first forks the others
BURN_TOGETHER = "import os, sys\nfor _ in range(int(sys.argv[1]) - 1):\n    if os.fork() == 0:\n        break\nwhile True: pass"


def autogroups() -> str:
    """Whether the kernel shares the CPU between sessions first (``sched_autogroup``): then
    each session's processes together get one session's share, whatever their number."""
    try:
        return "on" if Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() == "1" else "off"
    except OSError:
        return "unknown"


def start_burners(n: int, apart: bool) -> list[subprocess.Popen]:
    """``n`` CPU-burning processes: in one session (as a shell or a build starts them), or
    each in a session of its own (``apart``). With the kernel's autogroups on, the emulated
    skin (one session: ``mesh up`` and its 17 processes) gets one session's share of the
    cores beside them: a half with the burners together, a sixth with four apart."""
    if apart:
        return [subprocess.Popen([sys.executable, "-c", BURN], start_new_session=True) for _ in range(n)]
    return [subprocess.Popen([sys.executable, "-c", BURN_TOGETHER, str(n)], start_new_session=True)]


def children(pid: int) -> list[tuple[int, str]]:
    """(pid, command line) of ``pid``'s children, read from /proc."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            if ppid == pid:
                out.append((int(d.name), (d / "cmdline").read_bytes().replace(b"\0", b" ").decode()))
        except (OSError, ValueError, IndexError):
            continue
    return out


def stop_daemon_mid_press(demo: subprocess.Popen, pause: float, log: list[str]) -> None:
    """SIGSTOP the demo's daemon 1 s into the press for ``pause`` s, then SIGCONT: it
    reads its backlog. Its pid and the press are found among the demo's children."""
    daemon = None
    while demo.poll() is None:
        kids = children(demo.pid)
        daemon = daemon or next((p for p, cmd in kids if " daemon " in cmd), None)
        if daemon and any(" press " in cmd for _, cmd in kids):
            time.sleep(1.0)
            try:
                os.kill(daemon, signal.SIGSTOP)
                time.sleep(pause)
            finally:
                os.kill(daemon, signal.SIGCONT)
            log.append(f"daemon {daemon} stopped {pause:.1f} s")
            return
        time.sleep(0.05)


def one_run(x: float, y: float, pause: float = 0.0, defaults: bool = False, keep_failed: bool = False) -> dict:
    """One ``demo --check --json`` run: its JSON result, plus ``ok`` and ``error`` keys;
    with ``pause``, its daemon is stopped that long mid-press; ``defaults``: the skin and
    the daemon with their own defaults (``demo --defaults``); ``keep_failed``: a failed
    run's working folder (logs, the bridges' counters) is kept, its path the result's
    ``kept``, and a passed run's removed."""
    demo = subprocess.Popen([CLI, "demo", "--check", "--json", "--x", str(x), "--y", str(y),
                             *(["--defaults"] if defaults else []), *(["--keep"] if keep_failed else [])],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    log: list[str] = []
    watcher = threading.Thread(target=stop_daemon_mid_press, args=(demo, pause, log), daemon=True)
    if pause:
        watcher.start()
    try:
        out, err = demo.communicate(timeout=280)
    except subprocess.TimeoutExpired:
        stop(demo)
        return {"ok": False, "error": "timeout"}
    except BaseException:  # Ctrl-C, SIGTERM: the run in flight goes too
        stop(demo)
        raise
    finally:
        if pause:
            watcher.join(5.0)
    if pause and not log:
        return {"ok": False, "error": "the daemon was not stopped (press not seen)"}
    r = subprocess.CompletedProcess(demo.args, demo.returncode, out, err)
    try:
        res = json.loads(r.stdout)
    except json.JSONDecodeError:
        return {"ok": False, "error": (r.stderr.strip().splitlines() or ["no output"])[-1]}
    got = res.get("reported") or {}
    ok = (r.returncode == 0 and bool(got) and abs(got["x"] - x) <= 1e-3 and abs(got["y"] - y) <= 1e-3
          and abs(got["force"] - 3.0) <= 0.15 and len(res.get("ids", [])) == 1 and res.get("untrue", 0) == 0
          and res.get("untrue_force", 0) == 0)
    res.update(ok=ok, error="" if ok else f"rc {r.returncode}")
    if ok and res.get("kept"):
        shutil.rmtree(res.pop("kept"), ignore_errors=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20, help="runs per case (default 20)")
    ap.add_argument("--burn", action="store_true", help="keep every core busy while measuring")
    ap.add_argument("--burners", type=int, default=0,
                    help="with --burn: this many burning processes (default one per core)")
    ap.add_argument("--burners-apart", action="store_true",
                    help="with --burn: each burner in a session of its own (default: all in one session, as a "
                         "shell starts them); with the kernel's autogroups on, the skin then gets a smaller share")
    ap.add_argument("--second-skin", action="store_true",
                    help="run a second emulated 4x4 skin (mesh up) beside the demo's")
    ap.add_argument("--stop-daemon", type=float, default=0.0, metavar="SECONDS",
                    help="stop the daemon (SIGSTOP) this long 1 s into each press, then let it read its backlog")
    ap.add_argument("--defaults", action="store_true",
                    help="the skin and the daemon with their own defaults (periodic 100 Hz; demo --defaults)")
    ap.add_argument("--cases", default="seam,corner", help="comma-separated: seam, corner")
    ap.add_argument("--keep-failed", action="store_true",
                    help="keep each failed run's working folder (the daemon's log, the bridges' counters in "
                         "mesh.log) and print its path")
    args = ap.parse_args()
    unwind_on_signals()
    burners: list[subprocess.Popen] = []
    n_burn = (args.burners or os.cpu_count() or 2) if args.burn else 0
    if n_burn:
        burners = start_burners(n_burn, args.burners_apart)
    work = Path(tempfile.mkdtemp(prefix="bench-demo-"))
    try:
        if args.second_skin:
            burners.append(second_skin(work))
        arrangement = ("each in a session of its own" if args.burners_apart else "in one session") if n_burn else ""
        print(f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}, burners {n_burn}{' ' if n_burn else ''}{arrangement}"
              f"{', a second skin' if args.second_skin else ''}; the kernel's autogroups {autogroups()}")
        rows = []
        for name in args.cases.split(","):
            x, y = CASES[name]
            results = []
            for i in range(args.runs):
                t0 = time.monotonic()
                res = one_run(x, y, args.stop_daemon, args.defaults, args.keep_failed)
                results.append(res)
                print(f"  {name} {i + 1}/{args.runs}: {'ok ' if res['ok'] else 'BAD'} ids {res.get('ids')} "
                      f"pos {res.get('position_error_mm', float('nan')):.3f} mm "
                      f"force {res.get('force_error_pct', float('nan')):.2f} % {res['error']} "
                      f"({time.monotonic() - t0:.0f} s)", flush=True)
                if not res["ok"]:  # what the skin did not deliver meanwhile, and what the daemon knew
                    print(f"      unknown elements (contact messages listing each): {res.get('unknown_elements')}; "
                          f"skin frames: {res.get('skin_frames')}; reports {res.get('reports')}, with unknown "
                          f"near {res.get('with_unknown')}; known-only median: {res.get('known')}"
                          + (f"; kept in {res['kept']}" if res.get("kept") else ""), flush=True)
            pos = [r["position_error_mm"] for r in results if "position_error_mm" in r]
            frc = [r["force_error_pct"] for r in results if "force_error_pct" in r]
            rows.append([name, len(results), sum(r["ok"] for r in results),
                         f"{max(pos):.3f}" if pos else "-", f"{max(frc):.2f}" if frc else "-",
                         sum(1 for r in results if len(r.get("ids", [])) > 1),
                         sum(1 for r in results if not r.get("reported")),
                         sum(r.get("untrue", 0) for r in results), sum(r.get("untrue_force", 0) for r in results),
                         sum(r.get("with_unknown", 0) for r in results),
                         sum(r.get("reports", 0) for r in results)])
        load = (f"{n_burn} burners {arrangement}" if n_burn else "no burners") + (
            ", a second 4x4 skin" if args.second_skin else "") + (
            f", daemon stopped {args.stop_daemon:g} s mid-press" if args.stop_daemon else "") + (
            ", skin and daemon defaults" if args.defaults else "")
        table(f"demo --check, {load}",
              ["case", "runs", "passed", "worst pos mm", "worst force %", "runs >1 id", "runs no contact",
               "untrue positions", "untrue forces", "reports w/ unknown", "reports"], rows)
    finally:
        # A second signal (``timeout`` passes its SIGTERM on; a second Ctrl-C) must not cut
        # the clean-up short and leave burners or a skin running.
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, signal.SIG_IGN)
        for p in burners:
            stop(p)
        shutil.rmtree(work, ignore_errors=True)


def second_skin(work: Path) -> subprocess.Popen:
    """A second emulated 4×4 skin in real processes (its own ports), pressed by nobody."""
    mesh = work / "second.toml"
    subprocess.run([CLI, "mesh", "gen", "grid", "4", "4", "-o", str(mesh)], check=True, capture_output=True)
    port = free_port(3)  # a free base port: the medium takes it, the world the next two
    return subprocess.Popen([CLI, "mesh", "up", str(mesh), "--base-port", str(port)], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def stop(p: subprocess.Popen) -> None:
    """SIGTERM the process group (mesh up stops its bridges), SIGKILL after 10 s."""
    for sig, wait in ((signal.SIGTERM, 10.0), (signal.SIGKILL, None)):
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            break
        try:
            p.wait(wait)
            break
        except subprocess.TimeoutExpired:
            continue
    try:
        os.killpg(p.pid, signal.SIGKILL)  # whatever of the group is left
    except ProcessLookupError:
        pass


if __name__ == "__main__":
    main()
