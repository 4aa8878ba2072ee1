"""How much of each humanoid skin frame changes: what work that follows changes could skip.

Prints a table; asserts nothing. Run (about a minute a reporting mode):

    .venv/bin/python bench/bench_frame_changes.py [--seconds 12] [--reporting event:30,periodic]

The recording of ``bench_humanoid`` (rounds of 10 simultaneous presses) goes through the
daemon's pipeline as ``bench_humanoid.core_capacity`` feeds it; every frame's contact job
is compared with the one before. Per frame (mean, and the share of frames where it holds):

* elements sampled (a new reading in the frame: its sample time is the frame's);
* elements whose ΔC differs from the frame before (bit for bit), and whose baseline moved:
  the calibrator's tracker steps every element at every step, so an unchanged reading
  still has a new ΔC;
* touched elements, and those of them whose ΔC changed;
* frames whose whole estimate input (ΔC, touched, unknown) equals the frame before's: an
  estimate that could be reused as it is.
"""

from __future__ import annotations

import argparse
import heapq
import sys
import tempfile
from pathlib import Path

import numpy as np

from timing import table

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))


def changes(skin, gen: dict, into: Path) -> dict[str, list[float]]:
    """Per contact job of the recording: the figures of the module."""
    from cellbridge.daemon.core.config import parse_config
    from cellbridge.daemon.core.pipeline import Pipeline
    from cellbridge.daemon.shell.replay_source import read_records

    import bench_humanoid as bh

    links = [{"name": f"gw{g}", "url": "/dev/null"} for g in gen["gateways"]]
    p = Pipeline(parse_config({"link": links}), skin.layout())
    p.surface = skin
    p.want({"contact", "health"})
    bh.warm_calibration()
    streams = [((t, g, d) for t, d in read_records(into / f"gw{g}.cbcap", "x")) for g in gen["gateways"]]
    out: dict[str, list[float]] = {k: [] for k in ("sampled", "dc", "baseline", "touched", "touched_dc", "equal")}
    prev = None
    for t, g, data in heapq.merge(*streams):
        p.feed(f"gw{g}", data, t)
        job = p.contact_job(t)
        if job is None:
            continue
        s = job.snapshot
        stage = p.skin.elements  # (inspected, as a tool may: set once the layout is)
        assert stage is not None
        base = stage.calibrator.baseline.copy()
        unknown = np.zeros(s.dc.shape[0], dtype=bool) if s.unknown is None else s.unknown
        if prev is not None:
            pdc, ptouched, punknown, pbase = prev
            same = (s.dc == pdc) | (np.isnan(s.dc) & np.isnan(pdc))
            moved = ~((base == pbase) | (np.isnan(base) & np.isnan(pbase))).all(axis=1)
            dc_changed = ~same.all(axis=1)
            out["sampled"].append(float(np.count_nonzero(s.t_sample == s.t_frame)))
            out["dc"].append(float(np.count_nonzero(dc_changed)))
            out["baseline"].append(float(np.count_nonzero(moved)))
            out["touched"].append(float(np.count_nonzero(s.touched)))
            out["touched_dc"].append(float(np.count_nonzero(dc_changed & s.touched)))
            out["equal"].append(float(not dc_changed.any() and np.array_equal(s.touched, ptouched)
                                      and np.array_equal(unknown, punknown)))
        prev = (s.dc.copy(), s.touched.copy(), unknown.copy(), base)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=12.0, help="length of the recording (default 12)")
    ap.add_argument("--reporting", default="event:30,periodic", help="event:30, periodic, or both comma-separated")
    a = ap.parse_args()
    import bench_humanoid as bh

    skin = bh.load_skin(bh.HUMANOID)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_frame_changes.") as tmp:
        for reporting in a.reporting.split(","):
            into = Path(tmp) / reporting.replace(":", "")
            into.mkdir()
            gen = bh.generate(skin, reporting, a.seconds, into)
            c = changes(skin, gen, into)
            n = len(c["equal"])
            rows.append([reporting, skin.layout().n, n, *(f"{np.mean(c[k]):.1f}" for k in
                                                          ("sampled", "dc", "baseline", "touched", "touched_dc")),
                         f"{int(sum(c['equal']))} ({100.0 * sum(c['equal']) / max(n, 1):.0f} %)"])
    table(f"What changes from one humanoid skin frame to the next ({a.seconds:g} s recording; per frame, mean)",
          ["reporting", "elements", "frames", "sampled", "ΔC changed", "baseline moved", "touched",
           "touched, ΔC changed", "frames equal to the one before"], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
