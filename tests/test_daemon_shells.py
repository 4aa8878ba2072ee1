"""The daemon's shells in-process, on fakes: a serial device unplugged and replugged, a
clock that moves only when a link waits, a contact worker that hangs, and a whole
service bound to ``inproc://`` endpoints — reconnect and backoff, SIGHUP reload,
drain on SIGTERM, a hung worker, a control timeout, in milliseconds each. And the two
sans-I/O cores joined in memory: the virtual mesh's gateway bytes, at their virtual
times, through ``Pipeline.feed``. (Real ptys and processes: test_daemon_service.py.)
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import os
import signal
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import msgpack
import pytest
import zmq
import zmq.asyncio
from cellbridge.daemon.core.config import load_config, parse_config
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.daemon.shell.contact_worker import ContactWorker, InlineExecutor
from cellbridge.daemon.shell.links import SerialLink
from cellbridge.daemon.shell.replay_source import read_records
from cellbridge.daemon.shell.service import Service

from cellbridge.recording import codec
from cellbridge.recording.mcapfile import RecordingWriter
from cellbridge.recording.recorder import Recorder
from daemon_traffic import GridFrames
from support.pipeline_helpers import published, worker
from support.shell_fakes import FakeClock, FakeDevice, RecordingHooks, ScriptedExecutor, until

STRADDLE = (0.020, 0.006, 3.0, 0.012)  # on the seam of bridges 1 and 2


def _link_config(**kw: Any) -> Any:
    return parse_config({"link": [{"name": "gw", "url": "/dev/ttyFAKE0", **kw}]}).links[0]


# -- links ----------------------------------------------------------------------------------


def test_a_link_reads_byte_by_byte_and_reconnects_with_backoff_reset_after_an_open() -> None:
    async def scenario() -> None:
        dev, clock = FakeDevice(chunk=1), FakeClock()
        got = bytearray()
        states: list[tuple[bool, str]] = []
        link = SerialLink(_link_config(reconnect_min=0.1, reconnect_max=1.6),
                          lambda name, data, t: got.extend(data), lambda name, up, why: states.append((up, why)),
                          dev.open, clock)
        task = asyncio.create_task(link.run())
        try:
            await until(lambda: states == [(True, "")])
            dev.send(b"\x00hello\x00")
            await until(lambda: bytes(got) == b"\x00hello\x00")
            assert dev.port is not None and dev.port.reads == [1] * 7  # one byte a read
            dev.unplug()
            await until(lambda: len(clock.sleeps) >= 8)
            assert states[1] == (False, "device lost: device disconnected")
            assert "open failed" in states[2][1]
            # after the loss, then after each failed open: doubling, capped at reconnect_max
            assert clock.sleeps[:8] == [0.1, 0.1, 0.2, 0.4, 0.8, 1.6, 1.6, 1.6]
            dev.replug()
            await until(lambda: states[-1] == (True, ""))
            assert dev.opens == 2
            dev.send(b"again")
            await until(lambda: bytes(got).endswith(b"again"))
            assert link.write(b"\x00cmd\x00") and bytes(dev.written) == b"\x00cmd\x00"
            n = len(clock.sleeps)
            dev.unplug()
            await until(lambda: len(clock.sleeps) >= n + 2)
            assert clock.sleeps[n:n + 2] == [0.1, 0.1]  # an open succeeded: back to reconnect_min
            assert not link.write(b"lost") and link.stats()["writes_dropped"] == 1
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        assert dev.port is not None and dev.port.closed

    asyncio.run(scenario())


def test_bytes_lost_on_the_line_cost_frames_that_are_counted_and_the_rest_is_decoded() -> None:
    async def scenario(seed: int) -> tuple[int, int, dict[str, Any]]:
        sk = GridFrames()
        dev = FakeDevice(chunk=7, loss=0.002, seed=seed)
        p = Pipeline(parse_config({"link": [{"name": "gw", "url": "/dev/ttyFAKE0"}]}))
        elements = [0]

        def on_data(name: str, data: bytes, t: float) -> None:
            for topic, m in published(p.feed(name, data, t)):
                if topic == "element":
                    elements[0] += len(m["bridge"])

        link = SerialLink(_link_config(), on_data, lambda *a: p.link_state(a[0], a[1], 0.0, a[2]), dev.open,
                          FakeClock())
        task = asyncio.create_task(link.run())
        await until(lambda: dev.port is not None)
        total = 0
        for data in [sk.hellos() + sk.beacons()] + [d for _, d in sk.stream(300)]:
            dev.send(data)
            total += len(data)
            await asyncio.sleep(0)
        await until(lambda: p.health_body(0.0)["links"]["gw"]["bytes"] + dev.lost >= total)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        return elements[0], dev.lost, p.health_body(0.0)["links"]["gw"]

    samples, lost, health = asyncio.run(scenario(1))
    assert lost > 0 and 0 < samples < 300 * 4  # each lost byte costs at most its frame
    assert health["framing_errors"] + health["crc_errors"] > 0
    assert health["connected"]
    assert asyncio.run(scenario(1))[:2] == (samples, lost)  # deterministic by seed


# -- the contact worker ---------------------------------------------------------------------


def _job(p: Pipeline) -> Any:
    sk = GridFrames()
    p.feed("gw", sk.hellos() + sk.beacons(), 1000.0)
    for k, data in sk.stream(80):
        p.feed("gw", data, 1000.0 + k / sk.rate)
    for k, data in sk.stream(20, STRADDLE, start=80):
        p.feed("gw", data, 1000.0 + k / sk.rate)
    job = p.contact_job()
    assert job is not None
    return job


def test_a_hung_contact_worker_is_killed_and_a_new_one_answers() -> None:
    async def scenario() -> None:
        make = ScriptedExecutor.factory(answers=1)
        w = ContactWorker(logging.getLogger("tests"), make)
        p = Pipeline(parse_config({"link": [{"name": "gw", "url": "/dev/null"}], "calibration": {"n_baseline": 5}}))
        job = _job(p)
        assert await w.estimate(job, timeout=0.05) is not None  # answered: the worker is warm
        assert await w.estimate(job, timeout=0.05) is None  # hangs past its timeout
        assert w.stats["errors"] == 1 and w.stats["worker_restarts"] == 1
        assert ScriptedExecutor.made[0].killed and len(ScriptedExecutor.made) == 2
        assert await w.estimate(job, timeout=0.05) is not None  # the new worker answers
        w.close()

    asyncio.run(scenario())


class _HeldExecutor(concurrent.futures.Executor):
    """Hands out futures the test completes (a worker whose answer comes when the test says)."""

    def __init__(self) -> None:
        self.futures: list[concurrent.futures.Future[Any]] = []

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
        fut.set_running_or_notify_cancel()
        self.futures.append(fut)
        return fut


def test_an_estimate_cancelled_the_step_after_its_answer_came_is_cancelled() -> None:
    """Python 3.11's wait_for returns a result that came in the loop step before its task
    was cancelled, and the cancel is lost: an estimate cancelled by a stop right after its
    answer returned the answer, and the service's contact loop went on. Whichever step after
    the answer the cancel comes in, the estimate ends cancelled."""
    async def scenario() -> None:
        p = Pipeline(parse_config({"link": [{"name": "gw", "url": "/dev/null"}], "calibration": {"n_baseline": 5}}))
        job = _job(p)
        ex = _HeldExecutor()
        w = ContactWorker(logging.getLogger("tests"), lambda: ex)
        w._answered = True  # a warm worker: its estimates have their timeout
        lost = []
        for steps in range(6):
            task = asyncio.create_task(w.estimate(job, timeout=30.0))
            await until(lambda n=steps + 1: len(ex.futures) == n)  # type: ignore[misc]  # (bound now)
            ex.futures[-1].set_result([])
            for _ in range(steps):
                await asyncio.sleep(0)
            asked = task.cancel()  # (False: the estimate had returned already)
            with contextlib.suppress(asyncio.CancelledError):
                await task
            if asked and not task.cancelled():
                lost.append(steps)
        assert not lost, f"the cancel was lost {lost} steps after the answer"

    asyncio.run(scenario())


def test_the_inline_executor_runs_the_production_contact_path() -> None:
    p = Pipeline(parse_config({"link": [{"name": "gw", "url": "/dev/null"}], "calibration": {"n_baseline": 5}}))
    job = _job(p)
    w = ContactWorker(logging.getLogger("tests"), InlineExecutor)
    for _ in range(3):  # born after three estimates
        contacts = w.estimate_now(job)
    (c,) = p.contact_frame(job, contacts).payload["contacts"]
    assert sorted(c["elements"]) == [1, 2] and c["force"] == pytest.approx(3.0, rel=0.02)
    assert w.stats["runs"] == 3


# -- the whole service, in-process --------------------------------------------------------------

_N = [0]


def _write_config(path: Path, **sections: dict[str, Any]) -> None:
    base: dict[str, dict[str, Any]] = {
        "pub": {"endpoint": f"inproc://pub-{_N[0]}"}, "control": {"endpoint": f"inproc://control-{_N[0]}"},
        "health": {"interval": 0.1}, "calibration": {"n_baseline": 5}, "daemon": {"log_level": "warning"}}
    for name, values in sections.items():
        base.setdefault(name, {}).update(values)
    lines = []
    for name, values in base.items():
        lines.append(f"[{name}]")
        lines += [f"{k} = {v!r}".replace("'", '"') for k, v in values.items()]
    lines += ["[[link]]", 'name = "gw"', 'url = "/dev/ttyFAKE0"']
    path.write_text("\n".join(lines).replace("True", "true").replace("False", "false") + "\n")


@asynccontextmanager
async def running(tmp_path: Path, dev: FakeDevice, **kw: Any) -> AsyncIterator[tuple[Service, zmq.asyncio.Context]]:
    """A service on inproc endpoints and ``dev``; stopped (SIGTERM) on exit if still running."""
    _N[0] += 1
    path = tmp_path / "daemon.toml"
    if not path.exists():
        _write_config(path)
    cfg = load_config(path)
    ctx = zmq.asyncio.Context()
    hooks = RecordingHooks(cfg)
    kw.setdefault("contact_executor", InlineExecutor)  # no worker process to spawn and warm up
    svc = Service(cfg, config_path=path, hooks=hooks, ctx=ctx, opener=dev.open, **kw)
    task = asyncio.create_task(svc.run())
    try:
        await until(lambda: any(what == "ready" for what, _ in hooks.said) or task.done())
        assert not task.done(), "the service did not start"
        await until(lambda: dev.port is not None)  # the link opened its device (bytes before that are lost)
        svc.task = task  # type: ignore[attr-defined]  # the test keeps the service's task on it
        yield svc, ctx
    finally:
        if not task.done():
            os.kill(os.getpid(), signal.SIGTERM)
        if not task.cancelled():  # (a test may have cancelled it)
            await asyncio.wait_for(task, 20.0)  # a guard against a hang
        ctx.destroy(linger=0)


def _sub(ctx: zmq.asyncio.Context, svc: Service, *topics: str) -> zmq.asyncio.Socket:
    s = ctx.socket(zmq.SUB)
    for t in topics:
        s.setsockopt(zmq.SUBSCRIBE, t.encode())
    s.connect(svc.config.pub.endpoint)
    return s


async def _recv(sock: zmq.asyncio.Socket) -> tuple[str, dict[str, Any]]:
    topic, payload = await asyncio.wait_for(sock.recv_multipart(), 5.0)
    return topic.decode(), msgpack.unpackb(payload)


def test_sighup_reloads_the_config_and_sigterm_drains_to_a_last_health(tmp_path: Path) -> None:
    async def scenario() -> None:
        dev = FakeDevice()
        sk = GridFrames()
        async with running(tmp_path, dev) as (svc, ctx):
            health = _sub(ctx, svc, "health")
            await until(lambda: "health" in svc.pub.wanted)
            dev.send(sk.hellos() + sk.beacons())
            for _, data in sk.stream(20):
                dev.send(data)
            _write_config(tmp_path / "daemon.toml", health={"interval": 0.25})
            os.kill(os.getpid(), signal.SIGHUP)
            hooks: RecordingHooks = svc.hooks  # type: ignore[assignment]  # the test passed RecordingHooks
            await until(lambda: ("ready", "reloaded") in hooks.said)
            assert svc.config.health.interval == 0.25
            await until(lambda: svc.pipeline.health_body(0.0)["bridges"].get("4", {}).get("samples", 0) == 20)
            os.kill(os.getpid(), signal.SIGTERM)
            assert await asyncio.wait_for(svc.task, 20.0) == 0  # type: ignore[attr-defined]  # the test keeps the service's task on it
            assert ("stopping", "") in hooks.said
            assert dev.port is not None and dev.port.closed
            last = None
            while await health.poll(0):
                last = await _recv(health)
            assert last is not None and last[0] == "health"
            assert last[1]["bridges"]["4"]["samples"] == 20  # the drain's health saw everything read
            health.close(0)

    asyncio.run(scenario())


def test_a_wall_clock_step_does_not_enter_the_reads_a_recording_replays(tmp_path: Path) -> None:
    """``cellbridge record --serial`` keeps the ``serial`` topic and a ``replay:FILE.mcap``
    link re-runs the pipeline on its times. They were wall-clock times: replayed across an
    NTP step back, every bridge's clock 'restarted' and no contact came for the rest of the
    press. ``t_read`` is the read's arrival on a clock that never steps; ``t_host`` follows
    the wall clock, as every published stamp does."""
    async def scenario() -> None:
        dev, clock = FakeDevice(), FakeClock()
        async with running(tmp_path, dev, clock=clock) as (svc, ctx):
            sub = _sub(ctx, svc, "serial")
            await until(lambda: "serial" in svc.pub.wanted)
            got = []
            for step, data in ((0.0, b"\x00one\x00"), (-60.0, b"\x00two\x00"), (700.0, b"\x00three\x00")):
                clock.wall_offset += step
                clock.t += 0.5
                await until(lambda: svc.pipeline.wall_offset == clock.wall_offset)  # a tick saw the step
                dev.send(data)
                got.append((await _recv(sub))[1])
            sub.close(0)
        assert [m["t_read"] - got[0]["t_read"] for m in got] == [0.0, 0.5, 1.0]
        assert [m["t_host"] - m["t_read"] for m in got] == [0.0, -60.0, 640.0]
        rec = Recorder(tmp_path / "s.mcap", RecordingWriter)
        for m in got:
            rec.feed("serial", codec.to_msgpack(m), m["t_host"])
        rec.close()
        assert [t for t, _ in read_records(tmp_path / "s.mcap", "gw")] == [m["t_read"] for m in got]

    asyncio.run(scenario())


def test_a_control_command_to_a_bridge_that_never_answers_times_out(tmp_path: Path) -> None:
    async def scenario() -> None:
        dev = FakeDevice()
        sk = GridFrames()
        async with running(tmp_path, dev) as (svc, ctx):
            dev.send(sk.hellos())
            await until(lambda: "2" in svc.pipeline.health_body(0.0)["bridges"])
            ctl = ctx.socket(zmq.DEALER)
            ctl.connect(svc.config.control.endpoint)
            await ctl.send_multipart([b"", msgpack.packb({"v": 1, "cmd": "ping", "bridge": 2, "timeout": 0.05,
                                                         "id": 7})])
            frames = await asyncio.wait_for(ctl.recv_multipart(), 5.0)
            rep = msgpack.unpackb(frames[-1])
            assert rep["ok"] is False and rep["id"] == 7 and rep["missing"] == [2]
            assert "no reply within the timeout" in rep["error"]
            assert dev.written  # the PING went out on the line
            ctl.close(0)

    asyncio.run(scenario())


def test_control_replies_stamp_wall_clock_time(tmp_path: Path) -> None:
    """``ping`` and ``status`` answer with ``t_host``, epoch seconds like every published
    stamp. They answered with the pipeline's time base, the monotonic clock (seconds since
    boot on a robot), and a wall-clock step did not move it."""
    async def scenario() -> None:
        dev, clock = FakeDevice(), FakeClock(t=1000.0)
        clock.wall_offset = 1_700_000_000.0
        async with running(tmp_path, dev, clock=clock) as (svc, ctx):
            ctl = ctx.socket(zmq.DEALER)
            ctl.connect(svc.config.control.endpoint)
            for step in (0.0, -60.0):
                clock.wall_offset += step
                await until(lambda: svc.pipeline.wall_offset == clock.wall_offset)  # a tick saw the step
                for i, cmd in enumerate(("ping", "status")):
                    await ctl.send_multipart([b"", msgpack.packb({"v": 1, "cmd": cmd, "id": i})])
                    rep = msgpack.unpackb((await asyncio.wait_for(ctl.recv_multipart(), 5.0))[-1])
                    assert rep["ok"] and rep["t_host"] == pytest.approx(clock.wall(), abs=1.0), (cmd, rep["t_host"])
            ctl.close(0)

    asyncio.run(scenario())


async def _press_until_an_estimate_hangs(dev: FakeDevice, sk: GridFrames) -> None:
    """Stream the skin's slots (a press across a seam from the 31st) until the service's
    ScriptedExecutor holds a hung estimate (at most 60 s: a guard, not a speed check)."""
    dev.send(sk.hellos() + sk.beacons())
    k = 0
    end = asyncio.get_running_loop().time() + 60.0
    while not (ScriptedExecutor.made and ScriptedExecutor.made[0].hung):
        assert asyncio.get_running_loop().time() < end, f"no hung estimate after {k} slots"
        for _, data in sk.stream(1, STRADDLE if k > 30 else None, start=k):
            dev.send(data)
        k += 1
        await asyncio.sleep(0.002)


def test_sigterm_with_a_hung_contact_worker_stops_within_the_drain_limit(tmp_path: Path) -> None:
    """The worker answers two estimates, then hangs in the third. SIGTERM must neither
    wait out ``worker_timeout`` (30 s here, the default; systemd kills at 15) nor start a
    replacement worker on the way out, and the hung one is killed."""

    async def scenario() -> None:
        dev = FakeDevice()
        sk = GridFrames()
        make = ScriptedExecutor.factory(answers=2)
        async with running(tmp_path, dev, contact_executor=make, drain_limit=0.5) as (svc, ctx):
            contacts = _sub(ctx, svc, "contact", "health")
            await until(lambda: "contact" in svc.pub.wanted)
            await _press_until_an_estimate_hangs(dev, sk)
            os.kill(os.getpid(), signal.SIGTERM)
            assert await asyncio.wait_for(svc.task, 20.0) == 0  # type: ignore[attr-defined]  # the test keeps the service's task on it
            assert len(ScriptedExecutor.made) == 1  # no replacement started during shutdown
            assert ScriptedExecutor.made[0].killed
            topics = []
            while await contacts.poll(0):
                topics.append((await _recv(contacts))[0])
            assert topics and topics[-1] == "health"  # the last health still went out
            contacts.close(0)

    asyncio.run(scenario())


# -- the two sans-I/O cores, joined ---------------------------------------------------------------


def _virtual_press(seed: int) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    from cellbridge.emulator.mesh import meshgen
    from cellbridge.emulator.mesh.virtual import VirtualMesh
    from cellbridge.emulator.world.world import Contact, World

    mesh = meshgen.grid(2, 2)
    vm = VirtualMesh(mesh, seed=seed, world=World(mesh, [Contact(2.0, 1.0, 0.02, 0.0, 3.0, 0.012)]))
    p = Pipeline(parse_config({"link": [{"name": "gw", "url": "/dev/null"}]}))
    w = worker()
    elements, contacts = [], []
    sent, step, t0 = 0, 0.005, 1_700_000_000.0
    for i in range(1, 701):  # 3.5 s of virtual time, the gateway's bytes every 5 ms
        vm.run(step)
        data = bytes(vm.serial[1][sent:])
        sent += len(data)
        if data:
            elements += [m for topic, m in published(p.feed("gw", data, t0 + i * step)) if topic == "element"]
        job = p.contact_job()
        if job is not None:
            contacts += p.contact_frame(job, w.estimate_now(job)).payload["contacts"]
    return elements, contacts


def test_the_virtual_mesh_feeds_the_pipeline_deterministically_by_seed() -> None:
    elements, contacts = _virtual_press(3)
    assert {b for m in elements for b in m["bridge"]} == {1, 2, 3, 4}
    touched = {b for m in elements for b, t in zip(m["bridge"], m["touched"]) if t}
    assert touched == {1, 2}
    held = [c for c in contacts if c["missed"] == 0]
    assert held and {c["id"] for c in contacts} == {0}
    for c in held:
        assert sorted(c["elements"]) == [1, 2]
        assert c["x"] == pytest.approx(0.02, abs=1e-3) and c["force"] == pytest.approx(3.0, rel=0.05)
    again = _virtual_press(3)
    assert repr(again) == repr((elements, contacts))  # (repr: NaN equals NaN)
    assert repr(_virtual_press(4)[0]) != repr(elements)  # another seed, other noise


def test_a_flood_of_reads_that_move_no_frame_costs_few_contact_looks(tmp_path: Path) -> None:
    """``[contact] rate`` bounds estimates; a look that finds no new frame was followed by
    the next read's look at once: a serial line read in small pieces (a USB adapter's 32-byte
    chunks; the daemon at 20 % CPU on an emulated 4x4 skin) cost a skin-frame computation per
    read (246 looks a second against 69, 9 % of a core against 2.5 %). After such a look the
    next waits for data and at least a quarter of the estimate period, or until the frame is
    due. A count, not a speed: a slower run gives fewer looks and a larger bound."""
    async def scenario() -> None:
        _write_config(tmp_path / "daemon.toml", contact={"rate": 4.0})  # an estimate period of 0.25 s
        dev = FakeDevice()
        async with running(tmp_path, dev) as (svc, _ctx):
            looks = [0]
            job = svc.pipeline.contact_job

            def counted(now: float | None = None) -> Any:
                looks[0] += 1
                return job(now)

            svc.pipeline.contact_job = counted  # type: ignore[method-assign]  # counts the real method's calls
            loop = asyncio.get_running_loop()
            await asyncio.sleep(0.3)  # the start's looks are over
            start, looks[0], reads = loop.time(), 0, svc._n_reads
            for _ in range(300):
                dev.send(b"\x01\x02")  # a read that completes no frame
                await asyncio.sleep(0.001)
            await until(lambda: svc._n_reads >= reads + 300)
            elapsed = loop.time() - start
            gap = 0.25 / svc.config.contact.rate
            # a look per gap at most, plus the tick's ten a second (each a read's look's chance)
            assert looks[0] <= elapsed / gap + elapsed / svc.TICK + 3, (looks[0], elapsed)

    asyncio.run(scenario())


def test_a_finished_replay_waits_for_the_contact_workers_warm_up(tmp_path: Path, warm_kernels: None) -> None:
    """The worker's warm-up (on a fresh installation: compiling the kernels, about 20 s)
    outlasts the golden capture's replay. The daemon stopped as soon as the replay ended,
    gave the pending estimate a share of ``drain_limit`` and published no contact at all."""
    from support.golden_corpus import paths, published_diff
    from support.golden_corpus import scenario as corpus_scenario
    from support.shell_fakes import SlowStartExecutor

    sc = corpus_scenario("daemon_press")
    capture = paths(sc)[0]
    config = capture.with_suffix(".toml")

    async def scenario() -> None:
        path = tmp_path / "replay.toml"
        path.write_text('[pub]\nendpoint = "inproc://replay-pub"\n[control]\nendpoint = "inproc://replay-ctl"\n'
                        + config.read_text().replace("replay:daemon_press.cbcap", f"replay:{capture}"))
        cfg = load_config(path)
        ctx = zmq.asyncio.Context()
        svc = Service(cfg, config_path=path, hooks=RecordingHooks(cfg), ctx=ctx,
                      contact_executor=SlowStartExecutor.factory(1.5), drain_limit=0.5)
        task = asyncio.create_task(svc.run())
        await until(lambda: hasattr(svc, "pub") or task.done())
        sub = _sub(ctx, svc, "element", "contact")
        assert await asyncio.wait_for(task, 30.0) == 0
        messages = []
        while await sub.poll(0):
            messages.append(await _recv(sub))
        sub.close(0)
        ctx.destroy(linger=0)
        diffs = published_diff(sc, messages)
        assert not diffs, diffs[:10]

    asyncio.run(scenario())


def test_a_drain_cancelled_midway_still_closes_the_sockets_and_ends_the_worker(tmp_path: Path) -> None:
    """The service's task cancelled while it drains (an embedding program's timeout, a test's
    wait_for): the sockets, the ops hooks and the worker process were left open (a later
    term() of the context hung on them)."""

    async def scenario() -> None:
        dev = FakeDevice()
        sk = GridFrames()
        make = ScriptedExecutor.factory(answers=2)
        async with running(tmp_path, dev, contact_executor=make, drain_limit=10.0) as (svc, ctx):
            contacts = _sub(ctx, svc, "contact")
            await until(lambda: "contact" in svc.pub.wanted)
            await _press_until_an_estimate_hangs(dev, sk)
            task = svc.task  # type: ignore[attr-defined]
            svc._stop.set()  # the drain now waits up to 5 s for the hung estimate
            await until(lambda: any(w == "stopping" for w, _ in svc.hooks.said))  # type: ignore[attr-defined]
            await asyncio.sleep(0.2)
            assert not task.done()
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.wait_for(task, 5.0)
            assert svc.pub.sock.closed and svc.ctl.closed
            assert ScriptedExecutor.made[0].killed
            contacts.close(0)

    asyncio.run(scenario())


def test_the_contact_loop_ends_when_cancelled_the_step_after_data_came(tmp_path: Path) -> None:
    """The daemon once hung at a stop (its log said "stopping: draining", never "stopped")
    with an event-based skin and views subscribed: the contact loop then waits for new data
    or for held elements' next look (wait_for on its event), and Python 3.11's wait_for,
    cancelled in the step after the event was set (a tick sets it ten times a second),
    returns instead of raising: the cancel was lost, the loop went on, and the drain
    waited for it for ever. Whichever step the cancel comes in, the loop ends."""
    async def scenario() -> None:
        cfg = parse_config({"link": [{"name": "gw", "url": "/dev/ttyFAKE0"}], "daemon": {"log_level": "warning"}})
        svc = Service(cfg, hooks=RecordingHooks(cfg), contact_executor=InlineExecutor)
        svc.pipeline.contact_due = lambda now, idle=False: now + 0.05  # type: ignore[method-assign]  # a look due soon
        went_on = []
        for steps in range(6):
            task = asyncio.create_task(svc._contacts())
            await asyncio.sleep(0.01)  # in its wait for data or the look
            svc._fresh.set()
            for _ in range(steps):
                await asyncio.sleep(0)
            task.cancel()
            done, _ = await asyncio.wait([task], timeout=1.0)
            if not done:
                went_on.append(steps)
                while not task.done():  # (cancelled until it ends: the test must not leave it)
                    task.cancel()
                    await asyncio.wait([task], timeout=0.1)
        assert not went_on, f"the contact loop went on after a cancel {went_on} steps after data came"

    asyncio.run(scenario())


def test_a_stop_is_bounded_when_a_task_does_not_end_when_cancelled(tmp_path: Path) -> None:
    """The drain waited for its tasks with gather, without a bound: one task that did not
    end on its cancel (the contact loop's lost cancel, above) held the daemon at "stopping:
    draining" until it was killed. A task that outlives ``TASK_END_LIMIT`` is logged and
    left; the drain goes on, publishes its last health, and the service stops."""
    async def scenario() -> None:
        dev = FakeDevice()
        release = asyncio.Event()

        async def stubborn() -> None:
            while not release.is_set():
                with contextlib.suppress(asyncio.CancelledError):
                    await asyncio.sleep(1.0)

        left = asyncio.create_task(stubborn(), name="stubborn")
        try:
            async with running(tmp_path, dev, drain_limit=5.0) as (svc, ctx):
                try:
                    health = _sub(ctx, svc, "health")
                    await until(lambda: "health" in svc.pub.wanted)
                    svc._tasks.append(left)
                    t0 = time.monotonic()
                    os.kill(os.getpid(), signal.SIGTERM)
                    async with asyncio.timeout(15.0):  # a guard against the hang
                        assert await asyncio.shield(svc.task) == 0  # type: ignore[attr-defined]  # the test keeps the service's task on it
                    assert time.monotonic() - t0 < 5.0
                    assert svc.pub.sock.closed and svc.ctl.closed and not left.done()
                    topics = []
                    while await health.poll(0):
                        topics.append((await _recv(health))[0])
                    assert topics and topics[-1] == "health"  # the drain's last health went out
                    health.close(0)
                finally:
                    release.set()  # (a hung drain then ends: the test fails, it does not hang)
        finally:
            release.set()
            left.cancel()
            await asyncio.wait([left], timeout=2.0)

    asyncio.run(scenario())


_LEFT_OPEN = """
import asyncio, os, signal, sys
import zmq
sys.path.insert(0, {tests!r})
from cellbridge.daemon.core.config import load_config
from cellbridge.daemon.shell.contact_worker import InlineExecutor
from cellbridge.daemon.shell.service import Service
from support.shell_fakes import FakeDevice, RecordingHooks


class Hooks(RecordingHooks):
    def secure(self, ctx, socket, endpoint):
        super().secure(ctx, socket, endpoint)
        self.left = zmq.Context.shadow(ctx.underlying).socket(zmq.PAIR)  # a helper's, never closed


async def main():
    cfg = load_config({config!r})
    dev = FakeDevice()
    svc = Service(cfg, hooks=Hooks(cfg), opener=dev.open, contact_executor=InlineExecutor)  # its own context
    task = asyncio.create_task(svc.run())
    while not any(what == "ready" for what, _ in svc.hooks.said):
        await asyncio.sleep(0.01)
    os.kill(os.getpid(), signal.SIGTERM)
    print("returned", await task, flush=True)

asyncio.run(main())
"""


def test_a_socket_left_open_in_the_services_context_does_not_hold_its_stop(tmp_path: Path) -> None:
    """``term()`` of the service's ZeroMQ context waits for every socket of it to be closed,
    without a bound: a helper thread's socket left open (its thread did not end in its
    time) held the daemon after its drain. A separate process: the old stop hung in it."""
    import subprocess
    import sys

    _N[0] += 1
    config = tmp_path / "daemon.toml"
    _write_config(config, daemon={"log_level": "info"})
    script = _LEFT_OPEN.format(tests=str(Path(__file__).parent), config=str(config))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"the stop hung: {err.decode()[-400:]}")
    assert proc.returncode == 0 and b"returned 0" in out, err
    assert b"ZeroMQ context did not terminate" in err and b"stopped" in err, err


def test_a_shifted_replay_that_falls_behind_never_feeds_a_read_before_the_time_it_is_fed(tmp_path: Path) -> None:
    """A shifted replay at recorded speed on a starved loop (here a read that holds it for
    0.3 s): the records due meanwhile are fed late. Stamped on their schedule they came
    0.3 s before the time the pipeline's looks and ticks had already run at, and a daemon
    re-run on a recording took its baselines from other readings than the recorded run's
    (9 fF apart). Now they are stamped when fed, counted, and the replay is back on its
    schedule after them, as a line is after the kernel held its bytes.

    In fake time (the link's clock), so that what is late is the test's choice and not the
    machine's: on the wall clock a busy machine made other records late too (a record due
    at 30 ms fed 6 ms late). Each sleep ends 3 ms late, within ``LATE``: on schedule."""
    from cellbridge.daemon.core.config import LinkConfig
    from cellbridge.daemon.shell.capture import write_capture
    from cellbridge.daemon.shell.links import ReplayLink

    class LateWaking(FakeClock):
        async def sleep(self, seconds: float) -> None:
            await super().sleep(seconds + 0.003)

    path = tmp_path / "line.cbcap"
    write_capture(path, [(1000.0 + 0.01 * i, bytes([i])) for i in range(60)])
    clock = LateWaking(100.0)
    fed: list[tuple[float, float]] = []  # (stamp, the link's time when fed)

    def on_data(name: str, data: bytes, now: float) -> None:
        fed.append((now, clock.time()))
        if data == bytes([20]):
            clock.t += 0.3  # this read held the loop for 0.3 s

    link = ReplayLink(LinkConfig(name="gw", url=f"replay:{path}", replay_speed=1.0, replay_clock="shifted"),
                      on_data, lambda *a: None, clock=clock)
    asyncio.run(asyncio.wait_for(link.run(), 30))
    assert len(fed) == 60
    assert all(stamp >= fed_at - ReplayLink.LATE for stamp, fed_at in fed), \
        max(fed_at - stamp for stamp, fed_at in fed)
    stamps = [s for s, _ in fed]
    assert all(b >= a for a, b in zip(stamps, stamps[1:]))
    start = stamps[0]
    on_schedule = [i for i, s in enumerate(stamps) if abs(s - start - 0.01 * i) < 1e-9]
    late = [i for i in range(60) if i not in on_schedule]
    # due before the held read ended (and the one due then, behind them): stamped when fed
    assert late == list(range(21, 51)), late
    assert all(stamps[i] == fed[i][1] for i in late)
    assert on_schedule == [*range(21), *range(51, 60)]  # back on its schedule after them
    stats = link.stats()
    assert stats["replay_late"] == 30 and stats["replay_late_max"] == pytest.approx(0.293, abs=1e-9), stats


def test_a_failing_calibration_kernel_leaves_the_numpy_step_and_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    """The calibrator's compiled step failing to compile (or load) at the start: the warm-up
    ends (the start waits no longer), a warning says that numpy steps the calibrator and why,
    and a calibrator made for the kernel steps by numpy, never calling it."""
    import threading

    import numpy as np
    from cellbridge.tactile import calibration_kernel
    from cellbridge.tactile.calibration import CalibrationConfig, Calibrator

    def broken() -> None:
        raise RuntimeError("compiling the step failed")

    monkeypatch.setattr(calibration_kernel, "warm_up", broken)
    monkeypatch.setattr(calibration_kernel, "READY", False)
    cfg = parse_config({"link": [{"name": "gw", "url": "/dev/ttyFAKE0"}], "daemon": {"log_level": "warning"}})
    svc = Service(cfg, hooks=RecordingHooks(cfg), contact_executor=InlineExecutor)
    records: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    handler = Keep()
    svc.log.addHandler(handler)
    done = threading.Event()
    try:
        svc._warm_calibration(done)
    finally:
        svc.log.removeHandler(handler)
    assert done.is_set()
    said = [r for r in records if "numpy steps the calibrator" in r.getMessage()]
    assert said and "compiling the step failed" in str(said[0].fields)  # type: ignore[attr-defined]
    cal = Calibrator(4, 2, CalibrationConfig(n_baseline=1), compiled=True)

    def never(t0: float, v: Any) -> None:
        raise AssertionError("the compiled step was called without a warm kernel")

    monkeypatch.setattr(cal, "update_compiled", never)
    for k in range(3):
        cal.update(0.01 * k, np.full((4, 2), 1e-11))
    assert cal.ready.all()
