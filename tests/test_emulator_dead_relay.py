"""A relay that dies mid-run costs the skin its own subtree, not the rest of it.

Its parent expected it in every frame. Waited for until its slot (as a slow child is),
under the real-time shells' message delays the parent's record then reached the next
level after that level's slot, and so on up: siblings and cousins of the dead relay went
missing with it until it was forgotten, 2 s later (a third of the rest of a 4x4 known).
A child silent for ``ReadoutConfig.quiet`` is no longer waited for, only listed missing.
"""

from __future__ import annotations

from collections import defaultdict

from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import Latency, VirtualMesh
from cellbridge.emulator.realtime.process_bridge import ACK_SLACK, READOUT_HOP, READOUT_WINDOW
from cellbridge.protocol import FrameType, Readout, StreamDecoder

from support.payloads import payload_as

WARM = 6.0  #: s of virtual time before the kill: routes and mesh time settled
RATE = 100


def test_a_dead_relay_leaves_the_rest_of_the_skin_known_under_process_delays() -> None:
    mesh = meshgen.grid(4, 4, gateways=(1,))
    # the real-time shells' readout, and messages 6 ms late on average each way
    vm = VirtualMesh(mesh, seed=5, latency=Latency(up=0.006, down=0.006, wake_late=0.003), readout=True,
                     readout_acks=False, readout_window=READOUT_WINDOW, readout_hop=READOUT_HOP,
                     ack_slack=ACK_SLACK, readout_depths=mesh.readout_depths())
    vm.run(WARM)
    parents, children = vm.parents(), vm.children()

    def subtree(root: int) -> set[int]:
        out, todo = {root}, [root]
        while todo:
            for c in children.get(todo.pop(), set()) - out:
                out.add(c)
                todo.append(c)
        return out

    # a relay below another relay: its parent's record has a level above it to reach
    relays = [b for b in mesh.ids if children.get(b) and parents.get(b) not in (None, *mesh.gateways)]
    assert relays, parents
    victim = max(relays, key=lambda b: (len(mesh.ids) - len(subtree(b)), b))
    others = set(mesh.ids) - subtree(victim)
    start = len(vm.serial_chunks[1])
    vm.kill(victim, WARM + 0.1)
    vm.run(1.6)
    known: dict[int, set[int]] = defaultdict(set)
    dec = StreamDecoder()
    for _, chunk in vm.serial_chunks[1][start:]:
        for f in dec.feed(chunk):
            if f.type is FrameType.READOUT:
                r = payload_as(f, Readout)
                known[r.index] |= {s.bridge for s in r.samples} | set(r.unchanged)
    frames = [k for k in known if (WARM + 0.3) * RATE <= k < (WARM + 1.3) * RATE]
    assert len(frames) >= 95
    share = sum(len(known[k] & others) for k in frames) / (len(frames) * len(others))
    assert share >= 0.99, (victim, share)
    assert not any(victim in known[k] for k in frames)  # the dead relay is never called known
