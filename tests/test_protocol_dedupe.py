"""Duplicate filter: agrees with a plain reference model, wraps, restarts only on evidence, stays bounded."""

from __future__ import annotations

import random

from hypothesis import event, given, settings
from hypothesis import strategies as st

from cellbridge.protocol import DuplicateFilter

MOD = 65536


class Reference:
    """The rules of docs/protocol.md §7 written the obvious way: sets of numbers, lists of runs."""

    def __init__(self, window: int, restart_run: int, hello_guard: int) -> None:
        self.window, self.restart_run, self.hello_guard = window, restart_run, hello_guard
        self.highest: dict[int, int] = {}
        self.seen: dict[int, set[int]] = {}
        self.hello: dict[int, int | None] = {}
        self.run: dict[int, list[int]] = {}

    def _start(self, origin: int, seq: int, seen: set[int], hello: int | None) -> None:
        self.highest[origin], self.seen[origin], self.hello[origin], self.run[origin] = seq, seen, hello, []

    def _trim(self, origin: int) -> None:
        h = self.highest[origin]
        self.seen[origin] = {s for s in self.seen[origin] if (h - s) % MOD < self.window}

    def is_duplicate(self, origin: int, seq: int, hello: bool = False) -> bool:
        if origin not in self.highest:
            self._start(origin, seq, {seq}, seq if hello else None)
            return False
        h = self.highest[origin]
        if 0 < (seq - h) % MOD < 32768:
            self.highest[origin] = seq
            self.seen[origin].add(seq)
            self._trim(origin)
            self.run[origin] = []
            if hello:
                self.hello[origin] = seq
            return False
        inside = (h - seq) % MOD < self.window
        if inside and seq not in self.seen[origin]:
            self.seen[origin].add(seq)
            self.run[origin] = []
            if hello:
                self.hello[origin] = seq
            return False
        if hello and not (self.hello[origin] == seq and (h - seq) % MOD < self.hello_guard):
            self._start(origin, seq, {seq}, seq)
            return False
        if not inside:  # stale
            run = self.run[origin]
            if run and 0 < (seq - run[-1]) % MOD <= 4:
                run.append(seq)
                if len(run) >= self.restart_run:
                    self._start(origin, seq, set(run), None)
                    self._trim(origin)
                    return False
                return True
            if run and seq in run:
                return True
            self.run[origin] = [seq] if seq < self.window else []
            return True
        return True  # seen


@settings(max_examples=300)
@given(window=st.integers(8, 64), restart_run=st.integers(2, 8), hello_guard=st.integers(0, 8),
       start=st.integers(0, 65535),
       steps=st.lists(st.tuples(st.integers(0, 2), st.integers(-80, 80), st.booleans()), max_size=200))
def test_matches_reference(window, restart_run, hello_guard, start, steps) -> None:
    f = DuplicateFilter(window=window, restart_run=restart_run, hello_guard=hello_guard)
    ref = Reference(window, restart_run, hello_guard)
    for origin, delta, is_hello in steps:
        seq = (start + delta) % MOD
        start = seq if delta > 0 else start
        hello = is_hello and delta % 7 == 0
        assert f.is_duplicate(origin, seq, hello) == ref.is_duplicate(origin, seq, hello)


@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 1500), lag=st.integers(0, 600), jitter=st.integers(0, 3),
       wrap=st.booleans(), data=st.data(), seed=st.integers(0, 2**32 - 1))
def test_two_delayed_copies_deliver_each_frame_once(n, lag, jitter, wrap, data, seed) -> None:
    """Frame i leaves at time i; copy A arrives after 0..jitter, copy B after lag..lag+jitter.

    While B's lag stays inside the window every frame is delivered exactly once; once it
    is beyond the window B's copies are stale: counted, never delivered, never a restart.
    The sequence starts anywhere, so it wraps at 65536 as often as not. The bridge keeps
    sending while B catches up (A alone carries frames n.. until B's last copy is in):
    a path that goes silent while the other replays low numbers is a restart's evidence.
    """
    # Half the sequences cross 65535 -> 0 somewhere inside them.
    start = 65536 - data.draw(st.integers(1, n)) if wrap else data.draw(st.integers(0, 65535 - n))
    rng = random.Random(seed)
    window = 256
    # B's copy of i meets A's highest number at least lag - jitter - 1 ahead (A's copy of
    # i + lag - jitter may tie with it in time and come second), at most lag + jitter.
    event(f"lag {'within' if lag + jitter < window else 'beyond' if lag - jitter > window else 'at'} the window")
    event(f"wraps: {start + n > MOD}")
    events = []
    for i in range(n + lag + jitter + 1):
        events.append((i + rng.randint(0, jitter), rng.random(), i))
        if i < n:
            events.append((i + lag + rng.randint(0, jitter), rng.random(), i))
    events.sort()
    f = DuplicateFilter(window=window)
    delivered = [i for _, _, i in events if not f.is_duplicate(3, (start + i) % MOD)]
    delivered = [i for i in delivered if i < n]
    c = f.counters()
    assert c["restarts"] == 0
    if lag + jitter < window:  # every copy of B meets its number inside the window
        assert sorted(delivered) == list(range(n))
        assert c["stale"] == 0 and c["duplicates"] == n
    elif lag - jitter > window:  # every copy of B is stale
        assert sorted(delivered) == list(range(n))
        assert c["stale"] == n and c["duplicates"] == 0
    else:  # in between: still never twice, and every drop is counted
        assert len(delivered) == len(set(delivered)) and set(delivered) == set(range(n))
        assert c["stale"] + c["duplicates"] == n


def test_wraparound_and_stale() -> None:
    f = DuplicateFilter(window=16)
    for seq in (65530, 65535, 0, 3):
        assert not f.is_duplicate(1, seq)
    assert f.is_duplicate(1, 65535) and f.is_duplicate(1, 0)
    assert not f.is_duplicate(1, 2)  # inside the window, never seen
    assert f.is_duplicate(1, 40000)  # far behind: stale, not a restart
    assert f.counters() == {"origins": 1, "duplicates": 2, "stale": 1, "restarts": 0, "evicted_origins": 0}


def test_restart_from_a_run_of_low_numbers_without_hello() -> None:
    f = DuplicateFilter(restart_run=8)
    assert not any(f.is_duplicate(1, s) for s in range(1000, 2000))
    # The bridge reset and its HELLO was lost: it numbers 1, 2, 3, ... again (one frame lost).
    out = [f.is_duplicate(1, s) for s in (1, 2, 3, 5, 6, 7, 8, 9, 10, 11)]
    assert out == [True] * 7 + [False] * 3
    assert f.counters()["restarts"] == 1 and f.counters()["stale"] == 7
    assert f.is_duplicate(1, 10) and not f.is_duplicate(1, 4)  # a new window around the new numbering


def test_a_run_of_high_stale_numbers_is_no_restart() -> None:
    f = DuplicateFilter()
    assert not any(f.is_duplicate(1, s) for s in range(5000, 6000))
    assert all(f.is_duplicate(1, s) for s in range(4000, 4500))  # a path that lags 1000 frames
    assert f.counters()["restarts"] == 0 and f.counters()["stale"] == 500


def test_a_hello_heard_through_two_gateways_is_one_restart() -> None:
    f = DuplicateFilter(hello_guard=16)
    assert not any(f.is_duplicate(1, s) for s in range(100))
    got = [f.is_duplicate(1, 0, hello=True), f.is_duplicate(1, 1), f.is_duplicate(1, 2),
           f.is_duplicate(1, 0, hello=True), f.is_duplicate(1, 1), f.is_duplicate(1, 2)]
    assert got == [False, False, False, True, True, True]
    assert f.counters()["restarts"] == 1


def test_a_reordered_hello_is_no_restart() -> None:
    f = DuplicateFilter()
    assert not any(f.is_duplicate(1, s) for s in range(100))
    # HELLO 100 (sent on request) arrives after 101 and 102, then every copy arrives again
    assert [f.is_duplicate(1, s, hello=s == 100) for s in (101, 102, 100)] == [False] * 3
    assert all(f.is_duplicate(1, s, hello=s == 100) for s in (100, 101, 102))
    assert f.counters()["restarts"] == 0


def test_origins_are_bounded() -> None:
    f = DuplicateFilter(window=8, max_origins=100)
    for origin in range(10_000):
        f.is_duplicate(origin, 1)
    assert len(f) == 100 and f.evicted_origins == 9_900
