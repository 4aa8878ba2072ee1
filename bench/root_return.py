"""The root gateway goes and comes back: one scenario for the mesh-time test and its bench.

tests/test_emulator_meshtime.py asserts on it and bench/bench_root_return.py measures it
over seeds; both build it and read its errors here, so what is asserted is what is
measured. Virtual time, a 4x4 grid with gateways 1 and 16, crystals within ±50 ppm,
counters started at unrelated epochs. Gateway 1, the time root, is cut off (its cells
cut) or powered off at 8 s; gateway 16 takes the skin's time on, its fit frozen, so the
skin's time is then a line in true time. At 12 s gateway 1 is back.
"""

from __future__ import annotations

import functools
from typing import Callable, Literal

from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import Mesh
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh

US = CLOCK_HZ // 1_000_000  #: cycles per microsecond
ROOT, HEIR = 1, 16  #: the root gateway that goes, the gateway that carries the time on
GONE_AT, BACK_AT = 8.0, 12.0  #: s, when the root goes and when it is back

How = Literal["cut", "restart"]
HOWS: tuple[How, ...] = ("cut", "restart")  #: cut off (cells cut), or powered off and rebooted


def sync_bound(hops: int) -> float:
    """The sync target, µs: p99 <= 2 µs at one hop, <= 10 µs at eight, linear between."""
    return 2.0 + max(0, hops - 1) * 8.0 / 7.0


def root_goes_and_returns(seed: int, how: How) -> tuple[Mesh, VirtualMesh]:
    """The mesh and its virtual run, not started: the root is cut off (``"cut"``) or
    powered off and rebooted (``"restart"``) at :data:`GONE_AT` and back at :data:`BACK_AT`."""
    mesh = meshgen.grid(4, 4, gateways=(ROOT, HEIR))
    vm = VirtualMesh(mesh, seed=seed, random_epochs=True)
    if how == "cut":
        for c in next(b for b in mesh.bridges if b.id == ROOT).cells:
            vm.cut(c, at=GONE_AT)
            vm.at(BACK_AT, functools.partial(vm.medium.restore_cell, c))
    else:
        vm.kill(ROOT, at=GONE_AT)
        vm.restart(ROOT, at=BACK_AT)
    return mesh, vm


def skin_time_line(vm: VirtualMesh, span: float = 0.4) -> Callable[[int], float]:
    """The skin's time while the heir is root (its fit frozen): its global time now and
    ``span`` s later (the run advances by ``span``), as a line in the true tick."""
    heir = vm.nodes[HEIR]
    t1, y1 = vm.tick, heir.clock.global_at(heir.crystal.local(vm.tick))
    vm.run(span)
    t2, y2 = vm.tick, heir.clock.global_at(heir.crystal.local(vm.tick))
    return lambda tick: y1 + (y2 - y1) / (t2 - t1) * (tick - t1)


def errors_from_line(vm: VirtualMesh, line: Callable[[int], float]) -> dict[int, float | None]:
    """Every bridge but the root that went: |its global time − the line| now in µs, None
    where it is off mesh time. The root keeps its own time until it hears the skin
    (restart) or is the root again (cut), so it is not judged against the line."""
    out: dict[int, float | None] = {}
    for b, fw in vm.nodes.items():
        if b == ROOT:
            continue
        local = fw.crystal.local(vm.tick)
        out[b] = abs(fw.clock.global_at(local) - line(vm.tick)) / US if fw.clock.synced(local) else None
    return out
