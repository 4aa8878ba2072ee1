"""The real-time medium's carrier sense for transmissions it hears of late."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from cellbridge.emulator import meshgen
from cellbridge.emulator.carrier_arbiter import CarrierArbiter
from cellbridge.emulator.virtual import CLOCK_HZ, Latency, VirtualMesh

BIT = 50  # cycles per bit at 1 Mbit/s
CCA, DIFS = 4 * BIT, 40 * BIT


def test_a_free_cell_starts_at_once_and_a_late_heard_start_waits_for_the_cell() -> None:
    a = CarrierArbiter(BIT)
    assert a.admit((1,), sent=1000, now=5000, airtime=10_000) == 5000
    # started (by its sender) well after the first one: its carrier sense would have held it
    assert a.admit((1, 2), sent=3000, now=6000, airtime=4000) == 15_000 + DIFS
    # and a third behind the second, in arrival order (the cell's reservations queue up)
    assert a.admit((2,), sent=6500, now=7000, airtime=1000) == 15_000 + DIFS + 4000 + DIFS
    assert a.counters["deferred"] == 2
    # another cell is not held back
    assert a.admit((3,), sent=7000, now=7100, airtime=1000) == 7100


def test_starts_within_carrier_detection_still_collide() -> None:
    a = CarrierArbiter(BIT)
    assert a.admit((1,), sent=1000, now=5000, airtime=10_000) == 5000
    assert a.admit((1,), sent=1000 + CCA - 1, now=5200, airtime=10_000) == 5200  # on the wire together
    assert a.counters["deferred"] == 0


@given(st.lists(st.tuples(st.integers(1, 3), st.integers(0, 10**6), st.integers(1, 5000)), min_size=1, max_size=40))
def test_never_before_it_was_heard_and_deferred_ones_never_overlap(txs: list[tuple[int, int, int]]) -> None:
    a = CarrierArbiter(BIT)
    now = 0
    spans: dict[int, list[tuple[int, int]]] = {}
    for cell, gap, air in txs:
        now += gap
        start = a.admit((cell,), sent=now - 100, now=now, airtime=air)
        assert start >= now
        if start > now:  # deferred: after everything admitted before on that cell
            assert all(start >= end for _, end in spans.get(cell, []))
        spans.setdefault(cell, []).append((start, start + air))


def test_a_4x4_skin_under_real_time_latency_delivers_every_sample() -> None:
    # Without the arbiter (and short timers slept exactly) the latency model's 4x4 at
    # 100 Hz lost two thirds of some bridges' samples in queues; with them, none.
    mesh = meshgen.grid(4, 4)
    quiet = Latency(up=0.0001, down=0.0001, floor=0.00005, wake_late=0.0001, seed=1)  # a quiet machine
    vm = VirtualMesh(mesh, seed=0, latency=quiet, ack_slack=CLOCK_HZ // 100)
    r = vm.run(6.0)
    lo, hi = 3.0, 5.0
    for b, ss in r.samples().items():
        got = sum(1 for s in ss if lo * CLOCK_HZ <= vm.nodes[b].crystal.tick_at(s.cycle) < hi * CLOCK_HZ)
        assert got >= 0.999 * 100 * (hi - lo), (b, got)
    assert r.total("queue_drops") == 0 and r.medium["deferred"] > 0
