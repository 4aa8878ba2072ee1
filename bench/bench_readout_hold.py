"""Bridge processes held up on a loaded host: what the scheduled readout still delivers.

Run: ``.venv/bin/python bench/bench_readout_hold.py [--seed N] [--rate HZ] [--event] [--gateway ID]``.

A virtual real-time 4x4 (one gateway: the grid's default, its centre, or ``--gateway``; the real-time shells' schedule: levels of
``READOUT_WINDOW``, slots packed ``READOUT_HOP`` apart, no per-hop acknowledgements; each
message 2 ms late on average, each wake 1 ms) runs 6 s to settle, then the deepest leaf, or
the deepest relay below another relay, is held up (:meth:`VirtualMesh.hold`, as ``SIGSTOP``
then ``SIGCONT``) for 50 to 150 ms, once or every 500 ms, for 2.6 s. Printed per case:
element-frames of the window the host does not know (missing, or in no record), how many of
the held bridge's frames are known, and element-frames called known whose sample is not
what the bridge sampled (the emulator's ground truth: must be 0). Deterministic (virtual
time): a figure changes only with the code.
"""

from __future__ import annotations

import argparse

from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.firmware import Firmware
from cellbridge.emulator.firmware.reporting import ReportingMode
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import Latency, VirtualMesh
from cellbridge.emulator.realtime.process_bridge import ACK_SLACK, READOUT_HOP, READOUT_WINDOW
from cellbridge.emulator.world.world import Contact, World
from cellbridge.protocol import FrameType, Readout, Sample

WARM, SPAN = 6.0, 3.0  #: s settled before the holds; s held and measured after


def run(kind: str, held_ms: int, every_ms: int, seed: int, rate: int, event: bool,
        gateway: int | None = None) -> tuple[int, int, int, int, int]:
    """(unknown element-frames, of, the held bridge's known frames, frames, wrong) of one case."""
    truth: dict[tuple[int, int], tuple[int, int]] = {}
    real = Firmware._readout_sample

    def logged(self: Firmware, s: Sample, kept: bool, start: int) -> None:
        truth[(self.me, s.index)] = (s.c1, s.c2)
        real(self, s, kept, start)

    mesh = meshgen.grid(4, 4) if gateway is None else meshgen.grid(4, 4, gateways=(gateway,))
    settings = Settings(rate_hz=rate, reporting=ReportingMode(40, 1000)) if event else Settings(rate_hz=rate)
    world = World(mesh, [Contact(1.5 + 0.7 * i, 0.5 + 0.5 * i, 0.02 + 0.04 * (i % 3), 0.03 + 0.03 * (i % 2),
                                 3.0, 0.02) for i in range(6)]) if event else None
    Firmware._readout_sample = logged  # type: ignore[method-assign]  # the ground truth, logged
    try:
        vm = VirtualMesh(mesh, seed=seed, latency=Latency(up=0.002, down=0.002, wake_late=0.001), settings=settings,
                         world=world, readout=True, readout_acks=False, readout_window=READOUT_WINDOW,
                         readout_hop=READOUT_HOP, ack_slack=ACK_SLACK, readout_depths=mesh.readout_depths())
        vm.run(WARM)
        parents, kids = vm.parents(), vm.children()

        def depth(b: int) -> int:
            d = 0
            while parents.get(b) is not None and d < len(parents):
                b, d = parents[b], d + 1  # type: ignore[assignment]  # (not None: checked)
            return d

        gw = set(mesh.gateways)
        cands = [b for b in mesh.ids if b not in gw and (not kids[b] if kind == "leaf" else
                                                       kids[b] and parents[b] not in gw)]
        victim = max(cands, key=lambda b: (depth(b), b))
        t = WARM + 0.2
        while held_ms and t < WARM + SPAN - 0.3:
            vm.hold(victim, t, held_ms / 1000)
            if not every_ms:
                break
            t += every_ms / 1000
        vm.run(SPAN)
    finally:
        Firmware._readout_sample = real  # type: ignore[method-assign]
    lo, hi = int((WARM + 0.1) * rate), int((WARM + SPAN - 0.3) * rate)
    known: set[tuple[int, int]] = set()
    wrong = 0
    for frames in vm.frames.values():
        for f in frames:
            if f.type is FrameType.READOUT:
                r: Readout = f.payload  # type: ignore[assignment]  # a READOUT frame's payload
                if lo <= r.index < hi:
                    for s in r.samples:
                        known.add((s.bridge, r.index))
                        wrong += truth.get((s.bridge, r.index)) != (s.c1, s.c2)
                    known.update((b, r.index) for b in r.unchanged)
    n = len(mesh.ids) * (hi - lo)
    return n - len(known), n, sum(1 for b, _ in known if b == victim), hi - lo, wrong


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--rate", type=int, default=100)
    ap.add_argument("--event", action="store_true", help="event-based reporting, presses in the world")
    ap.add_argument("--gateway", type=int, default=None, help="the gateway's bridge id (default: the grid's centre)")
    args = ap.parse_args()
    gw = meshgen.grid(4, 4).gateways[0] if args.gateway is None else args.gateway
    print(f"4x4, gateway {gw}, {args.rate} Hz, {'event-based' if args.event else 'periodic'}, seed {args.seed}")
    print(f"{'held':>6} {'every':>6} {'bridge':>6} {'unknown':>9} {'of':>6} {'held known':>11} {'wrong':>6}")
    for kind in ("leaf", "relay"):
        for every in (0, 500):
            for held in (0, 50, 90, 110, 150):
                if held == 0 and every:
                    continue
                unknown, n, vk, frames, wrong = run(kind, held, every, args.seed, args.rate, args.event, args.gateway)
                print(f"{held:>4}ms {every or 'once':>6} {kind:>6} {unknown:>9} {n:>6} {vk:>5}/{frames:<5} {wrong:>6}")


if __name__ == "__main__":
    main()
