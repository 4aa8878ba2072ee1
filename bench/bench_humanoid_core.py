"""The daemon's core on the humanoid skin, this checkout against another revision, in one run.

Prints a table; asserts nothing. Run (a few minutes on a loaded machine):

    .venv/bin/python bench/bench_humanoid_core.py [--against main] [--seconds 12] [--repeat 3]

One recording of the humanoid's traffic (``bench_humanoid.generate``: rounds of 10
simultaneous presses, event-based at 30 counts and/or periodic) goes through
``bench_humanoid.core_capacity`` (the pipeline fed every read in order of arrival, a
contact estimate per frame, inline) once with this checkout's ``cellbridge`` and once with
``--against``'s (``git archive`` of that revision, put first on the import path of a
child process). Each side runs once to warm up (compiled kernels cached, every path
taken), then ``--repeat`` times, the two sides alternating (a load that comes and goes on
a shared machine falls on both); CPU of the measuring thread per recorded second (what
real speed needs of a core, whatever else the machine runs), best and median.
``--topics contact,health`` builds only the messages of the daemon's subscriber in
``bench_humanoid`` (no ``raw`` or ``element`` messages, no per-element inverse for them).
The frames' counts, the estimates run and a hash of every output (each message the pipeline
returned, packed as the publisher packs it, and the last health) are printed for both sides: a
line under the table says when they differ (a change that should keep every output does not).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import pickle
import signal
import statistics
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

from timing import table

ROOT = Path(__file__).resolve().parents[1]


def child(into: Path, reporting: str, topics: tuple[str, ...] | None) -> None:
    """In the child: warm up, then one run per line read from stdin, one JSON line each."""
    src = os.environ.get("BENCH_CELLBRIDGE_SRC")
    if src:  # imported first: bench_humanoid puts this checkout's root first on the path
        sys.path.insert(0, src)
    import cellbridge

    sys.path.insert(0, str(ROOT / "bench"))
    import bench_humanoid as bh

    skin = bh.load_skin(bh.HUMANOID)
    gen = pickle.loads((into / "gen.pkl").read_bytes())
    bh.core_capacity(skin, gen, into, reporting, topics)
    print(json.dumps({"package": str(Path(cellbridge.__file__).parent)}), flush=True)
    for _ in sys.stdin:
        print(json.dumps(bh.core_capacity(skin, gen, into, reporting, topics)), flush=True)


class Side:
    """A child process running one revision's core on the recording, a run per request."""

    def __init__(self, src: Path | None, into: Path, reporting: str, topics: str) -> None:
        env = dict(os.environ)
        env.pop("BENCH_CELLBRIDGE_SRC", None)
        if src is not None:  # the other revision's package, ahead of this checkout's editable install
            env["BENCH_CELLBRIDGE_SRC"] = str(src)
        self.proc = subprocess.Popen([sys.executable, __file__, "--child", str(into), reporting, topics], env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                     start_new_session=True)
        self.src = src

    def ready(self) -> None:
        got = json.loads(self._line())
        want = (self.src / "cellbridge") if self.src is not None else ROOT / "cellbridge"
        if Path(got["package"]).resolve() != want.resolve():
            raise SystemExit(f"the child ran the package at {got['package']}, not {want}")

    def run(self) -> list:
        assert self.proc.stdin is not None
        self.proc.stdin.write("run\n")
        self.proc.stdin.flush()
        return json.loads(self._line())

    def _line(self) -> str:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise SystemExit(f"the child stopped (exit {self.proc.wait()})")
        return line

    def close(self) -> None:
        """Stop the child (its stdin closed ends its loop; a child stuck in a run is killed)."""
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGTERM)
            self.proc.wait(timeout=30)


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(Path(sys.argv[2]), sys.argv[3], None if sys.argv[4] == "all" else tuple(sys.argv[4].split(",")))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--against", default="main", help="git revision to compare with (default main)")
    ap.add_argument("--seconds", type=float, default=12.0, help="length of the recording (default 12)")
    ap.add_argument("--repeat", type=int, default=3, help="measured runs per side after the warm-up (default 3)")
    ap.add_argument("--reporting", default="event:30", help="event:30, periodic, or both comma-separated")
    ap.add_argument("--topics", default="all",
                    help="topics subscribed, comma-separated (the pipeline builds only their messages; 'contact,health' "
                         "is bench_humanoid's subscriber of the daemon), or 'all' (default: every message built)")
    a = ap.parse_args()
    sys.path.insert(0, str(ROOT / "bench"))
    import bench_humanoid as bh

    skin = bh.load_skin(bh.HUMANOID)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_humanoid_core.") as tmp:
        old = Path(tmp) / "old"
        src = Path(tmp) / "src"
        src.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", a.against], capture_output=True, check=True)
        with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tf:
            tf.extractall(src, filter="data")
        # the package as pyproject's package-dir maps it: cellbridge/, with protocol/, tactile/,
        # emulator/ and daemon/ of the checkout's root as its subpackages
        old.mkdir()
        (src / "cellbridge").rename(old / "cellbridge")
        for sub in ("protocol", "tactile", "emulator", "daemon"):
            (src / sub).rename(old / "cellbridge" / sub)
        for reporting in a.reporting.split(","):
            into = Path(tmp) / reporting.replace(":", "")
            into.mkdir()
            gen = bh.generate(skin, reporting, a.seconds, into)
            (into / "gen.pkl").write_bytes(pickle.dumps(gen))
            names = (a.against, "this checkout")
            sides = [Side(pkg, into, reporting, a.topics) for pkg in (old, None)]
            try:
                for sd in sides:
                    sd.ready()
                runs: list[list[list]] = [[], []]
                for _ in range(a.repeat):  # alternating: a load that comes and goes falls on both sides
                    for i, sd in enumerate(sides):
                        runs[i].append(sd.run())
            finally:
                for sd in sides:
                    sd.close()
            for name, r in zip(names, runs):
                ingest, est, total = ([float(x[i]) for x in r] for i in (1, 2, 3))
                rows.append([reporting, name, f"{min(ingest):.3f} / {statistics.median(ingest):.3f}",
                             f"{min(est):.3f} / {statistics.median(est):.3f}",
                             f"{min(total):.3f} / {statistics.median(total):.3f}", r[0][4], r[0][5], r[0][6],
                             r[0][7], r[0][8], r[0][9]])
    for k in range(0, len(rows), 2):
        if rows[k][5:] != rows[k + 1][5:]:
            print(f"NOTE: {rows[k][0]}: the two sides' estimates or frames differ: {rows[k][5:]} vs {rows[k + 1][5:]}")
    table(f"The daemon's core per second of the humanoid skin ({a.seconds:g} s recording, CPU s of one thread per "
          f"recorded s, best / median of {a.repeat}; topics: {a.topics}; target event-based together <= 0.25, periodic <= 1)",
          ["reporting", "code", "ingest", "estimates", "together", "estimates run", "frames complete",
           "by deadline", "missed", "late records", "outputs (sha256)"], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
