"""Capture files survive what a robot's daemon meets: a path it cannot open, a restart."""

from __future__ import annotations

import asyncio
import functools
import subprocess
from pathlib import Path

from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.shell.capture import CaptureWriter, read_capture
from cellbridge.daemon.shell.links import SerialLink

from daemon_harness import CLI, Client, Pty, daemon, write_config
from support.shell_fakes import FakeClock, FakeDevice, until


def test_a_restart_keeps_the_previous_capture(tmp_path: Path) -> None:
    """The file used to be opened "wb": the first session's records were gone."""
    path = tmp_path / "gw.cap"
    for session in range(3):
        w = CaptureWriter(path)
        w.write(float(session), b"session %d" % session)
        w.close()
    assert list(read_capture(path)) == [(2.0, b"session 2")]
    kept = sorted(tmp_path.glob("gw.cap.*"))
    assert [p.name for p in kept] == ["gw.cap.1", "gw.cap.2"]
    assert list(read_capture(kept[0])) == [(0.0, b"session 0")]
    assert list(read_capture(kept[1])) == [(1.0, b"session 1")]


def test_an_empty_or_special_file_is_not_rotated(tmp_path: Path) -> None:
    (tmp_path / "empty.cap").write_bytes(b"")
    CaptureWriter(tmp_path / "empty.cap").close()
    assert not list(tmp_path.glob("empty.cap.*"))
    w = CaptureWriter("/dev/null")  # a device is written to as it is
    w.write(0.0, b"x")
    w.close()
    assert w.error == "" and w.records == 1


def test_an_unopenable_capture_is_an_error_in_stats_not_an_exception(tmp_path: Path) -> None:
    w = CaptureWriter(tmp_path / "no" / "such" / "dir" / "gw.cap")
    w.write(0.0, b"abc")
    w.close()
    assert "no/such/dir/gw.cap" in w.error and w.records == 0 and w.dropped == 1


def test_check_names_the_capture_path_it_cannot_write(tmp_path: Path) -> None:
    cfg = tmp_path / "daemon.toml"
    write_config(cfg, [{"name": "gw", "url": "/dev/ttyUSB0", "capture": "/no/such/dir/gw.cap"}])
    out = subprocess.run([CLI, "daemon", "--config", str(cfg), "--check"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2, out.stdout
    assert "link[0].capture" in out.stderr and "/no/such/dir" in out.stderr


def test_an_unopenable_capture_costs_the_capture_not_the_link(tmp_path: Path) -> None:
    """Under Restart=on-failure this was a crash loop; now health names the capture's error
    and the line is read."""
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link, "capture": str(tmp_path / "gone" / "gw.cap")}],
                             contact={"enabled": False})
    client = Client(endpoints, (b"health",))
    try:
        with daemon(cfg, tmp_path / "stderr.log") as proc:
            h = client.wait_for("health", lambda m: m["links"]["gw"]["connected"], timeout=20.0)
            assert "gone/gw.cap" in h["links"]["gw"]["capture_error"]
            assert proc.poll() is None
    finally:
        client.close()
        pty.close()


def test_a_wall_clock_step_does_not_enter_a_capture(tmp_path: Path) -> None:
    """A capture is replayed in recorded time as the pipeline's one time base. It kept each
    read's wall-clock time, so NTP stepping the clock back 60 s mid-capture made the replay
    step back too: every bridge's clock 'restarted' and no contact was estimated for the
    rest of the press (forward 700 s: every bridge silent, a held press re-baselined). The
    capture's times are wall-clock time at its start, then the monotonic clock's."""
    async def scenario() -> None:
        dev, clock = FakeDevice(), FakeClock()
        cfg = parse_config({"link": [{"name": "gw", "url": "/dev/ttyFAKE0",
                                      "capture": str(tmp_path / "gw.cbcap")}]}).links[0]
        got = bytearray()
        link = SerialLink(cfg, lambda name, data, t: got.extend(data), lambda *a: None, dev.open, clock)
        task = asyncio.create_task(link.run())
        try:
            await until(lambda: dev.port is not None)
            for k, (step, data) in enumerate([(0.0, b"\x00one\x00"), (-60.0, b"two\x00"), (760.0, b"three\x00")]):
                clock.wall_offset += step
                clock.t += 0.5
                dev.send(data)
                want = sum(map(len, (b"\x00one\x00", b"two\x00", b"three\x00")[:k + 1]))
                await until(functools.partial(lambda n: len(got) == n, want))
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    start = FakeClock().t
    asyncio.run(scenario())
    times = [t for t, _ in read_capture(tmp_path / "gw.cbcap")]
    assert times == [start + 0.5, start + 1.0, start + 1.5]
