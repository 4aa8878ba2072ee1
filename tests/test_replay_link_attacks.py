"""Attacks on a replay's pacing and late stamping (daemon/shell/links.py ReplayLink.run): a sleep that
ends late, a replay far behind, a recording whose times step back."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

from cellbridge.daemon.core.config import LinkConfig
from cellbridge.daemon.shell.capture import write_capture
from cellbridge.daemon.shell.links import RecordedOrder, ReplayLink


def _link(path: Path, speed: float, clock: str, on_data) -> ReplayLink:
    return ReplayLink(LinkConfig(name="gw", url=f"replay:{path}", replay_speed=speed, replay_clock=clock),
                      on_data, lambda *a: None)


def test_a_record_fed_late_after_the_replay_slept_is_stamped_when_fed(tmp_path: Path) -> None:
    """The starved loop of the commit's story, starved by ANOTHER task (a contact result, a
    tick, a big publish) while the replay sleeps towards its next record: the sleep wakes
    0.3 s late and the record is stamped with its due time, 0.3 s before the time it is fed
    and before the ticks that ran in between. Only a record whose lateness is seen before
    the sleep gets the fed-time stamp."""
    path = tmp_path / "line.cbcap"
    write_capture(path, [(1000.0 + 0.01 * i, bytes([i])) for i in range(40)])
    fed: list[tuple[float, float]] = []
    ticks: list[float] = []

    def on_data(name: str, data: bytes, now: float) -> None:
        fed.append((now, time.monotonic()))

    async def hog() -> None:
        await asyncio.sleep(0.105)  # mid-way between two records
        ticks.append(time.monotonic())
        time.sleep(0.3)  # the loop is busy elsewhere
        ticks.append(time.monotonic())  # e.g. the pipeline ticked at this time

    async def main() -> None:
        link = _link(path, 1.0, "shifted", on_data)
        await asyncio.gather(link.run(), hog())

    asyncio.run(asyncio.wait_for(main(), 10))
    worst = max(fed_at - stamp for stamp, fed_at in fed)
    first_after = next(s for s, f in fed if f > ticks[1])
    assert worst <= ReplayLink.LATE + 1e-3, \
        f"a record fed {worst * 1e3:.0f} ms after its stamp; first stamp after the hog {first_after - ticks[1]:+.3f} s vs its end"


def test_a_fast_replay_that_is_behind_lets_the_loop_run(tmp_path: Path) -> None:
    """Paced (speed > 0) but behind: every record's due time is past, the loop feeds them all
    without one await (speed 0 yields every 64 records). At a high speed, or after a long
    stall, the whole rest of the recording is fed with the loop blocked: no tick, no
    contact estimate, no control reply, no systemd watchdog (WatchdogSec=10s)."""
    path = tmp_path / "line.cbcap"
    n = 20000
    write_capture(path, [(1000.0 + 0.001 * i, bytes([i % 256])) for i in range(n)])
    spins = [0]
    fed_during: list[int] = []

    def on_data(name: str, data: bytes, now: float) -> None:
        if len(fed_during) < 1 or fed_during[-1] != spins[0]:
            fed_during.append(spins[0])
        for _ in range(200):  # a little ingest work per read
            pass

    async def other() -> None:
        while True:
            spins[0] += 1
            await asyncio.sleep(0)

    async def main() -> tuple[int, float]:
        t = asyncio.create_task(other())
        await asyncio.sleep(0)
        link = _link(path, 1e6, "shifted", on_data)  # 20 s of recording at 1e6x
        t0 = time.monotonic()
        await link.run()
        took = time.monotonic() - t0
        t.cancel()
        return spins[0], took

    s, took = asyncio.run(asyncio.wait_for(main(), 60))
    assert s > 10, f"the other task ran {s} times while the replay fed {n} records in {took:.2f} s"


def test_a_recording_that_steps_back_is_not_counted_late(tmp_path: Path) -> None:
    """A recording whose times step back 0.3 s (two captures appended, a wall-clock step in a
    foreign recording): every later record's due time is in the past, so each is fed at
    once (a 0.3 s burst) and counted in replay_late, on a machine that was never late."""
    path = tmp_path / "line.cbcap"
    times = [1000.0 + 0.01 * i for i in range(40)] + [1000.1 + 0.01 * i for i in range(40)]
    write_capture(path, [(t, bytes([i % 256])) for i, t in enumerate(times)])
    fed: list[tuple[float, float]] = []
    link = _link(path, 1.0, "shifted", lambda n, d, now: fed.append((now, time.monotonic())))
    asyncio.run(asyncio.wait_for(link.run(), 10))
    stamps = [s for s, _ in fed]
    assert all(b >= a for a, b in zip(stamps, stamps[1:]))
    st: dict[str, Any] = link.stats()
    # (a busy machine may wake a sleep late: that is late, and under a full test run on two
    # cores it was 0.107 s once; the step counted late would be ~0.3 s: 0.2 tells them apart)
    assert st["replay_late_max"] < 0.2, f"{st['replay_late']} records counted late (max {st['replay_late_max']:.3f} s)"


# -- things that should hold -------------------------------------------------------------------

def test_stamps_never_go_back_or_run_ahead_when_paced(tmp_path: Path) -> None:
    path = tmp_path / "line.cbcap"
    times = [1000.0 + 0.002 * i for i in range(200)]
    times[50] = times[49]  # a duplicate
    times[120:125] = [times[119]] * 5
    write_capture(path, [(t, bytes([i % 256])) for i, t in enumerate(times)])
    for speed in (0.5, 1.0, 7.0, 1e9):
        fed: list[tuple[float, float]] = []

        def on_data(name: str, data: bytes, now: float, fed: list[tuple[float, float]] = fed) -> None:
            fed.append((now, time.monotonic()))
            if len(fed) % 37 == 0:
                time.sleep(0.02)

        link = _link(path, speed, "shifted", on_data)
        asyncio.run(asyncio.wait_for(link.run(), 20))
        stamps = [s for s, _ in fed]
        assert all(b >= a for a, b in zip(stamps, stamps[1:])), speed
        assert all(s <= f + 1e-6 for s, f in fed), speed  # never ahead of the clock when fed


def _two_links(tmp_path: Path, speed: float, records: dict[str, list[tuple[float, bytes]]],
               fed: list[tuple[str, float]]) -> list[ReplayLink]:
    """Replay links of one service in recorded time, one capture each, sharing one order."""
    order = RecordedOrder(list(records))
    links = []
    for name, recs in records.items():
        path = tmp_path / f"{name}.cbcap"
        write_capture(path, recs)
        cfg = LinkConfig(name=name, url=f"replay:{path}", replay_speed=speed, replay_clock="recorded")
        links.append(ReplayLink(cfg, lambda n, d, t: fed.append((n, t)), lambda *a: None, order=order))
    return links


def test_replays_in_recorded_time_flat_out_feed_one_time_order_across_links(tmp_path: Path) -> None:
    """Flat out, each link fed 64 records before letting the other run: a busy line's 64
    records cover less recorded time than a quiet one's, so the quiet link ran ahead, the
    service's recorded clock with it, and the busy line's bridges looked silent (on a long
    recording, forgotten) while their reads were still to come."""
    busy = [(1000.0 + 0.001 * i, b"a") for i in range(600)]  # 1000 reads a second
    quiet = [(1000.0 + 0.01 * i, b"b") for i in range(60)]  # 100 reads a second
    fed: list[tuple[str, float]] = []

    async def run() -> None:
        await asyncio.gather(*(ln.run() for ln in _two_links(tmp_path, 0.0, {"busy": busy, "quiet": quiet}, fed)))

    asyncio.run(run())
    assert len(fed) == 660
    times = [t for _, t in fed]
    worst = max(a - b for a, b in zip(times, times[1:], strict=False))
    assert worst <= 0.0, f"recorded time stepped back {worst:.3f} s between links"


def test_replays_in_recorded_time_are_paced_from_one_origin(tmp_path: Path) -> None:
    """A gateway that came up 0.3 s after the other: its first record is due 0.3 s after
    the other's first (paced each from its own first record, both started at once and the
    later line's times ran ahead of the earlier one's, by however long it came up later)."""
    early = [(1000.0 + 0.02 * i, b"e") for i in range(10)]  # over by 0.18 s
    late = [(1000.3 + 0.02 * i, b"l") for i in range(5)]
    fed: list[tuple[str, float]] = []

    async def run() -> None:
        await asyncio.gather(*(ln.run() for ln in _two_links(tmp_path, 1.0, {"early": early, "late": late}, fed)))

    started = time.monotonic()
    asyncio.run(run())
    times = [t for _, t in fed]
    assert times == sorted(times), "fed out of recorded order"
    assert time.monotonic() - started >= 0.3 + 0.08, "the later line's records were not paced from the origin"


def test_a_recording_that_steps_back_is_paced_on_from_the_step(tmp_path: Path) -> None:
    """Two captures appended, the second made earlier (a day's, here 0.5 s): paced on the
    recording's newest time, every record after the step was behind it and the whole
    second capture was fed at once, a day's recording in a burst."""
    path = tmp_path / "line.cbcap"
    times = [1000.0 + 0.01 * i for i in range(40)] + [999.5 + 0.01 * i for i in range(40)]
    write_capture(path, [(t, bytes([i % 256])) for i, t in enumerate(times)])
    for clock in ("recorded", "shifted"):
        fed: list[tuple[float, float]] = []
        link = _link(path, 1.0, clock, lambda n, d, now, fed=fed: fed.append((now, time.monotonic())))
        asyncio.run(asyncio.wait_for(link.run(), 10))
        second = [w for _, w in fed[40:]]
        assert second[-1] - second[0] >= 0.38, (clock, second[-1] - second[0])  # its 0.39 s, paced
