"""Mesh time and skin frames attacked as a robot and its users will: resets under a press,
forged or corrupted beacons, clocks at their limits. Each test is a defect once found."""

from __future__ import annotations

from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import VirtualMesh
from cellbridge.emulator.world.world import Contact, World
from cellbridge.protocol import Data, Readout

CORNER = (0.0585, 0.0625)  # across the corner of bridges 6, 7, 10 and 11 of a 4x4 grid
UNDER = (6, 7, 10, 11)


def test_bridges_reset_under_a_press_deliver_again_within_a_second() -> None:
    """The four bridges under a held press reset at 5 s, DATA frames (the path a skin
    without the readout, or a bridge not yet on it, takes). A restarted bridge whose HELLO
    went to one parent and whose next frames go to another was silenced by that relay's
    duplicate filter: its new numbers (1, 2, ...) lay inside the window of its old ones, so
    the relay dropped every frame until the new numbering passed the old (bridge 6: 14 s
    and more, element unknown the whole time). A relay only needs to catch retransmitted
    copies and loops, which come within a few frames of the newest."""
    mesh = meshgen.grid(4, 4, gateways=(1,))
    vm = VirtualMesh(mesh, seed=1, world=World(mesh, [Contact(4.0, 4.5, *CORNER, 3.0, 0.020)]), random_epochs=True,
                     readout=False)
    for b in UNDER:
        vm.restart(b, at=5.0)
    vm.run(7.0)
    for b in UNDER:
        mine = [f for f in vm.frames[1] if f.origin == b]
        hello = max(i for i, f in enumerate(mine) if f.seq == 0)  # its restart's HELLO
        after = [f for f in mine[hello:] if isinstance(f.payload, Data)]
        sent = vm.nodes[b].counters_snapshot()["data_frames"]
        assert sent > 30
        assert len(after) >= sent - 10, (b, len(after), sent)  # a few lost while the restart is recognised


def test_bridges_reset_under_a_press_are_read_out_again_within_a_second() -> None:
    """The same resets on the readout (the default): within a second of its restart each
    bridge is back in the gateway's records as a sample, and stays there frame after frame
    (periodic reporting: every frame of a bridge on the schedule holds its sample)."""
    mesh = meshgen.grid(4, 4, gateways=(1,))
    vm = VirtualMesh(mesh, seed=1, world=World(mesh, [Contact(4.0, 4.5, *CORNER, 3.0, 0.020)]), random_epochs=True)
    for b in UNDER:
        vm.restart(b, at=5.0)
    vm.run(7.5)
    rate = 100
    sampled: dict[int, set[int]] = {b: set() for b in UNDER}
    newest = 0
    for f in vm.frames[1]:
        if isinstance(f.payload, Readout):
            newest = max(newest, f.payload.index)
            for smp in f.payload.samples:
                if smp.bridge in sampled:
                    sampled[smp.bridge].add(f.payload.index)
    # frame indices count mesh time from the root's epoch: the newest read out is ~7.5 s
    at = lambda t: newest - round((7.5 - t) * rate)
    for b in UNDER:
        indices = sampled[b]
        before = [i for i in indices if at(4.0) <= i < at(5.0)]
        assert len(before) >= 0.9 * rate, (b, len(before))  # read out before the reset, too
        back = [i for i in indices if at(6.0) <= i < at(7.0)]
        assert len(back) >= 0.95 * rate, (b, len(back))  # back on the schedule by 6 s, and kept
