"""Loading a mesh file and building its medium, by size: both must grow linearly.

Prints a table; asserts nothing. Run: ``.venv/bin/python bench/bench_mesh_load.py``.
Before issue 17 (point 19) both were quadratic (a linear search per id, per cell and
per link): 10 000 bridges took 8 s to load and 5.6 s more for the medium, and every
bridge process ``mesh up`` forked loaded the file again.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout too

from cellbridge.emulator.medium.medium import Medium
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import mesh_to_toml, parse_mesh

from timing import table


def main() -> None:
    rows = []
    for n in (30, 60, 100):
        text = mesh_to_toml(meshgen.grid(n, n))
        t0 = time.perf_counter()
        mesh = parse_mesh(text)
        t1 = time.perf_counter()
        Medium(mesh, 0)
        t2 = time.perf_counter()
        rows.append([f"{n}×{n}", n * n, f"{t1 - t0:.2f}", f"{1e6 * (t1 - t0) / (n * n):.0f}", f"{t2 - t1:.2f}",
                     f"{1e6 * (t2 - t1) / (n * n):.0f}"])
    table("Mesh file → Mesh → Medium (grid meshes; TOML parsing included)",
          ["grid", "bridges", "load s", "µs per bridge", "medium s", "µs per bridge"], rows)


if __name__ == "__main__":
    main()
