"""The real-time medium's carrier sense for transmissions it hears of late."""

from __future__ import annotations

from cellbridge.emulator.medium.carrier_arbiter import HOLD, CarrierArbiter
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, Latency, VirtualMesh
from hypothesis import given
from hypothesis import strategies as st

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


def test_a_start_within_carrier_detection_of_an_early_handed_one_still_collides() -> None:
    # A bridge hands a transmission due within microseconds over early, stamped with its
    # start (process_bridge's EARLY): the medium admits it at its stamp, before that tick.
    # Another bridge's transmission, started on the wire within carrier detection of that
    # stamp, heard after it: the two collide on the wire, and must here (it waited for the
    # first instead, as if the chip's carrier sense had seen a start not yet made).
    a = CarrierArbiter(BIT)
    assert a.admit((1,), sent=10_000, now=10_000, airtime=10_000) == 10_000  # heard at 9 950
    assert a.admit((1,), sent=10_000 - CCA + 1, now=9_960, airtime=10_000) == 9_960
    # stamped early too, within CCA after it: collides as well
    assert a.admit((1,), sent=10_000 + CCA - 1, now=10_000 + CCA - 1, airtime=10_000) == 10_000 + CCA - 1
    assert a.counters["deferred"] == 0
    # one started a carrier detection or more after the early one's stamp still waits for it
    b = CarrierArbiter(BIT)
    b.admit((1,), sent=10_000, now=10_000, airtime=10_000)
    assert b.admit((1,), sent=10_000 + CCA, now=10_000 + CCA, airtime=1000) == 20_000 + DIFS


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
    mesh = meshgen.grid(4, 4, gateways=(1,))
    quiet = Latency(up=0.0001, down=0.0001, floor=0.00005, wake_late=0.0001, seed=1)  # a quiet machine
    vm = VirtualMesh(mesh, seed=0, latency=quiet, ack_slack=CLOCK_HZ // 100, readout=False)  # every DATA sample
    r = vm.run(6.0)
    lo, hi = 3.0, 5.0
    for b, ss in r.samples().items():
        got = sum(1 for s in ss if lo * CLOCK_HZ <= vm.nodes[b].crystal.tick_at(s.cycle) < hi * CLOCK_HZ)
        assert got >= 0.999 * 100 * (hi - lo), (b, got)
    assert r.total("queue_drops") == 0 and r.medium["deferred"] > 0


# Acknowledgements keep their place (a frame asking for one reserves its sender's cells).
GUARD = 200_000  # 4 ms
S, D, X = 1, 2, 3  # sender, its addressee (acks), a third bridge


def _frame_to_d(a: CarrierArbiter) -> int:
    """S sends a frame asking D for an ack on cell 1, from 0 to 10 000; its end."""
    assert a.admit((1,), sent=0, now=0, airtime=10_000, src=S, acker=D) == 0
    return 10_000


def test_after_a_frame_that_asks_for_an_ack_what_would_reach_its_sender_waits_for_the_ack() -> None:
    a = CarrierArbiter(BIT, ack_guard=GUARD)
    end = _frame_to_d(a)
    # X (on S's cell 1) started on the wire after the frame and after the ack: its carrier
    # sense saw the cell free, but the ack has not reached the medium yet
    assert a.admit((1, 7), sent=end + DIFS, now=end + 500, airtime=3000, src=X) == HOLD
    assert a.next_release() == end + GUARD
    # S itself, sending again (a beacon) while its ack is still to come here: held too
    assert a.admit((1,), sent=end + 900, now=end + 1000, airtime=3000, src=S) == HOLD
    # the ack comes 2 ms late: it is never held, and starts at once
    ack_at = end + 100_000
    assert a.admit((5, 1), sent=end + 600, now=ack_at, airtime=1000, src=D, ack_for=S) == ack_at
    assert a.next_release() is None
    # held ones, admitted again, start once the ack is over (they came after it on the wire)
    assert a.admit((1, 7), sent=end + DIFS, now=ack_at + 10, airtime=3000, src=X) == ack_at + 1000 + DIFS
    assert a.counters["held_for_ack"] == 2


def test_what_cannot_reach_the_waiting_sender_is_not_held() -> None:
    a = CarrierArbiter(BIT, ack_guard=GUARD)
    end = _frame_to_d(a)
    assert a.admit((9,), sent=end + DIFS, now=end + 500, airtime=3000, src=X) == end + 500
    # and the acker's own frames are not held for its own ack
    assert a.admit((5,), sent=end + DIFS, now=end + 600, airtime=3000, src=D) == end + 600


def test_a_hold_ends_without_its_ack_after_the_guard_or_when_the_frame_did_not_arrive() -> None:
    a = CarrierArbiter(BIT, ack_guard=GUARD)
    end = _frame_to_d(a)
    assert a.admit((1,), sent=end + DIFS, now=end + 500, airtime=3000, src=X) == HOLD
    assert a.admit((1,), sent=end + DIFS, now=end + GUARD, airtime=3000, src=X) == end + GUARD
    assert a.counters["ack_holds_expired"] == 1
    b = CarrierArbiter(BIT, ack_guard=GUARD)
    end = _frame_to_d(b)
    assert b.admit((1,), sent=end + DIFS, now=end + 500, airtime=3000, src=X) == HOLD
    b.no_ack(S, D)  # the frame collided at D: no ack will come
    assert b.next_release() is None
    assert b.admit((1,), sent=end + DIFS, now=end + 600, airtime=3000, src=X) == end + 600


def test_without_a_guard_nothing_is_held() -> None:
    a = CarrierArbiter(BIT)
    end = _frame_to_d(a)
    assert a.admit((1,), sent=end + DIFS, now=end + 500, airtime=3000, src=X) == end + 500


@given(st.lists(st.tuples(st.integers(1, 4), st.integers(1, 3), st.integers(0, 30_000), st.integers(0, 3),
                          st.integers(500, 12_000)), min_size=1, max_size=60))
def test_an_admitted_ack_is_never_overlapped_by_what_reaches_its_waiting_sender_after_it(
        txs: list[tuple[int, int, int, int, int]]) -> None:
    # bridges 1..4 on cells {b, b+1}; each transmission is a frame to a neighbour asking for
    # an ack (kind 0), an ack to the last bridge that asked this one (kind 1), or plain
    # (kinds 2, 3). Whatever else was admitted to reach a waiting sender once its ack is on
    # air starts after that ack ends; holds end at the latest at the guard.
    a = CarrierArbiter(BIT, ack_guard=GUARD)
    now = 0
    asked: dict[int, int] = {}  # acker -> the sender that asked it
    acks_on_air: dict[int, tuple[int, int, frozenset[int], int]] = {}  # waiter -> (start, end, cells, acker)
    latest = 0  # the latest end admitted
    held: list[tuple[tuple[int, ...], int, int, int]] = []
    # waiter -> (acker, end of its hold) of its latest admitted frame asking for an ack: only
    # that one's ack is waited for (a newer frame's replaces an older one's; a late ack, past
    # the hold, answers nobody waiting)
    waits: dict[int, tuple[int, int]] = {}
    for src, peer, gap, kind, air in txs:
        now += gap
        cells = (src, src + 1)
        ack_for = acker = -1
        if kind == 0:
            acker = 1 + (src + peer - 1) % 4
            if acker == src:
                continue
            asked[acker] = src
        elif kind == 1 and src in asked:
            ack_for = asked.pop(src)
        todo = held + [(cells, src, ack_for, acker)]
        held = []
        for c, s, af, ak in todo:
            start = a.admit(c, sent=now - 50, now=now, airtime=air, src=s, ack_for=af, acker=ak)
            if start == HOLD:
                assert af < 0  # acks are never held
                held.append((c, s, af, ak))
                continue
            assert start >= now
            latest = max(latest, start + air)
            if ak >= 0:
                waits[s] = (ak, start + air + GUARD)
            if af >= 0:
                w = waits.get(af)
                if w is not None and w[0] == s and now < w[1]:
                    del waits[af]
                    acks_on_air[af] = (start, start + air, frozenset((af, af + 1)), s)
            else:
                for waiter, (s0, e0, wcells, answering) in acks_on_air.items():
                    if s not in (waiter, answering) and not wcells.isdisjoint(c) and s0 <= now < e0:
                        assert start >= e0
        release = a.next_release()
        assert release is None or release <= latest + GUARD


def test_a_sender_hidden_from_the_acker_starts_after_the_ack_not_during_it() -> None:
    # S is on cells 1 and 5, D on 5 and 6, X on 1 only: X does not hear D's ack, but S
    # would hear both at once (a collision at S, on the wire only if X started during it)
    a = CarrierArbiter(BIT, ack_guard=GUARD)
    assert a.admit((1, 5), sent=0, now=0, airtime=10_000, src=S, acker=D) == 0
    ack_at = 60_000
    assert a.admit((5, 6), sent=10_600, now=ack_at, airtime=1000, src=D, ack_for=S) == ack_at
    # X, started after the ack on the wire, reaches the medium while the ack is on air
    assert a.admit((1,), sent=12_000, now=ack_at + 200, airtime=3000, src=X) == ack_at + 1000
    assert a.counters["after_ack"] == 1
    # once the ack is over nothing waits
    assert a.admit((1,), sent=70_000, now=ack_at + 20_000, airtime=3000, src=X) == ack_at + 20_000
