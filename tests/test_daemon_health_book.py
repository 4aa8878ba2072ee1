"""The health book's account of bridges the readout records speak for (daemon/core/health.py):
folded in when health is read, the newest record's time and link each, every sample counted."""

from __future__ import annotations

from cellbridge.daemon.core.health import HealthBook


def test_records_spoken_for_fold_into_each_bridges_newest_time_link_and_sample_count() -> None:
    hb = HealthBook(50e6, [("a", "/dev/a"), ("b", "/dev/b")])
    hb.spoken_for("a", [7, 2], [3], 1)  # (an int time: a time, as every other)
    hb.spoken_for("b", [2], [7], 2.0)  # a later record on another line: 2 sampled again
    hb.spoken_for("a", [9], [], 1.5)  # out of order between links: that record's own time
    assert hb.bridges == {}  # nothing per record: folded when health is read
    hb.fold()
    got = {b: (h.last_seen, type(h.last_seen), h.link, h.samples, h.first_seen) for b, h in hb.bridges.items()}
    assert got == {2: (2.0, float, "b", 2, 2.0), 3: (1.0, float, "a", 0, 1.0), 7: (2.0, float, "b", 1, 2.0),
                   9: (1.5, float, "a", 1, 1.5)}
    assert list(hb.bridges) == [2, 3, 7, 9]  # first seen in id order, as a fold has always made them
    hb.spoken_for("a", [3], [], 0.5)  # older than what the book has: counted, the time kept
    hb.fold()
    assert (hb.bridges[3].last_seen, hb.bridges[3].link, hb.bridges[3].samples) == (1.0, "a", 1)
    hb.fold()  # nothing new: nothing moves
    assert hb.bridges[3].samples == 1
