"""``cellbridge info`` and ``cellbridge replay`` on 1 000 mutated recordings: time, peak RSS, exit codes.

Run: ``.venv/bin/python bench/bench_recording_fuzz.py [--count N] [--exec] [--keep DIR]``.

The recordings (bench/recording_mutations.py) are mutations of recordings the recorder
makes (every topic, small chunks; zstd, lz4, uncompressed; finished and cut short):
truncated, bit flips, random runs of bytes, oversized declared lengths (records, chunk
sizes, compression names, data lengths), a chunk's zstd frame header overwritten,
decompression bombs (a 256 MB message in an 8 kB file, frames that expand to 1 GB,
frames claiming 4 GB, a million tiny JSON values, 200 000 messages in a few kB, chunks
at the size bounds), odd JSON payloads in well-formed files, and chunks duplicated,
dropped, swapped, the summary and the footer damaged.

Each file goes through ``cellbridge info FILE`` and ``cellbridge replay --fast FILE``,
each run in a process of its own: by default forked from a process that has imported
the command (as ``cellbridge`` would run it, without paying the imports 2 000 times),
with ``--exec`` the installed ``cellbridge`` executable itself. Per run: exit status,
wall time, peak RSS (``wait4``: the whole process, imports included), and whether it
ended as it must (exit 0, or 1 with one line naming the file; never a traceback).
Replay runs ``--fast``: paced replay waits as recorded, every pause bounded by
``--max-gap`` (tests/test_recording_robust.py).

The machine is shared: wall times grow with other load.
"""

from __future__ import annotations

import argparse
import collections
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import recording_mutations as rm
from timing import table


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=1000, help="mutated recordings (default 1000)")
    ap.add_argument("--exec", action="store_true", help="run the installed cellbridge executable per run (slow)")
    ap.add_argument("--keep", type=Path, help="write the recordings here and keep them (default: a temporary dir)")
    ap.add_argument("--timeout", type=float, default=60.0, help="s before a run is killed and counted as hung")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        t0 = time.monotonic()
        pid = os.fork()  # made in a child: the runs are forked from a process that never held a bomb
        if pid == 0:
            code = 1
            try:
                rm.corpus(work / "corpus", args.count)
                code = 0
            finally:
                os._exit(code)
        if os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]) != 0:
            print("making the recordings failed")
            return 1
        made = time.monotonic() - t0
        files = [(p, p.stem.split("-", 1)[1]) for p in sorted((work / "corpus").glob("m*.mcap"))]
        kinds = dict((str(p), k) for p, k in files)
        sizes = [p.stat().st_size for p, _ in files]
        print(f"{len(files)} recordings made in {made:.1f} s: {min(sizes)} to {max(sizes)} bytes, "
              f"median {sorted(sizes)[len(sizes) // 2]}")
        runs = []
        t0 = time.monotonic()
        for r in rm.run_all([p for p, _ in files], work / "run", exec_cli=args.exec, timeout=args.timeout):
            runs.append(r)
            if len(runs) % 200 == 0:
                print(f"  {len(runs)} runs, {time.monotonic() - t0:.0f} s", flush=True)
        load = open("/proc/loadavg").read().split()[:3] if Path("/proc/loadavg").exists() else ["?"]
    rows = []
    for kind in (*rm.KINDS, "all"):
        for tool in ("info", "replay"):
            rs = [r for r in runs if r.tool == tool and (kind == "all" or kinds[r.file] == kind)]
            if not rs:
                continue
            codes = collections.Counter(r.code for r in rs)
            wrong = [r for r in rs if rm.verdict(r)]
            slow = max(rs, key=lambda r: r.seconds)
            rows.append([kind, tool, len(rs), " ".join(f"{c}:{n}" for c, n in sorted(codes.items())),
                         f"{sorted(r.seconds for r in rs)[len(rs) // 2]:.2f}", f"{slow.seconds:.2f}",
                         f"{max(r.rss_mb for r in rs):.0f}", sum(1 for r in rs if r.seconds > 10),
                         sum(1 for r in rs if r.rss_mb >= 200), len(wrong)])
    table(f"info and replay --fast on {len(files)} mutated recordings "
          f"({'exec' if args.exec else 'forked'} runs; load average {' '.join(load)})",
          ["kind", "tool", "runs", "exit codes", "p50 s", "max s", "max RSS MB", "over 10 s", "over 200 MB",
           "wrong end"], rows)
    wrong = [r for r in runs if rm.verdict(r)]
    for r in wrong[:20]:
        print(f"WRONG {r.tool} {r.file}: {rm.verdict(r)}")
    slowest = sorted(runs, key=lambda r: -r.seconds)[:5]
    print("\nslowest runs: " + "; ".join(f"{Path(r.file).name} {r.tool} {r.seconds:.2f} s" for r in slowest))
    fattest = sorted(runs, key=lambda r: -r.rss_mb)[:5]
    print("largest RSS: " + "; ".join(f"{Path(r.file).name} {r.tool} {r.rss_mb:.0f} MB" for r in fattest))
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"(the process the runs were forked from: {own:.0f} MB peak RSS)")
    ok = not wrong and all(r.seconds <= 10 and r.rss_mb < 200 for r in runs)
    print("every run ended within 10 s, under 200 MB, with exit 0 or one line naming the file: "
          + ("yes" if ok else "NO"))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
