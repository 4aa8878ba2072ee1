"""The contact worker's warm-up loads every compiled kernel an estimate needs, in the one
signature the estimate calls it with: on a grid and on a robot's skin (wrap seams, links'
rows gathered), two disks in one cluster (split in two contacts) and the area method, no
kernel compiles again after it. A second signature costs 25 ms of
compiling mid-run, in the worker, on the estimate of a robot's first press: a latency spike
where the daemon should be fastest.

Run in a fresh interpreter: the test process's kernels already hold whatever signatures
earlier tests called them with."""

from __future__ import annotations

import subprocess
import sys

SCRIPT = r"""
import importlib, pkgutil
import numpy as np
from numba.core.registry import CPUDispatcher
import cellbridge.tactile as T
from cellbridge.daemon.core.contacts import ContactStage, EstimateRequest, warm_up
from cellbridge.daemon.core.elements import default_params
from cellbridge.emulator.world.robot_world import ARM_SKIN
from cellbridge.tactile.layout import grid_layout
from cellbridge.tactile.response import skin_response
from cellbridge.tactile.skin_geometry import parse_skin

def kernels():
    out = {}
    for m in pkgutil.iter_modules(T.__path__):
        mod = importlib.import_module(f"cellbridge.tactile.{m.name}")
        for k, v in vars(mod).items():
            if isinstance(v, CPUDispatcher):
                out[f"{mod.__name__}.{k}"] = v
    return out

def press(layout, params, bands, disks, rng, method="capacitance"):
    dc1, dc2 = skin_response(layout, disks, params)
    dc = np.stack([dc1, dc2], axis=1) + rng.normal(0.0, 2e-15, (layout.n, 2))
    touched = (dc > 50e-15).any(axis=1)
    stage = ContactStage(layout, params, 2e-15, method, birth_frames=1, bands=bands)
    got = []
    for k in range(3):
        got += stage.run(EstimateRequest("t", b"", None, dc, touched, 0.01 * k, 0.01 * k, None, 0, ()))
    return got

warm_up()
before = {k: len(v.signatures) for k, v in kernels().items()}
rng = np.random.default_rng(3)
grid = grid_layout(4, 4)
found = press(grid, default_params(grid), (), [(0.05, 0.05, 3.0, 0.012), (0.11, 0.12, 2.0, 0.01)], rng)
grid8 = grid_layout(8, 8)  # two disks in one cluster: split in two contacts
found += press(grid8, default_params(grid8), (), [(0.1, 0.1, 8.0, 0.0082), (0.08, 0.08, 1.0, 0.0169)], rng)
found += press(grid, default_params(grid), (), [(0.05, 0.05, 3.0, 0.012)], rng, "area")  # the area method
skin = parse_skin(ARM_SKIN, "arm skin")
lay = skin.layout()
c = lay.centres
band = skin.bands[0]
first = int(np.flatnonzero(band.holds(c[:, 0], c[:, 1], lay.side))[np.argmin(c[band.holds(c[:, 0], c[:, 1], lay.side), 0])])
seam = (float(c[first, 0] - 0.5 * lay.side), float(c[first, 1]), 3.0, 0.012)  # across the band's wrap seam
disks = [seam, (float(c[lay.n // 2, 0]), float(c[lay.n // 2, 1]), 3.0, 0.012)]
for b in skin.bands:
    disks += b.ghosts(disks[:2], lay.side)
found += press(lay, default_params(lay), skin.bands, disks, rng)
assert found, "no contact estimated: the kernels were not reached"
again = {k: (before.get(k, 0), len(v.signatures)) for k, v in kernels().items() if len(v.signatures) != before.get(k, 0)}
print("COMPILED AFTER WARM-UP", again)
"""


def test_no_kernel_compiles_again_after_the_warm_up_on_a_grid_or_a_robot_skin() -> None:
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    line = next(x for x in out.stdout.splitlines() if x.startswith("COMPILED AFTER WARM-UP"))
    assert line == "COMPILED AFTER WARM-UP {}", line
