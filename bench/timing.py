"""Timing helpers shared by the benchmark scripts (imported as ``timing`` when a
script in bench/ runs, since Python puts the script's folder first on sys.path)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable


def pin_to_one_core() -> None:
    """Run on one core, so figures read as "per core" and do not depend on idle siblings."""
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    except (AttributeError, OSError):
        pass


def best_rate(fn: Callable[[], object], n: int, repeats: int = 3) -> float:
    """Items per second of ``fn`` processing ``n`` items, best of ``repeats`` runs
    (the best run is the one least disturbed by the rest of the machine)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return n / best


def row(cells: list[object], widths: list[int]) -> str:
    """One table line: first column left-aligned, the others right-aligned."""
    return "  ".join(str(c).rjust(w) if i else str(c).ljust(w) for i, (c, w) in enumerate(zip(cells, widths)))


def table(title: str, head: list[str], rows: list[list[object]]) -> None:
    """Print a titled table with a dashed rule under the header."""
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    print(f"\n{title}")
    print(row(head, widths))
    print(row(["-" * w for w in widths], widths))
    for r in rows:
        print(row(r, widths))
