"""After a gateway dies, every bridge the other gateways reach still fits the readout schedule.

The schedule's levels (``Mesh.readout_depths``) are fixed when the skin starts. They were
the deepest bridge's hops from its nearest gateway plus two: a 4x4 with its centre bridge 6
and corner 16 as gateways got 5, and once 6 died bridge 1 was 6 hops from 16. A bridge
deeper than the last level sends in its parent's slot, always too late, so bridge 1 was
listed missing in every frame, for good (never wrong, but a corner of the skin lost).
"""

from __future__ import annotations

from collections import Counter
from itertools import combinations

import pytest
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import VirtualMesh
from cellbridge.protocol import FrameType, Readout

from support.payloads import payload_as


@pytest.mark.parametrize(("rows", "cols"), [(2, 3), (3, 3), (4, 4), (3, 5), (5, 5)])
def test_the_schedule_has_a_level_for_every_bridge_after_any_one_gateway_died(rows: int, cols: int) -> None:
    """Every pair of gateways of small grids: the levels cover the deepest bridge the other
    gateway reaches once either one is dead (and, as before, the intact skin's depth plus two)."""
    ids = range(1, rows * cols + 1)
    for pair in combinations(ids, 2):
        mesh = meshgen.grid(rows, cols, gateways=pair)
        depths = mesh.readout_depths()
        assert depths >= max(mesh.hops().values()) + 2
        for g in pair:
            assert depths >= max(mesh.hops(dead=frozenset((g,))).values()), (pair, g, depths)


def test_one_gateway_keeps_its_depth_plus_two() -> None:
    """A single gateway has no failover to make room for: the default 4x4 (centre 6) keeps 6 levels."""
    assert meshgen.grid(4, 4).readout_depths() == 6
    assert meshgen.grid(4, 4, gateways=(1,)).readout_depths() == 8


def test_the_centre_gateway_dying_leaves_the_far_corner_known_through_the_other() -> None:
    """Gateways 6 (the centre) and 16 (the far corner); 6 dies at 6 s: in the last second,
    every bridge but 6 is known (sampled) in nearly every frame 16 delivers, bridge 1, six
    hops from 16, too (before: in none)."""
    mesh = meshgen.grid(4, 4, gateways=(6, 16), loss=0.01)
    vm = VirtualMesh(mesh, seed=5, random_epochs=True, readout=True)
    vm.kill(6, at=6.0)
    vm.run(9.0)
    records = [payload_as(f, Readout) for f in vm.frames[16] if f.type is FrameType.READOUT and f.src == f.origin]
    top = max(r.index for r in records)
    window = range(top - 105, top - 5)  # (the last frames may still be on their way)
    known: Counter[int] = Counter()
    for r in records:
        if r.index in window:
            known.update({s.bridge for s in r.samples} | set(r.unchanged))
    assert {b: known[b] for b in mesh.ids if b != 6 and known[b] < 95} == {}
