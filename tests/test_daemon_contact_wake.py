"""A read that completes a skin frame ends the contact loop's rest after a look that found
nothing (``ContactScheduler.wakes``): in the offline driver, and in the service's loop.

A frame is complete at the read of its last gateway record. A look at an earlier read of
the frame finds nothing, and the rest after it (a quarter of a period, so that a line read
in small pieces does not cost a look per piece) held the completed frame back until its
end: up to 2.5 ms at 100 Hz on every frame, every press's first contact included."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import pytest
import zmq.asyncio
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.shell.contact_worker import InlineExecutor
from cellbridge.daemon.shell.offline import OfflineDaemon
from cellbridge.daemon.shell.service import Service
from cellbridge.daemon.shell.skin_file import load_skin
from cellbridge.emulator.mesh.skin_mesh import mesh_from_skin
from cellbridge.emulator.mesh.skin_traffic import SkinTraffic
from cellbridge.emulator.mesh.virtual import CLOCK_HZ
from cellbridge.emulator.world.world import Contact, World

from support.shell_fakes import RecordingHooks

#: A 4x4 plate read out through two gateways at opposite corners.
TWO_GATEWAYS = """name = "plate"
side = 0.04
[[link]]
name = "base"
[[patch]]
name = "p"
link = "base"
shape = "plane"
rows = 4
cols = 4
[[gateway]]
name = "a"
patch = "p"
row = 0
col = 0
[[gateway]]
name = "b"
patch = "p"
row = 3
col = 3
"""
T0 = 1_800_000_000.0  #: host time of the traffic's start


def _traffic(tmp_path: Path, frames: int) -> tuple[Any, SkinTraffic, list[tuple[float, str, bytes]], dict[int, float]]:
    """The plate pressed from 0.5 s for 0.5 s: the skin, its traffic, the reads of ``frames``
    frames in order of arrival (host times from ``T0``), and each frame's completing read's time."""
    (tmp_path / "skin.toml").write_text(TWO_GATEWAYS)
    skin = load_skin(tmp_path / "skin.toml")
    x, y = skin.atlas[skin.row_of(skin.element_id("p", 1, 1))]
    traffic = SkinTraffic(skin, World(mesh_from_skin(skin), [Contact(0.5, 0.5, x + 0.01, y, 3.0, 0.02)]))
    rate = traffic.settings.rate_hz
    reads, completed = [], {}
    for k in range(frames):
        got = sorted(traffic.frame(k))
        assert len(got) == 2 and got[1][0] - got[0][0] < 0.25 / rate  # both records within the rest
        completed[k] = T0 + got[-1][0]
        reads += [(T0 + t, f"gw{g}", data) for t, g, data in got]
    reads.sort(key=lambda r: r[0])
    return skin, traffic, reads, completed


def _config(traffic: SkinTraffic, **more: Any) -> Any:
    links = [{"name": f"gw{g}", "url": "/dev/null"} for g in traffic.gateways]
    return parse_config({"link": links, "contact": {"birth_frames": 1}, **more})


def test_the_offline_driver_estimates_every_frame_at_the_read_that_completed_it(tmp_path: Path) -> None:
    skin, traffic, reads, completed = _traffic(tmp_path, 100)
    rate = traffic.settings.rate_hz
    d = OfflineDaemon(_config(traffic), skin.layout(), surface=skin)
    lags = []
    for t, topic, m in d.run(reads, start=T0):
        if topic == "contact" and m["contacts"]:
            k = round(max(max(c["cycles"]) for c in m["contacts"]) * rate / CLOCK_HZ)  # the frame's gate start
            lags.append(t - completed[k])  # (host times near 1.8e9 s: a µs is their precision)
    assert len(lags) > 30  # the press, frame after frame
    assert max(lags) <= 1e-6, f"estimated up to {max(lags) * 1e3:.2f} ms after the frame completed"


@pytest.mark.parametrize("estimated", [False, True])
def test_the_service_s_rest_after_an_empty_look_ends_at_the_read_completing_a_frame(
        tmp_path: Path, estimated: bool) -> None:
    """The service's loop, its reads fed by hand: during a rest after a look that ran no
    estimate, the read of a frame's first record leaves it resting and the read of its last
    ends it. After an estimate, the rest is the token bucket's and no read ends it."""
    skin, traffic, reads, _ = _traffic(tmp_path, 60)
    cfg = _config(traffic, pub={"endpoint": "inproc://wake"}, control={"endpoint": "inproc://wake-ctl"})

    async def run() -> tuple[bool, bool]:
        ctx = zmq.asyncio.Context()
        svc = Service(cfg, skin.layout(), hooks=RecordingHooks(cfg), ctx=ctx, contact_executor=InlineExecutor)
        try:
            svc._bind(ctx)
            for t, link, data in reads[:-2]:  # the press is on: frames complete, each says something new
                svc._on_data(link, data, t)
            rest = asyncio.create_task(svc._rest(30.0, estimated))
            await asyncio.sleep(0.05)
            (t1, l1, d1), (t2, l2, d2) = reads[-2:]
            svc._on_data(l1, d1, t1)  # the frame's first record: nothing to look at yet
            await asyncio.sleep(0.05)
            after_first = rest.done()
            svc._on_data(l2, d2, t2)  # its last: the frame is complete
            began = time.monotonic()
            while not rest.done() and time.monotonic() - began < 1.0:
                await asyncio.sleep(0.01)
            after_last = rest.done()
            rest.cancel()
            await asyncio.gather(rest, return_exceptions=True)
            return after_first, after_last
        finally:
            svc.pub.sock.close(0)
            svc.ctl.close(0)
            svc.hooks.close()  # (its peer guard's thread, before the context ends)
            ctx.term()

    after_first, after_last = asyncio.run(run())
    assert not after_first
    assert after_last is not estimated
