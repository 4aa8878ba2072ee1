"""The emulated mesh in virtual time, on one core.

Run: ``.venv/bin/python bench/bench_emulator.py`` (or ``make bench``); about a minute.
Prints four tables:

1. real-time factor (virtual seconds per wall second) for 1, 16 and 64 bridges at
   100 Hz (targets >= 100x for one bridge, >= 1x for 64); "delivered" is the share of
   samples that reached the gateway (64 bridges at 100 Hz periodic overload one
   gateway's cells: the last row reports events only, as a large skin should);
2. cell-link efficiency at saturation of the unscheduled path (DATA frames, what bridges
   without mesh time send): sample bits delivered to the gateway per second as a share
   of the 1 Mbit/s of its cell, with more bridges at 250 Hz on the gateway's cell than
   the cell can carry (target >= 70 %). A sample's bits are its msgpack bytes on the
   wire (14 bytes: element, cycle, c1, c2, flags). The scheduled readout's figures (its
   records, at saturation and in event-based traffic) are ``bench/bench_readout.py``'s;
3. per-element rate end to end for a 16-element gateway at 2 ms gates (target 250 Hz);
4. periodic vs event-based DATA frames per second reaching the gateway of a 4x4
   skin, idle and pressed (four moving contacts), on the unscheduled path.

Sections 2 and 4 run the bridges without the readout schedule (``readout=False``): with
it, samples on mesh time go in READOUT records, and counting DATA frames would count
only the stragglers without mesh time.
"""

from __future__ import annotations

import time

import msgpack
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.reporting import ReportingMode
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import Bridge, Cell, Mesh
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, MeshResult, VirtualMesh
from cellbridge.emulator.world.world import Contact, World
from cellbridge.protocol import Data, FrameType
from cellbridge.protocol.messages import packed_samples

from timing import pin_to_one_core


def ok(flag: bool) -> str:
    return "yes" if flag else "NO"


def delivered_share(r: MeshResult, mesh: Mesh, rate: int, lo: float, hi: float) -> float:
    want = len(mesh.bridges) * rate * (hi - lo)
    got = sum(1 for v in r.samples().values() for s in v if lo * CLOCK_HZ <= s.cycle < hi * CLOCK_HZ)
    return got / want


def real_time_factor() -> None:
    print("1. virtual time, 100 Hz sampling")
    print(f"{'mesh':<12} {'bridges':>7} {'virtual s':>9} {'wall s':>7} {'x real time':>11} {'delivered':>9} "
          f"{'target':>7} {'ok':>4}")
    big = meshgen.grid(8, 8, gateways=(28,))
    for mesh, secs, target, mode in ((meshgen.line(1), 30.0, 100.0, ReportingMode()),
                                     (meshgen.grid(4, 4), 5.0, None, ReportingMode()),
                                     (big, 4.0, 1.0, ReportingMode()),
                                     (big, 4.0, 1.0, ReportingMode(40, 1000))):
        vm = VirtualMesh(mesh, seed=1, settings=Settings(reporting=mode))
        t0 = time.perf_counter()
        r = vm.run(secs)
        wall = time.perf_counter() - t0
        share = f"{delivered_share(r, mesh, 100, 0.5, secs - 0.5):.1%}" if mode.periodic else "events"
        t = f"{target:g}x" if target else "-"
        print(f"{mesh.name:<12} {len(mesh.bridges):>7} {secs:>9.1f} {wall:>7.2f} {secs / wall:>11.1f} "
              f"{share:>9} {t:>7} {ok(secs / wall >= target) if target else '':>4}")


def star(n: int) -> Mesh:
    """A gateway and n bridges on one cell: the gateway's link is that cell."""
    return Mesh((Cell(1),), tuple(Bridge(i, (1,), ((i - 1) * 0.04, 0.0), i == 1) for i in range(1, n + 2)),
                name=f"star-{n}")


def efficiency() -> None:
    print("\n2. cell-link efficiency at the gateway's cell, 250 Hz per bridge (1 Mbit/s raw), DATA frames "
          "(no readout schedule; bench_readout.py section 4 for the schedule's)")
    print(f"{'bridges':>7} {'offered kbit/s':>14} {'delivered kbit/s':>16} {'share':>6} {'collisions':>10} "
          f"{'target':>7} {'ok':>4}")
    for n in (40, 60):
        mesh = star(n)
        vm = VirtualMesh(mesh, seed=1, settings=Settings(rate_hz=250), readout=False)
        vm.run(0.5)
        first = len(vm.frames[1])
        secs = 2.0
        r = vm.run(secs)
        # the samples' bytes as they travel (protocol version 3 packs all but a frame's first)
        bits = sum(8 * len(msgpack.packb(x)) for f in r.gateway_frames[1][first:] if isinstance(f.payload, Data)
                   and f.origin != 1 for x in packed_samples(f.payload.samples, f.payload.period))
        share = bits / secs / mesh.bitrate
        offered = n * 250 * 14 * 8 / 1000
        print(f"{n:>7} {offered:>14.0f} {bits / secs / 1000:>16.0f} {share:>6.1%} "
              f"{r.medium.get('collision', 0):>10} {'70%':>7} {ok(share >= 0.70):>4}")


def per_element_rate() -> None:
    print("\n3. per-element rate end to end, 16 elements behind one gateway, 2 ms gates")
    print(f"{'mesh':<10} {'set Hz':>6} {'min Hz':>7} {'mean Hz':>7} {'queue drops':>11} {'target':>7} {'ok':>4}")
    for mesh in (meshgen.grid(4, 4), star(15)):
        name = mesh.name or "star-15"
        vm = VirtualMesh(mesh, seed=2, settings=Settings(rate_hz=250))
        r = vm.run(4.0)
        lo, hi = 1.0, 3.5
        rates = [sum(1 for s in r.samples().get(b, []) if lo * CLOCK_HZ <= s.cycle < hi * CLOCK_HZ) / (hi - lo)
                 for b in mesh.ids]
        print(f"{name:<10} {250:>6} {min(rates):>7.1f} {sum(rates) / len(rates):>7.1f} "
              f"{r.total('queue_drops'):>11} {'250':>7} {ok(min(rates) >= 249.0):>4}")


def reporting_modes() -> None:
    print("\n4. DATA frames per second at the gateway of a 4x4 skin, 100 Hz (its corner gateway 1), no readout "
          "schedule (bench_readout.py section 3 for the schedule's traffic)")
    print(f"{'skin':<8} {'periodic':>9} {'event-based':>11} {'ratio':>6} {'bridges heard':>13}")
    mesh = meshgen.grid(4, 4, gateways=(1,))  # (the figures before the grid's default gateway moved to its centre)
    moving = [Contact(0.0, 10.0, 0.0, 0.02 * k, 2.0, 0.02, vx=0.03, vy=0.0) for k in range(4)]
    for label, contacts in (("idle", []), ("pressed", moving)):
        rates = {}
        for mode in (ReportingMode(), ReportingMode(40, 1000)):
            vm = VirtualMesh(mesh, seed=3, world=World(mesh, list(contacts)), settings=Settings(reporting=mode),
                             readout=False)
            r = vm.run(5.0)
            frames = [f for f in r.gateway_frames[1] if f.type is FrameType.DATA
                      and f.payload.samples[0].cycle >= CLOCK_HZ]  # type: ignore[union-attr]  # a DATA frame's payload is a Data
            rates[mode.periodic] = len(frames) / 4.0
            if not mode.periodic:
                seen = len({f.origin for f in frames})
        print(f"{label:<8} {rates[True]:>9.1f} {rates[False]:>11.1f} {rates[False] / rates[True]:>6.1%} "
              f"{seen:>13}")


def main() -> None:
    pin_to_one_core()
    real_time_factor()
    efficiency()
    per_element_rate()
    reporting_modes()


if __name__ == "__main__":
    main()
