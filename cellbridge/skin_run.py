"""A skin description's emulated skin read by the daemon's core, in virtual time.

The virtual-time mesh (every bridge, the medium and the world in one process) writes each
gateway's serial bytes at virtual instants; the daemon's :class:`Pipeline` (its sans-I/O
core, with the skin description as its layout) reads them at those instants, one link per
gateway, and its contact worker estimates inline: what the daemon would publish, the same
for the same seed on any machine, faster than real time. The shells (ptys, ZeroMQ,
processes) are left out; ``cellbridge demo`` runs them.
"""

from __future__ import annotations

import heapq
import logging
from collections.abc import Iterator
from typing import Any

from cellbridge.daemon.config import parse_config
from cellbridge.daemon.contact_worker import ContactWorker, InlineExecutor
from cellbridge.daemon.messages import Publish
from cellbridge.daemon.pipeline import Pipeline
from cellbridge.emulator.commands import Settings
from cellbridge.emulator.skin_mesh import mesh_from_skin
from cellbridge.emulator.skin_traffic import SkinTraffic
from cellbridge.emulator.virtual import CLOCK_HZ, VirtualMesh
from cellbridge.emulator.world import World
from cellbridge.tactile.skin_geometry import SkinGeometry

__all__ = ["run_daemon_on_skin", "run_daemon_on_traffic"]

#: Host time of the virtual run's start (any; the daemon stamps wall-clock times from it).
T0 = 1_800_000_000.0


def run_daemon_on_skin(skin: SkinGeometry, world: World | None, seconds: float, *, seed: int = 1,
                       settings: Settings = Settings(), step: float = 0.005, chunk: float = 1.0,
                       sections: dict[str, Any] | None = None) -> Iterator[tuple[float, str, dict[str, Any]]]:
    """Yield ``(t, topic, payload)`` of what the daemon publishes while the emulated skin of
    ``skin`` runs for ``seconds`` of virtual time under ``world`` (None: untouched); ``t`` is
    virtual seconds from the start. Contacts are estimated every ``step`` s when a new skin
    frame is in (``contact`` messages only when there are contacts, or the one after the
    last); the mesh runs ``chunk`` s at a time (memory stays bounded in a long run).
    ``sections``: more of the daemon's configuration."""
    mesh = mesh_from_skin(skin)
    vm = VirtualMesh(mesh, seed=seed, world=world, settings=settings, random_epochs=True)
    links = [{"name": f"gw{g}", "url": "/dev/null"} for g in mesh.gateways]
    p = Pipeline(parse_config({"link": links, **(sections or {})}), skin.layout())
    p.surface = skin
    w = ContactWorker(logging.getLogger("cellbridge.skin_run"), InlineExecutor)
    done = {g: 0 for g in mesh.gateways}
    now = 0.0
    shown = False
    ran = 0.0
    while now < seconds:
        if ran < min(now + step, seconds):
            ran = min(ran + chunk, seconds)
            vm.run(ran - vm.tick / CLOCK_HZ)
        reads = []
        for g in mesh.gateways:
            chunks = vm.serial_chunks[g]
            while done[g] < len(chunks) and chunks[done[g]][0] / CLOCK_HZ <= now + step:
                tick, data = chunks[done[g]]
                reads.append((tick, g, data))
                done[g] += 1
            del chunks[:done[g]]  # read: kept no longer
            done[g] = 0
        now += step
        for tick, g, data in heapq.nsmallest(len(reads), reads, key=lambda r: (r[0], r[1])):
            t = tick / CLOCK_HZ
            for m in p.feed(f"gw{g}", data, T0 + t):
                if isinstance(m, Publish):
                    yield t, m.topic, m.payload
        for m in p.tick(T0 + now):
            if isinstance(m, Publish):
                yield now, m.topic, m.payload
        job = p.contact_job(T0 + now)
        if job is not None:
            contacts = w.estimate_now(job)
            if contacts or shown:
                yield now, "contact", p.contact_frame(job, contacts).payload
            shown = bool(contacts)


def run_daemon_on_traffic(traffic: SkinTraffic, seconds: float, *, step: float = 0.005,
                          sections: dict[str, Any] | None = None) -> Iterator[tuple[float, str, dict[str, Any]]]:
    """:func:`run_daemon_on_skin` on a skin's frame-level traffic
    (:class:`~cellbridge.emulator.skin_traffic.SkinTraffic`: the gateways' readout records
    without the cells, for a skin too large for the cycle-level mesh): the daemon's core
    reads each gateway's bytes at their arrival, one link per gateway."""
    skin = traffic.skin
    links = [{"name": f"gw{g}", "url": "/dev/null"} for g in traffic.gateways]
    p = Pipeline(parse_config({"link": links, **(sections or {})}), skin.layout())
    p.surface = skin
    w = ContactWorker(logging.getLogger("cellbridge.skin_run"), InlineExecutor)
    reads = traffic.run(seconds)
    pending = next(reads, None)
    now = 0.0
    shown = False
    while now < seconds + 0.2:
        now += step
        while pending is not None and pending[0] <= now:
            t, g, data = pending
            for m in p.feed(f"gw{g}", data, T0 + t):
                if isinstance(m, Publish):
                    yield t, m.topic, m.payload
            pending = next(reads, None)
        for m in p.tick(T0 + now):
            if isinstance(m, Publish):
                yield now, m.topic, m.payload
        job = p.contact_job(T0 + now)
        if job is not None:
            contacts = w.estimate_now(job)
            if contacts or shown:
                yield now, "contact", p.contact_frame(job, contacts).payload
            shown = bool(contacts)
