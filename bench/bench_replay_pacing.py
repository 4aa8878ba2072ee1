"""The replay links' own cost at recorded speed: each line pacing itself, or one pacer for all.

Prints a table; asserts nothing. Run (about a minute):

    .venv/bin/python bench/bench_replay_pacing.py [--seconds 10] [--repeat 2]

The humanoid's 22 gateway lines, idle and event-based (``bench_humanoid.generate`` with no
presses: 2 200 records a second), replayed on shifted time at recorded speed by
:class:`~cellbridge.daemon.shell.links.ReplayLink` into a callback that does nothing: what
is left is the replays' reading and pacing, the shell's part of each read that the
daemon's core does not see. Each line alone (a timer, a future and a task's wake per
record), or one :class:`~cellbridge.daemon.shell.links.ReplayPacer` for all (one wake per
group of records due within its window). The two alternate, ``--repeat`` times each; CPU
of this process (user + system) per wall second after the first second, per record, the
pacer's wakes a second, and the records fed more than ``ReplayLink.LATE`` after their due
time (a loaded machine).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import pickle
import sys
import tempfile
import time
from pathlib import Path

from timing import table

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout too
from cellbridge.daemon.core.config import LinkConfig  # noqa: E402
from cellbridge.daemon.shell.links import ReplayLink, ReplayPacer  # noqa: E402


def run(into: Path, gateways: list[int], seconds: float, paced: bool) -> list[object]:
    fed = [0]

    def on_data(name: str, data: bytes, now: float) -> None:
        fed[0] += 1

    async def main() -> list[object]:
        pacer = ReplayPacer() if paced else None
        links = [ReplayLink(LinkConfig(name=f"gw{g}", url=f"replay:{into / f'gw{g}.cbcap'}", replay_speed=1.0),
                            on_data, lambda *a: None, pacer=pacer) for g in gateways]
        tasks = [asyncio.create_task(ln.run()) for ln in links]
        await asyncio.sleep(1.0)
        c0, n0, t0, w0 = time.process_time(), fed[0], time.monotonic(), pacer.wakes if pacer else 0
        await asyncio.sleep(seconds)
        c1, n1, t1, w1 = time.process_time(), fed[0], time.monotonic(), pacer.wakes if pacer else 0
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        wall = t1 - t0
        return ["one pacer" if paced else "each line", f"{os.getloadavg()[0]:.1f}", f"{(n1 - n0) / wall:,.0f}",
                f"{(c1 - c0) / wall:.4f}", f"{(c1 - c0) / max(n1 - n0, 1) * 1e6:.1f}",
                f"{(w1 - w0) / wall:,.0f}" if pacer else "-", sum(ln.late for ln in links),
                f"{max(ln.late_max for ln in links) * 1e3:.1f}"]

    return asyncio.run(main())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="s measured per run (default 10)")
    ap.add_argument("--repeat", type=int, default=2, help="runs of each, alternating (default 2)")
    a = ap.parse_args()
    import bench_humanoid as bh

    skin = bh.load_skin(bh.HUMANOID)
    bh.presses = lambda *args: []  # an idle skin: the records' pacing, not the presses, is measured
    with tempfile.TemporaryDirectory(prefix="bench_replay_pacing.") as tmp:
        into = Path(tmp)
        gen = bh.generate(skin, "event:30", a.seconds + 3.0, into)
        (into / "gen.pkl").write_bytes(pickle.dumps(gen))
        rows = [run(into, gen["gateways"], a.seconds, paced) for _ in range(a.repeat) for paced in (False, True)]
    table(f"The humanoid's 22 replay links alone at recorded speed (idle, event:30; a callback that does nothing; "
          f"{a.seconds:.0f} s a run)",
          ["pacing", "load avg", "records/s", "CPU (cores)", "us a record", "wakes/s", "late records",
           "late max ms"], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
