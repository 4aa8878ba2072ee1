"""A skin description's emulated skin read by the daemon, in virtual time.

The virtual-time mesh (every bridge, the medium and the world in one process) writes each
gateway's serial bytes at virtual instants; the daemon offline
(:class:`~cellbridge.daemon.shell.offline.OfflineDaemon`: its sans-I/O core and its contact
loop's schedule, with the skin description as its layout) reads them at those instants,
one link per gateway, and estimates contacts inline when the service would: what the
daemon would publish, the same for the same seed on any machine, faster than real time.
The shells (ptys, ZeroMQ, processes) are left out; ``cellbridge demo`` runs them.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Iterable, Iterator
from typing import Any

from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.shell.offline import OfflineDaemon
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.mesh.skin_mesh import mesh_from_skin
from cellbridge.emulator.mesh.skin_traffic import SkinTraffic
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh
from cellbridge.emulator.world.world import World
from cellbridge.tactile.skin_geometry import SkinGeometry

__all__ = ["run_daemon_on_skin", "run_daemon_on_traffic"]

#: Host time of the virtual run's start (any; the daemon stamps wall-clock times from it).
T0 = 1_800_000_000.0


def _daemon_on(skin: SkinGeometry, gateways: Iterable[int], reads: Iterable[tuple[float, str, bytes]],
               until: float, sections: dict[str, Any] | None) -> Iterator[tuple[float, str, dict[str, Any]]]:
    """The daemon offline on ``reads`` (virtual seconds, link, bytes), one link per gateway;
    ``(t, topic, payload)`` in virtual seconds."""
    links = [{"name": f"gw{g}", "url": "/dev/null"} for g in gateways]
    d = OfflineDaemon(parse_config({"link": links, **(sections or {})}), skin.layout(), surface=skin)
    for t, topic, payload in d.run(((T0 + t, link, data) for t, link, data in reads), T0 + until, start=T0):
        yield t - T0, topic, payload


def run_daemon_on_skin(skin: SkinGeometry, world: World | None, seconds: float, *, seed: int = 1,
                       settings: Settings = Settings(), chunk: float = 1.0,
                       sections: dict[str, Any] | None = None) -> Iterator[tuple[float, str, dict[str, Any]]]:
    """Yield ``(t, topic, payload)`` of what the daemon publishes while the emulated skin of
    ``skin`` runs for ``seconds`` of virtual time under ``world`` (None: untouched); ``t`` is
    virtual seconds from the start. Contacts are estimated when the daemon's loop would
    (``[contact] rate``, frames as they come due; ``contact`` messages only when there are
    contacts, or the one after the last); the mesh runs ``chunk`` s at a time (memory stays
    bounded in a long run). ``sections``: more of the daemon's configuration."""
    mesh = mesh_from_skin(skin)
    vm = VirtualMesh(mesh, seed=seed, world=world, settings=settings, random_epochs=True)

    def reads() -> Iterator[tuple[float, str, bytes]]:
        ran = 0.0
        while ran < seconds:  # the mesh runs a chunk at a time; what it wrote is read and let go
            ran = min(ran + chunk, seconds)
            vm.run(ran - vm.tick / CLOCK_HZ)
            got = []
            for g in mesh.gateways:
                got += [(tick, g, data) for tick, data in vm.serial_chunks[g]]
                vm.serial_chunks[g].clear()
            for tick, g, data in sorted(got, key=lambda r: (r[0], r[1])):
                yield tick / CLOCK_HZ, f"gw{g}", data

    yield from _daemon_on(skin, mesh.gateways, reads(), seconds, sections)


def run_daemon_on_traffic(traffic: SkinTraffic, seconds: float, *,
                          sections: dict[str, Any] | None = None) -> Iterator[tuple[float, str, dict[str, Any]]]:
    """:func:`run_daemon_on_skin` on a skin's frame-level traffic
    (:class:`~cellbridge.emulator.mesh.skin_traffic.SkinTraffic`: the gateways' readout records
    without the cells, for a skin too large for the cycle-level mesh): the daemon's core
    reads each gateway's bytes at their arrival, one link per gateway."""
    reads = ((t, f"gw{g}", data) for t, g, data in _arrivals(traffic, seconds))
    yield from _daemon_on(traffic.skin, traffic.gateways, reads, seconds + 0.2, sections)


def _arrivals(traffic: SkinTraffic, seconds: float) -> Iterator[tuple[float, int, bytes]]:
    """The gateways' bytes of ``seconds`` of traffic in order of arrival: a frame's records may
    arrive after the next frame's first (a slow gateway's slot), and none arrives before its
    frame's gates start, so each is given out once no later frame can come before it."""
    rate = traffic.settings.rate_hz
    waiting: list[tuple[float, int, bytes]] = []
    for k in range(math.ceil(seconds * rate - 1e-9)):
        for arrival in traffic.frame(k):
            heapq.heappush(waiting, arrival)
        while waiting and waiting[0][0] <= (k + 1) / rate:
            yield heapq.heappop(waiting)
    while waiting:
        yield heapq.heappop(waiting)
