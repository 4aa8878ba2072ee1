"""Light touches across seams: how often a resolved axis is a confident untruth, and the cost.

Prints a table; asserts nothing. Run: ``.venv/bin/python bench/bench_light_touch.py
[--n 200] [--against REV]``.

Random light touches (0.6-2.5 N on 14-24 mm pads: no element's inverse is valid) near
the seams and corners of two layouts of the robot's arm skin: the upper arm's two rings
(columns 41.9 mm apart, a 1.9 mm gap between them, the rings' seam without one) and the
forearm's wrap seam as its second chart sees it; readings with the daemon's noise
(0.4 fF rms) quantised to 0.78 fF, touch flags at 50 fF, as the emulated skin gives them.
Per estimator (this checkout's light touch and, with ``--against``, ``tactile/light_touch.py``
of another git revision in its place, on the same readings): resolved axes, how many are
off by more than 1 mm and 3 σ (the robot scorer's untruth), their error p50/p95,
unresolved axes and how many lie within 2 σ, and CPU per light-touch frame.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout too

from cellbridge.tactile import estimator as est_mod  # noqa: E402
from cellbridge.tactile.estimator import ContactEstimator  # noqa: E402
from cellbridge.tactile.layout import SkinLayout  # noqa: E402
from cellbridge.tactile.light_touch import locate_light  # noqa: E402
from cellbridge.tactile.response import skin_response  # noqa: E402

NOISE = 7e-16  # the daemon's default noise of one reading (the fit's weight)
READ_NOISE = 0.4e-15  # rms of the emulated skin's readings
STEP = 0.78e-15  # their resolution
TOUCH = 50e-15  # the calibrator's touch threshold


def layouts() -> list[tuple[str, SkinLayout]]:
    up = 2 * math.pi * 0.04 / 6
    fore = 2 * math.pi * 0.045 / 7
    return [
        ("upper arm", SkinLayout(np.array([[0.26094395 + up * i, y] for y in (0.02, 0.06) for i in range(4)]),
                                 side=0.040, neighbour_gap=0.01)),
        ("forearm", SkinLayout(np.array([[0.51073955 + fore * i, y] for y in (0.02, 0.06) for i in range(4)]),
                               side=0.040, neighbour_gap=0.01)),
    ]


def cases(n: int) -> list[tuple[SkinLayout, float, float, np.ndarray, np.ndarray]]:
    """(layout, x, y, ΔC1, ΔC2) of ``n`` light touches per layout, seeded."""
    rng = np.random.default_rng(7)
    out = []
    for _, lay in layouts():
        b = lay.bounds
        for _ in range(n):
            pad, force = rng.uniform(0.014, 0.024), rng.uniform(0.6, 2.5)
            x = (rng.uniform(b[1, 2] - 0.6 * pad, b[2, 0] + 0.6 * pad) if rng.random() < 0.7
                 else rng.uniform(b[1, 0], b[2, 2]))
            y = rng.uniform(0.04 - 0.6 * pad, 0.04 + 0.6 * pad) if rng.random() < 0.5 else rng.uniform(0.005, 0.035)
            d1, d2 = skin_response(lay, [(x, y, force, pad)])
            n1 = np.round((d1 + rng.normal(0, READ_NOISE, lay.n)) / STEP) * STEP
            n2 = np.round((d2 + rng.normal(0, READ_NOISE, lay.n)) / STEP) * STEP
            out.append((lay, x, y, n1, n2))
    return out


def run(locate: Callable, data: list) -> list[str]:
    est_mod.locate_light = locate  # the estimator's light touch, swapped for the run
    ests = {id(lay): ContactEstimator(lay, noise=NOISE) for lay, *_ in data}
    resolved, untrue, unres, covered, light = [], 0, 0, 0, 0
    cpu = 0.0
    for lay, x, y, n1, n2 in data:
        c0 = time.process_time()
        cs = ests[id(lay)].estimate(n1, n2, n1 > TOUCH)
        dt = time.process_time() - c0
        if len(cs) != 1 or cs[0].valid:
            continue
        c = cs[0]
        light += 1
        cpu += dt
        for ax, (v, t, s) in enumerate(((c.x, x, c.sigma_x), (c.y, y, c.sigma_y))):
            e = abs(v - t)
            if c.observable[ax]:
                resolved.append(e)
                untrue += int(e > 1e-3 and e > 3 * s)
            else:
                unres += 1
                covered += int(e <= 2 * s)
    r = np.array(resolved) * 1e3
    return [f"{light}", f"{r.size}", f"{untrue}", f"{np.percentile(r, 50):.2f}", f"{np.percentile(r, 95):.2f}",
            f"{unres}", f"{covered}", f"{1e3 * cpu / max(light, 1):.2f}"]


def at_revision(rev: str) -> Callable:
    """``locate_light`` of ``tactile/light_touch.py`` at git revision ``rev``."""
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:tactile/light_touch.py"],
                         check=True, capture_output=True, text=True).stdout
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as fh:
        fh.write(src)
    spec = importlib.util.spec_from_file_location(f"light_touch_{rev}", fh.name)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    Path(fh.name).unlink()
    return mod.locate_light  # the module's own function


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=200, help="touches per layout (default 200)")
    ap.add_argument("--against", metavar="REV", help="also run the light touch of git revision REV")
    a = ap.parse_args()
    data = cases(a.n)
    run(locate_light, data[:10])  # the kernels compiled and loaded before anything is timed
    rows = []
    if a.against:
        rows.append([a.against] + run(at_revision(a.against), data))
    rows.append(["this checkout"] + run(locate_light, data))
    head = ["light touch", "light", "resolved axes", "untrue (>1 mm, >3σ)", "err p50 mm", "err p95 mm",
            "unresolved axes", "within 2σ", "CPU ms/frame"]
    w = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    print(f"light touches near seams, {a.n} per layout, {READ_NOISE * 1e15:.1f} fF noise quantised to "
          f"{STEP * 1e15:.2f} fF")
    print("  ".join(h.rjust(w[i]) for i, h in enumerate(head)))
    for r in rows:
        print("  ".join(v.rjust(w[i]) for i, v in enumerate(r)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
