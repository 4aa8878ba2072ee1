"""What the emulated skin does, as one hash per scenario: a change that only makes the
skin cheaper must leave every hash as it was.

Run: ``.venv/bin/python bench/bench_skin_hash.py [--seconds 3]`` (about a minute); compare
its table with the same script on the commit before the change.

Each scenario runs :class:`~cellbridge.emulator.mesh.virtual.VirtualMesh` (deterministic:
a pure function of the mesh, the scenario and the seed) and hashes, in order, every
gateway's serial writes (the tick of each write and its bytes), every bridge's firmware
counters and the medium's counters. The scenarios are the configurations the CPU and
readout benches use:

1. a periodic 4x4 at 100 Hz with the real-time shells' readout (``bench_skin_cpu_split.py``);
2. the same skin event-based (threshold 40) under four moving presses (``bench_readout.py``);
3. the same 4x4 with the latencies of real processes modelled (``Latency``);
4. a periodic 8x8 at 250 Hz with a gateway per quadrant and 1 % loss per hop (``bench_readout.py``).
"""

from __future__ import annotations

import argparse
import hashlib
import time
from collections.abc import Callable

from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.reporting import ReportingMode
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import Latency, VirtualMesh
from cellbridge.emulator.realtime.process_bridge import ACK_SLACK, READOUT_HOP, READOUT_WINDOW
from cellbridge.emulator.world.world import Contact, World

from timing import table

RT = dict(readout=True, readout_acks=False, readout_window=READOUT_WINDOW, readout_hop=READOUT_HOP,
          ack_slack=ACK_SLACK)


def periodic_4x4() -> VirtualMesh:
    return VirtualMesh(meshgen.grid(4, 4), seed=1, **RT)  # type: ignore[arg-type]  # firmware keywords


def event_4x4() -> VirtualMesh:
    mesh = meshgen.grid(4, 4)
    moving = [Contact(0.0, 100.0, 0.0, 0.02 * k + 0.01, 2.0, 0.02, vx=0.03, vy=0.0) for k in range(4)]
    return VirtualMesh(mesh, seed=3, world=World(mesh, moving), settings=Settings(reporting=ReportingMode(40, 1000)),
                       readout=True)


def latency_4x4() -> VirtualMesh:
    return VirtualMesh(meshgen.grid(4, 4), seed=5, latency=Latency(seed=2), **RT)  # type: ignore[arg-type]


def grid_8x8() -> VirtualMesh:
    mesh = meshgen.grid(8, 8, gateways=(10, 14, 42, 46), loss=0.01)
    return VirtualMesh(mesh, seed=2, settings=Settings(rate_hz=250), readout=True)


SCENARIOS: dict[str, Callable[[], VirtualMesh]] = {
    "periodic 4x4 100 Hz (real-time readout)": periodic_4x4,
    "event:40 4x4, four moving presses": event_4x4,
    "periodic 4x4, real-time latencies": latency_4x4,
    "periodic 8x8 250 Hz, 4 gateways, 1 % loss": grid_8x8,
}


def digest(vm: VirtualMesh) -> str:
    """Hash of every gateway's serial writes, every bridge's counters and the medium's."""
    h = hashlib.sha256()
    for g in sorted(vm.serial_chunks):
        for tick, data in vm.serial_chunks[g]:
            h.update(b"%d %d:%d:" % (g, tick, len(data)))
            h.update(data)
    res = vm.result()
    for b in sorted(res.counters):
        h.update(repr((b, sorted(res.counters[b].items()))).encode())
    h.update(repr(sorted(res.medium.items())).encode())
    return h.hexdigest()[:16]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=3.0, help="skin time per scenario (default 3)")
    args = ap.parse_args()
    rows = []
    for name, make in SCENARIOS.items():
        vm = make()
        t0 = time.process_time()
        vm.run(args.seconds)
        cpu = time.process_time() - t0
        frames = sum(len(c) for c in vm.serial_chunks.values())
        rows.append([name, str(frames), f"{cpu:.2f}", digest(vm)])
    table(f"what the skin did in {args.seconds:g} s of virtual time",
          ["scenario", "serial writes", "CPU s", "hash"], rows)


if __name__ == "__main__":
    main()
