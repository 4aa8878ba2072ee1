"""The real-time skin's CPU savings under the faults of a test bench, in virtual time.

A relay computes its readout sample at its children's records (lazy sampling), and a
real-time bridge has the chip compute its next samples' counts ahead (Sampler.prefetch,
as process_bridge does after a wake that sampled). Both claim to change nothing a bridge
sends: whatever the bench does to the skin (children dying or reset mid-frame, the time
root dying and coming back, rate and gate commands while counts are computed ahead, a
RESET, lossy cells, a still and a moving press at 250 Hz), every gateway writes the
same bytes at the same ticks gate by gate, lazily, and lazily with counts computed ahead.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import Mesh
from cellbridge.emulator.mesh.virtual import VirtualMesh
from cellbridge.emulator.realtime.process_bridge import READOUT_HOP, READOUT_WINDOW
from cellbridge.emulator.world.world import Contact, World
from cellbridge.protocol import ADDR_BROADCAST, Command, Flags, Frame, Op

from support.virtual_prefetch import prefetch_after_sampling

HOST = 0


def _cmd(seq: int, target: int, op: Op, value: int | None = None) -> Frame:
    return Frame(0, target, HOST, seq, Command(seq, op, value), flags=int(Flags.ACK_REQUEST))


def _children_die(vm: VirtualMesh) -> None:  # relay 3's only child dies mid-frame, relay 8's resets
    vm.kill(6, 3.0033)
    vm.restart(9, 3.0051)


def _root_dies(vm: VirtualMesh) -> None:  # the time root goes, and comes back: the gates move
    vm.kill(1, 3.0037)
    vm.restart(1, 3.5)


def _rates(vm: VirtualMesh) -> None:  # counts computed ahead at 100 Hz, then 50 Hz, one bridge 200
    vm.host_write(1, _cmd(100, ADDR_BROADCAST, Op.SET_RATE, 50), at=3.0037)
    vm.host_write(1, _cmd(101, 3, Op.SET_RATE, 200), at=3.3011)


def _gate(vm: VirtualMesh) -> None:  # a relay's gate longer than its children's
    vm.host_write(1, _cmd(100, 2, Op.SET_GATE, 150_000), at=3.0037)


def _reset(vm: VirtualMesh) -> None:
    vm.host_write(1, _cmd(100, 5, Op.RESET), at=3.0037)


def _nothing(vm: VirtualMesh) -> None:
    pass


_PRESSES = [Contact(2.9, 0.3, 0.05, 0.05, 2.0, 0.03), Contact(3.1, 0.2, 0.09, 0.02, 3.0, 0.02, 0.05, 0.0)]

SCENARIOS: dict[str, tuple[Mesh, int, Callable[[VirtualMesh], None], list[Contact], int]] = {
    "children die and reset mid-frame": (meshgen.grid(3, 3, gateways=(1,)), 100, _children_die, [], 2),
    "the time root dies and comes back": (meshgen.grid(3, 3, gateways=(1, 9)), 100, _root_dies, [], 2),
    "the root dies on lossy cells": (meshgen.grid(3, 3, gateways=(1, 9), loss=0.03), 100, _root_dies, [], 2),
    "rate commands while counts are ahead": (meshgen.grid(3, 3, gateways=(1,)), 100, _rates, [], 2),
    "a relay's longer gate": (meshgen.grid(3, 3, gateways=(1,)), 100, _gate, [], 2),
    "a RESET": (meshgen.grid(3, 3, gateways=(1,)), 100, _reset, [], 2),
    "a still and a moving press at 250 Hz": (meshgen.grid(4, 4, gateways=(1,)), 250, _nothing, _PRESSES, 3),
}


def _run(name: str, lazy: bool, ahead: bool) -> list[list[tuple[int, bytes]]]:
    mesh, rate, fault, presses, seed = SCENARIOS[name]
    vm = VirtualMesh(mesh, seed=seed, world=World(mesh, list(presses)), settings=Settings(rate_hz=rate),
                     lazy_sampling=lazy, readout=True, readout_acks=False,
                     readout_window=READOUT_WINDOW, readout_hop=READOUT_HOP)
    fault(vm)
    if ahead:
        prefetch_after_sampling(vm)
    vm.run(3.6)
    return [vm.serial_chunks[g] for g in mesh.gateways]


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_the_skin_sends_the_same_gate_by_gate_lazily_and_with_counts_computed_ahead(name: str) -> None:
    eager = _run(name, lazy=False, ahead=False)
    assert sum(len(chunks) for chunks in eager) > 500  # the gateways wrote all along
    assert _run(name, lazy=True, ahead=False) == eager
    assert _run(name, lazy=True, ahead=True) == eager
