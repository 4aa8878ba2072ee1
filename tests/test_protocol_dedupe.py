"""Duplicate filter: agrees with a plain reference model, wraps, restarts, stays bounded."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from cellbridge.protocol import DuplicateFilter


class Reference:
    """Same semantics, written the obvious way: remember every seq within the window."""

    def __init__(self, window: int) -> None:
        self.window = window
        self.highest: dict[int, int] = {}
        self.seen: dict[int, set[int]] = {}

    def is_duplicate(self, origin: int, seq: int) -> bool:
        if origin not in self.highest:
            self.highest[origin], self.seen[origin] = seq, {seq}
            return False
        h = self.highest[origin]
        ahead = (seq - h) % 65536
        if 0 < ahead < 32768:
            self.highest[origin] = seq
            self.seen[origin] = {s for s in self.seen[origin] | {seq} if (seq - s) % 65536 < self.window}
            return False
        behind = (h - seq) % 65536
        if behind >= self.window:
            self.highest[origin], self.seen[origin] = seq, {seq}
            return False
        if seq in self.seen[origin]:
            return True
        self.seen[origin].add(seq)
        return False


@settings(max_examples=200)
@given(window=st.integers(1, 64), start=st.integers(0, 65535),
       steps=st.lists(st.tuples(st.integers(0, 2), st.integers(-80, 80)), max_size=200))
def test_matches_reference(window, start, steps) -> None:
    f, ref = DuplicateFilter(window=window), Reference(window)
    for origin, delta in steps:
        seq = (start + delta) % 65536
        start = seq if delta > 0 else start
        assert f.is_duplicate(origin, seq) == ref.is_duplicate(origin, seq)


def test_wraparound_and_restart() -> None:
    f = DuplicateFilter(window=16)
    for seq in (65530, 65535, 0, 3):
        assert not f.is_duplicate(1, seq)
    assert f.is_duplicate(1, 65535) and f.is_duplicate(1, 0)
    assert not f.is_duplicate(1, 2)  # inside the window, never seen
    assert not f.is_duplicate(1, 40000)  # far behind: a reset bridge numbering again
    assert f.restarts == 1
    assert f.duplicates == 2


def test_origins_are_bounded() -> None:
    f = DuplicateFilter(window=8, max_origins=100)
    for origin in range(10_000):
        f.is_duplicate(origin, 1)
    assert len(f) == 100 and f.evicted_origins == 9_900
