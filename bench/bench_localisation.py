"""Contact localisation on the paper's own experiments (§III.B, Fig. 6; §II.B stimulators).

Prints tables; asserts nothing. Run: ``.venv/bin/python bench/bench_localisation.py``.

* Fig. 6 sweep: a D = 10 mm stimulator at 3 N moved along the centre line of two
  adjacent 40 mm elements (A centred at x = 0, B at x = 40 mm, seam at x = 20 mm).
  Error of the paper's force-weighted centroid and of the model-based fits, over the
  positions where the skin sees the straddle (both elements touched), noise-free and
  with the counter quantisation of one 2 ms gate per channel.
* Random straddling contacts anywhere on the 2×2 skin (seams and corners), random D
  and F: error along the axes the readings resolve, and whether the reported
  uncertainty covers the error on all axes.
* The six stimulators D = 10 … 40 mm pressed at an element's centre: force, diameter.
* Membrane-tension spread (s = 2 mm) on the Fig. 6 sweep: the spread-aware fit
  against the uniform-pressure fit and the centroid.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout too

from cellbridge.tactile.contacts import ContactEstimator
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.layout import grid_layout
from cellbridge.tactile.response import skin_response
from cellbridge.tactile.transfer import counter_delta, counts_per_farad

from timing import table

MM = 1e-3
P = ElementParams()
LAY = grid_layout(2, 2)
COUNTER_NOISE = (0.5 / float(counts_per_farad(P.C1_rest)), 0.5 / float(counts_per_farad(P.C2_rest)))


def quantised(dc1, dc2, rng):
    return [counter_delta(dc, rest, rng.uniform(0, 1, dc.shape)) for dc, rest in ((dc1, P.C1_rest), (dc2, P.C2_rest))]


def rms(a) -> float:
    a = np.asarray(a, dtype=float)
    return float(math.sqrt(np.mean(a * a))) if a.size else float("nan")


TIMES: list[float] = []


def run(est, dc1, dc2):
    t0 = time.perf_counter()
    cs = est.estimate(dc1, dc2)
    TIMES.append(time.perf_counter() - t0)
    return cs


def sweep(est, xs, y, f, d, rng=None, trials=1, spread=0.0):
    """Per position: (x error of model, of centroid, force rel. error, D error, straddle seen, σx)."""
    out: list[tuple[float, float, float, float, bool, float]] = []
    for x in xs:
        dc1, dc2 = skin_response(LAY, [x, y, f, d], spread=spread)
        for _ in range(trials):
            m1, m2 = (dc1, dc2) if rng is None else quantised(dc1, dc2, rng)
            cs = run(est, m1, m2)
            if len(cs) != 1:
                out.append((np.nan, np.nan, np.nan, np.nan, False, np.nan))
                continue
            c = cs[0]
            seen = c.elements == (0, 1)
            out.append((c.x - x, c.centroid_x - x, c.force / f - 1.0, c.diameter - d, seen, c.sigma_x))
    return out


def fig6():
    xs = np.arange(0.0, 0.0400001, 0.5 * MM)
    geo = np.abs(xs - 0.020) < 0.005
    cases = [
        ("model, ΔC fit", ContactEstimator(LAY), None, 1),
        ("model, area fit", ContactEstimator(LAY, method="area"), None, 1),
        ("model, ΔC fit", ContactEstimator(LAY, noise=COUNTER_NOISE), np.random.default_rng(1), 4),
        ("model, area fit", ContactEstimator(LAY, method="area", noise=COUNTER_NOISE), np.random.default_rng(1), 4),
    ]
    rows: list[list[object]] = []
    for name, est, rng, trials in cases:
        res = sweep(est, xs, 0.0, 3.0, 0.010, rng, trials)
        seen = np.array([r[4] for r in res])
        ex = np.array([r[0] for r in res])
        ec = np.array([r[1] for r in res])
        ef = np.array([r[2] for r in res])
        ed = np.array([r[3] for r in res])
        data = "noise-free" if rng is None else "2 ms counter"
        if not rows or rows[-1][1] != data:
            rows.append(["centroid (paper)", data, int(seen.sum()), f"{rms(ec[seen]) / MM:.2f}",
                         f"{np.nanmax(np.abs(ec[seen])) / MM:.2f}", "-", "-"])
        rows.append([name, data, int(seen.sum()), f"{rms(ex[seen]) / MM:.4f}", f"{np.nanmax(np.abs(ex[seen])) / MM:.4f}",
                     f"{100 * rms(ef[seen]):.3f}", f"{rms(ed[seen]) / MM:.4f}"])
    table(
        f"Fig. 6 sweep: D = 10 mm, F = 3 N, x = 0..40 mm step 0.5 mm on the centre line "
        f"(straddle seen: both elements touched; {int(geo.sum())} positions straddle geometrically)",
        ["estimate", "data", "n", "RMS x err mm", "max x err mm", "RMS F err %", "RMS D err mm"],
        rows,
    )


def random_straddles(n=150):
    rng = np.random.default_rng(5)
    rows: list[list[object]] = []
    for label, noise, q in (("noise-free", None, None), ("2 ms counter", COUNTER_NOISE, np.random.default_rng(2))):
        est = ContactEstimator(LAY) if noise is None else ContactEstimator(LAY, noise=noise)
        err_m, err_c, covered, n_seen, n_all, n_light = [], [], 0, 0, 0, 0
        while n_all < n:
            d = rng.uniform(0.010, 0.030)
            f = rng.uniform(2.0, 10.0)
            x, y = rng.uniform(0.020 - d / 2, 0.020 + d / 2, 2)  # over a seam or the corner
            if rng.uniform() < 0.5:  # half of them straddle only the vertical seam
                y = rng.uniform(-0.015 + d / 2, 0.015 - d / 2)
            dc1, dc2 = skin_response(LAY, [x, y, f, d])
            if q is not None:
                dc1, dc2 = quantised(dc1, dc2, q)
            cs = run(est, dc1, dc2)
            n_all += 1
            if len(cs) != 1 or not cs[0].fit_ok:
                continue
            c = cs[0]
            n_seen += 1
            n_light += not c.valid
            for ax, (t, e, _s) in enumerate(((x, c.x, c.sigma_x), (y, c.y, c.sigma_y))):
                # Resolved axes of contacts with a pressure; a light touch's position
                # is an interval (its σ is counted in the coverage column).
                if c.observable[ax] and c.valid:
                    err_m.append(e - t)
                    err_c.append((c.centroid_x, c.centroid_y)[ax] - t)
            covered += all(abs(e - t) <= 2 * s + 1e-9 for t, e, s in ((x, c.x, c.sigma_x), (y, c.y, c.sigma_y)))
        rows.append([label, n_all, n_seen, n_light, len(err_m), f"{rms(err_c) / MM:.2f}", f"{rms(err_m) / MM:.4f}",
                     f"{np.max(np.abs(err_m)) / MM:.4f}", f"{100 * covered / max(n_seen, 1):.1f}"])
    table(
        "Random straddling contacts on the 2×2 skin (D 10-30 mm, F 2-10 N; half across one seam, half near the corner)",
        ["data", "contacts", "fitted", "of them light", "resolved axes (valid)", "RMS err centroid mm",
         "RMS err model mm",
         "max err model mm", "within 2σ (all axes) %"],
        rows,
    )


def stimulators():
    rows: list[list[object]] = []
    est = ContactEstimator(LAY)
    estq = ContactEstimator(LAY, noise=COUNTER_NOISE)
    rng = np.random.default_rng(3)
    for d_mm in (10, 16, 20, 26, 30, 40):
        d = d_mm * MM
        for f in (3.0, 10.0):
            dc1, dc2 = skin_response(LAY, [0.0, 0.0, f, d])
            (c,) = run(est, dc1, dc2)
            qs = [run(estq, *quantised(dc1, dc2, rng))[0] for _ in range(10)]
            qf = [q.force / f - 1 for q in qs if q.valid]
            qd = [q.diameter - d for q in qs if q.valid]
            if c.valid:
                rows.append([d_mm, f"{f:.0f}", "yes", f"{100 * (c.force / f - 1):+.2e}", f"{(c.diameter - d) / MM:+.1e}",
                             f"{100 * rms(qf):.3f}", f"{rms(qd) / MM:.4f}",
                             f"({c.x / MM:.1f}, {c.y / MM:.1f}) ± {c.sigma_xy / MM:.1f}"])
            else:
                rows.append([d_mm, f"{f:.0f}", "no (ambiguous)", "-", "-", "-", "-",
                             f"({c.x / MM:.1f}, {c.y / MM:.1f}) ± {c.sigma_xy / MM:.1f}"])
    table(
        "Six stimulators pressed at the centre of element A (noise-free; quantised: 10 gates each)",
        ["D mm", "F N", "valid", "F err % (exact)", "D err mm (exact)", "RMS F err % (2 ms)", "RMS D err mm (2 ms)",
         "position mm ± σ"],
        rows,
    )


def spread_sweep(s=0.002):
    xs = np.arange(0.0155, 0.0246, 1.5 * MM)
    rows: list[list[object]] = []
    for name, est in (("model, spread-aware", ContactEstimator(LAY, spread=s)), ("model, uniform (s = 0)", ContactEstimator(LAY))):
        res = sweep(est, xs, 0.0, 3.0, 0.010, spread=s)
        ex = np.array([r[0] for r in res])
        ec = np.array([r[1] for r in res])
        ef = np.array([r[2] for r in res])
        ed = np.array([r[3] for r in res])
        if not rows:
            rows.append(["centroid (paper)", len(xs), f"{rms(ec) / MM:.2f}", "-", "-"])
        rows.append([name, len(xs), f"{rms(ex) / MM:.4f}", f"{100 * rms(ef):.2f}", f"{rms(ed) / MM:.3f}"])
    table(
        f"Tension spread s = {s / MM:.0f} mm in the readings, Fig. 6 straddle positions (noise-free)",
        ["estimate", "n", "RMS x err mm", "RMS F err %", "RMS D err mm"],
        rows,
    )


def main() -> None:
    t0 = time.perf_counter()
    print("cellbridge contact localisation bench — 2×2 skin, 40 mm elements at 40 mm pitch")
    print(f"counter quantisation: one 2 ms gate per channel, rms ≤ {COUNTER_NOISE[0] * 1e15:.2f} fF (C1), "
          f"{COUNTER_NOISE[1] * 1e15:.2f} fF (C2)")
    fig6()
    random_straddles()
    stimulators()
    n_fast = len(TIMES)
    fast = np.array(TIMES)
    spread_sweep()
    slow = np.array(TIMES[n_fast:])
    print(f"\nestimate() time per contact: uniform model median {1e3 * np.median(fast):.1f} ms "
          f"(p95 {1e3 * np.percentile(fast, 95):.1f} ms); spread model median {1e3 * np.median(slow):.0f} ms")
    print(f"total bench time {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
