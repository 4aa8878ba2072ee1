"""The service's shifted replays fed by one task (links.ReplayPacer): one wake for the records
due together, each fed at or after its due time and stamped with it, in time order across
the lines; a line that ends, fails or is cancelled leaves the others going."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from cellbridge.daemon.core.config import LinkConfig
from cellbridge.daemon.shell.capture import write_capture
from cellbridge.daemon.shell.links import ReplayLink, ReplayPacer

from support.shell_fakes import FakeClock

T0 = 1000.0


def capture(tmp_path: Path, name: str, times: list[float]) -> Path:
    """A capture whose first record (empty) is at T0, then one record a time, its data the line's name."""
    path = tmp_path / f"{name}.cbcap"
    write_capture(path, [(T0, b""), *((T0 + t, name.encode()) for t in times)])
    return path


def replay(path: Path, name: str, fed: list[tuple[str, float, float]], pacer: ReplayPacer,
           clock: FakeClock | None = None, **kw: object) -> ReplayLink:
    """A replay of ``path`` on ``pacer`` noting (line, stamp, the clock's time when fed) in ``fed``."""
    def on_data(link: str, data: bytes, now: float) -> None:
        if data:
            fed.append((link, now, clock.time() if clock is not None else now))

    cfg = LinkConfig(name=name, url=f"replay:{path}", replay_speed=1.0, replay_clock="shifted")
    if clock is not None:
        kw["clock"] = clock
    return ReplayLink(cfg, on_data, lambda *a: None, pacer=pacer, **kw)  # type: ignore[arg-type]


def test_records_due_together_are_fed_at_one_wake_each_stamped_with_its_due_time(tmp_path: Path) -> None:
    clock = FakeClock(100.0)
    pacer = ReplayPacer(clock, window=0.0003)
    fed: list[tuple[str, float, float]] = []
    # three lines whose records of a frame come within 0.2 ms, a fourth 5 ms after them
    offsets = {"a": 0.0, "b": 0.0001, "c": 0.0002, "d": 0.005}
    links = [replay(capture(tmp_path, n, [0.01 + off + 0.01 * i for i in range(20)]), n, fed, pacer, clock)
             for n, off in offsets.items()]

    async def main() -> None:
        await asyncio.wait_for(asyncio.gather(*(ln.run() for ln in links)), 30)

    asyncio.run(main())
    assert len(fed) == 80
    due = {(n, round(100.0 + 0.01 + off + 0.01 * i, 9)) for n, off in offsets.items() for i in range(20)}
    assert {(n, round(stamp, 9)) for n, stamp, _ in fed} == due  # each stamped with its own due time
    assert all(0 <= at - stamp <= pacer.window + 1e-9 for _, stamp, at in fed)  # never early, at most a window late
    assert [s for _, s, _ in fed] == sorted(s for _, s, _ in fed)  # in time order across the lines
    assert pacer.wakes == 1 + 40  # the first records at once; then a, b and c at one wake, d at another, each frame
    assert all(ln.finished and ln.stats()["replay_late"] == 0 for ln in links)


def test_a_line_that_fails_or_is_cancelled_leaves_the_others_going(tmp_path: Path) -> None:
    clock = FakeClock(100.0)
    pacer = ReplayPacer(clock)
    fed: list[tuple[str, float, float]] = []
    good = replay(capture(tmp_path, "good", [0.01 * i for i in range(1, 31)]), "good", fed, pacer, clock)
    gone = replay(capture(tmp_path, "gone", [0.01 * i for i in range(1, 31)]), "gone", fed, pacer, clock)

    def raising(link: str, data: bytes, now: float) -> None:
        if len(fed) > 10:
            raise RuntimeError("a bug in the read's handling")
        fed.append((link, now, clock.time()))

    bad = ReplayLink(LinkConfig(name="bad", url=f"replay:{capture(tmp_path, 'bad', [0.01 * i for i in range(1, 31)])}",
                                replay_speed=1.0, replay_clock="shifted"), raising, lambda *a: None,
                     clock=clock, pacer=pacer)

    async def main() -> None:
        tasks = [asyncio.create_task(ln.run()) for ln in (good, gone, bad)]
        while sum(n == "gone" for n, _, _ in fed) < 5:
            await asyncio.sleep(0)
        tasks[1].cancel()
        done = await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 30)
        assert done[0] is None and isinstance(done[1], asyncio.CancelledError)
        assert isinstance(done[2], RuntimeError)
        await asyncio.sleep(0)
        assert asyncio.all_tasks() == {asyncio.current_task()}  # no pacer task left behind

    asyncio.run(main())
    assert sum(n == "good" for n, _, _ in fed) == 30 and good.finished
    assert 5 <= sum(n == "gone" for n, _, _ in fed) < 30


def test_a_line_joining_while_the_pacer_sleeps_for_later_records_is_fed_at_once(tmp_path: Path) -> None:
    """On the host's clock: a line whose gate opens while the pacer sleeps towards another
    line's record due in 30 s is fed now, not at that record's time."""
    pacer = ReplayPacer()
    fed: list[tuple[str, float, float]] = []
    first = asyncio.Event

    async def main() -> None:
        came = first()

        def on_data(link: str, data: bytes, now: float) -> None:
            if data:
                fed.append((link, now, now))
                came.set()

        slow = ReplayLink(LinkConfig(name="slow", url=f"replay:{capture(tmp_path, 'slow', [0.001, 30.0])}",
                                     replay_speed=1.0, replay_clock="shifted"), on_data, lambda *a: None, pacer=pacer)
        late = replay(capture(tmp_path, "late", [0.001, 0.002]), "late", fed, pacer, start_gate=came.wait)
        tasks = [asyncio.create_task(slow.run()), asyncio.create_task(late.run())]
        await asyncio.wait_for(tasks[1], 10)  # (30 s: the pacer slept on towards slow's record)
        assert [n for n, _, _ in fed] == ["slow", "late", "late"]
        tasks[0].cancel()
        with pytest.raises(asyncio.CancelledError):
            await tasks[0]

    asyncio.run(main())
