"""Throughput and accuracy of the element model's forward and inverse.

Run: .venv/bin/python bench/bench_inverse.py   (one core, about 10 s)

Throughput: arrays of 1e6 elements, best of several runs, numpy on one thread.
Accuracy: noise-free readings of the target grid, F 1-20 N × D 10-40 mm, inverted
with the default options and with exact data (noise = 0).
"""

from __future__ import annotations

import os

# One core: keep any threaded numpy backend to a single thread before importing it.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


import numpy as np  # noqa: E402
from cellbridge.tactile import DEFAULT_NOISE, forward, inverse, solve  # noqa: E402

from timing import best_rate, pin_to_one_core  # noqa: E402

N = 1_000_000
REPEATS = 5


def main() -> int:
    pin_to_one_core()
    rng = np.random.default_rng(1)
    f = rng.uniform(1.0, 20.0, N)
    d = rng.uniform(10e-3, 40e-3, N)
    s = np.pi * d * d / 4
    c1, c2 = forward(f, s)
    inverse(c1[:10], c2[:10])  # build the tables outside the timing

    rows = [
        ("forward (F, S) -> (dC1, dC2)", best_rate(lambda: forward(f, s), N, REPEATS)),
        ("inverse (dC1, dC2) -> (F, S, valid)", best_rate(lambda: inverse(c1, c2), N, REPEATS)),
        ("solve (inverse + error estimates)", best_rate(lambda: solve(c1, c2), N, REPEATS)),
    ]
    print(f"throughput, one core, arrays of {N:,} elements (best of {REPEATS})")
    print(f"  {'operation':<38} {'elements/s':>14}")
    for name, rate in rows:
        print(f"  {name:<38} {rate:>14,.0f}")
    print("  target: inverse >= 1,000,000 elements/s")
    print()

    F, D = np.meshgrid(np.linspace(1.0, 20.0, 191), np.linspace(10e-3, 40e-3, 301),
                       indexing="ij")
    g1, g2 = forward(F, np.pi * D * D / 4)
    print(f"accuracy, noise-free readings, grid F 1-20 N x D 10-40 mm ({F.size:,} points)")
    print(f"  {'inverse noise option':<22} {'valid':>7} {'max |dF|/F':>12} {'max |dD| mm':>12}"
          f" {'min valid F at D=10/20/30/40 mm':>34}")
    for label, noise in ((f"default ({DEFAULT_NOISE * 1e15:g} fF)", DEFAULT_NOISE),
                         ("exact data (0 fF)", 0.0), ("10 fF", 10e-15)):
        fe, se, ok = inverse(g1, g2, noise=noise)
        de = 2 * np.sqrt(se / np.pi)
        ef = float(np.max(np.abs(fe[ok] / F[ok] - 1))) if ok.any() else float("nan")
        ed = float(np.max(np.abs(de[ok] - D[ok]))) * 1e3 if ok.any() else float("nan")
        mins = []
        for dmm in (10, 20, 30, 40):
            j = int(np.argmin(np.abs(D[0] - dmm * 1e-3)))
            col = ok[:, j]
            mins.append(f"{F[np.argmax(col), j]:.1f}" if col.any() else "-")
        print(f"  {label:<22} {ok.mean():>7.1%} {ef:>12.2e} {ed:>12.2e} {' / '.join(mins) + ' N':>34}")
    print("  target: |dF|/F <= 1e-2 and |dD| <= 0.2 mm wherever valid")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
