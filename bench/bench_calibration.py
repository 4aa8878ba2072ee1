"""Cost of loading a large skin layout and of one calibration step over many elements.

Run: .venv/bin/python bench/bench_calibration.py   (one core, about 10 s)

Layout: a 150 × 200 grid (30 000 elements) as an ``[[element]]`` TOML document —
parse, validate (no overlaps) and build both neighbour lists. Calibration: one
``Calibrator.update`` over N elements × 2 channels, with drift and a few touches.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import time  # noqa: E402

import numpy as np  # noqa: E402
from cellbridge.tactile import (  # noqa: E402
    CalibrationConfig,
    Calibrator,
    grid_layout,
    layout_to_toml,
    parse_layout,
)

from timing import best_rate, pin_to_one_core  # noqa: E402


def layout_rows() -> list[tuple[str, int, float, float, float]]:
    rows = []
    for r, c in ((40, 50), (100, 100), (150, 200)):
        text = layout_to_toml(grid_layout(r, c))
        t0 = time.perf_counter()
        lay = parse_layout(text, "bench")
        t1 = time.perf_counter()
        e, ce = lay.edges, lay.corner_edges
        t2 = time.perf_counter()
        assert len(e) == r * (c - 1) + c * (r - 1) and len(ce) > len(e)
        rows.append((f"{r}×{c}", lay.n, t1 - t0, t2 - t1, t2 - t0))
    return rows


def calibration_rows() -> list[tuple[int, float]]:
    rows = []
    rng = np.random.default_rng(3)
    for n in (16, 1_000, 10_000):
        cfg = CalibrationConfig(n_baseline=5)
        cal = Calibrator(n, 2, cfg)
        base = 20e-12 + rng.normal(0, 1e-15, (n, 2))
        for k in range(5):
            cal.update(0.01 * k, base)
        v = base.copy()
        v[: max(1, n // 100)] += 1e-12  # 1 % of the skin touched
        state = {"t": 0.05}

        def step(cal: Calibrator = cal, v: np.ndarray = v, state: dict[str, float] = state) -> None:
            for _ in range(200):
                state["t"] += 0.01
                cal.update(state["t"], v + 1e-16 * state["t"])

        rows.append((n, 1e6 / best_rate(step, 200)))
    return rows


def main() -> int:
    pin_to_one_core()
    print("Layout from TOML text (parse + validate, then both neighbour lists), one core")
    print(f"{'grid':>8}  {'elements':>8}  {'parse s':>8}  {'neighbours s':>12}  {'total s':>8}")
    for name, n, a, b, tot in layout_rows():
        print(f"{name:>8}  {n:>8}  {a:>8.3f}  {b:>12.3f}  {tot:>8.3f}")
    print()
    print("Calibrator.update, 2 channels, one step")
    print(f"{'elements':>8}  {'µs/step':>8}")
    for n, us in calibration_rows():
        print(f"{n:>8}  {us:>8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
