"""A relay's copy filter (protocol/copies.py): copies by time, never by a numbering window."""

from __future__ import annotations

import pytest
from cellbridge.protocol.copies import RecentFrames


def test_a_copy_within_max_age_is_told_with_its_first_hop_count() -> None:
    r = RecentFrames(max_age=100)
    assert r.first(7, 3, 2, now=0) is None  # new: forward it
    assert r.first(7, 3, 5, now=50) == 2  # a copy (three hops more: round a loop)
    assert r.first(8, 3, 1, now=50) is None  # another origin's number 3 is another frame
    assert r.first(7, 3, 2, now=101) is None  # too old to be a copy: goes on (the host judges it)
    assert r.copies == 1


def test_a_new_boot_is_not_mistaken_for_the_last_whatever_its_numbers() -> None:
    # The old boot's numbers 0..199 passed; the new boot's 1, 2, ... come by another path
    # (its HELLO went elsewhere) a second later: a numbering window dropped them all.
    r = RecentFrames(max_age=50)
    for s in range(200):
        assert r.first(4, s, 1, now=s // 10) is None
    assert all(r.first(4, s, 2, now=100 + s) is None for s in range(1, 150))


def test_a_hello_with_a_new_boot_counter_clears_its_origin() -> None:
    r = RecentFrames(max_age=1000)
    assert r.first(4, 0, 0, now=0, boot=1) is None
    for s in range(1, 10):
        r.first(4, s, 0, now=s)
    r.first(5, 1, 0, now=10)
    assert r.first(4, 0, 0, now=20, boot=1) == 0  # a copy of the same boot's HELLO
    assert r.first(4, 0, 0, now=21, boot=2) is None  # a restart seen soon after the boot
    assert r.first(4, 1, 0, now=22) is None and r.boots == 1
    assert r.first(5, 1, 0, now=23) == 0  # other origins keep their memory


def test_memory_is_bounded_and_forgetting_is_counted() -> None:
    r = RecentFrames(max_age=10**9, capacity=16)
    for s in range(100):
        r.first(1, s, 0, now=s)
    assert len(r) == 16 and r.forgotten == 84
    r.remember(1, 99, 4, now=100)
    assert r.first(1, 99, 9, now=101) == 4
    with pytest.raises(ValueError):
        RecentFrames(max_age=0)
