"""Carrier sense done by a medium that hears of transmissions late (real-time meshes).

On a chip, carrier is sensed ``cca_bits`` (4 µs) after another transmission starts, so
only transmissions started within those microseconds of each other collide. Between
processes, a transmission reaches the medium process, and its carrier report reaches the
other bridges, hundreds of microseconds to milliseconds later: a bridge that starts after
the cell went busy has not been told yet. Left alone, every such start collides (and a
link acknowledgement, sent SIFS after a frame *as the receiver saw it*, reaches the medium
after the other bridges' next frames), retransmissions follow, and the cells of a 4×4 skin
at 100 Hz delivered a third of its samples, seconds late.

:class:`CarrierArbiter` gives the medium back what the chip's carrier sense would have done:
a transmission whose sender started it (its own start tick, carried in the TX message)
``cca_bits`` or more after one still on air on the same cells was a transmission that
sender's transceiver would have held back; the medium starts it DIFS after the cells are
free instead, in order of arrival (its own backoff already ran). Transmissions started
within ``cca_bits`` of each other still collide, as they do on the wire. Everything else
(loss, bit errors, collisions at a receiver on another cell, half duplex) is the
:class:`~cellbridge.emulator.medium.medium.Medium`'s, unchanged. Virtual time without latency
never needs it (carrier reports arrive at once). Sans-I/O: ticks in, ticks out.

**Acknowledgements keep their place.** On the wire a LINK_ACK goes out SIFS after the frame
it answers, before anyone else's DIFS is over, so the frame's sender hears it. Between
processes it reaches the medium a millisecond or more after the frame ended (the
receiver's process has to wake and answer), and by then other bridges, whose carrier
sense saw the cell free after the frame, are on air: at the waiting sender the ack
collided with them, or the sender was itself sending already, and it retried after its
whole ack wait. On a 4×4 skin at 100 Hz these were most of the frames lost to their
addressee (in a 15 s run: 254 acks lost against 131 data frames and bundles; 126 of the
153 acks lost to collisions collided with a transmission its sender started after the
ack had ended on the wire). So a frame that asks for an ack reserves its sender's cells
from its end (:meth:`admit` with ``acker``): a transmission that would start after that and reach
the sender (or is the sender's own) is *held* (:data:`HOLD`) until the ack is admitted,
then starts once the ack is over. The hold ends anyway ``ack_guard`` after the frame's
end (an ack that never comes: the receiver is gone or late), or when the frame turns
out not to have reached its addressee (:meth:`no_ack`). What this leaves out: a hidden
sender that on the wire would start during the ack (it does not hear the ack's sender)
and collide with it there.
"""

from __future__ import annotations

from collections import Counter
from typing import NamedTuple

HOLD = -1  #: :meth:`CarrierArbiter.admit`: not yet; admit it again once a hold is over


class _Ack(NamedTuple):
    acker: int  #: the bridge that answers
    cells: frozenset[int]  #: the waiting sender's cells (where the ack is heard)
    after: int  #: medium tick the frame ends: what starts later waits for the ack
    until: int  #: medium tick: for an ack not admitted by then, nobody waits any more


class CarrierArbiter:
    """When the medium should start each transmission it hears of (``admit``)."""

    def __init__(self, bit_cycles: int, cca_bits: int = 4, difs_bits: int = 40, ack_guard: int = 0) -> None:
        """``ack_guard``: medium ticks a transmission is held at most for an ack
        (:meth:`admit`); 0 holds nothing."""
        self.cca = cca_bits * bit_cycles
        self.difs = difs_bits * bit_cycles
        self.ack_guard = ack_guard
        #: cell -> (sender's start tick, medium start, end) of the latest transmission admitted on it
        self._on: dict[int, tuple[int, int, int]] = {}
        self._acks: dict[int, _Ack] = {}  #: waiting sender -> the ack it waits for, not yet admitted
        #: waiting sender -> (its cells, the acker, the ack's end): acks on air
        self._hearing: dict[int, tuple[frozenset[int], int, int]] = {}
        self.counters: Counter[str] = Counter()

    def no_ack(self, waiter: int, acker: int) -> None:
        """``waiter``'s frame did not reach ``acker`` (collision, loss, a bad CRC, gone): no
        ack will come, nobody waits for it."""
        a = self._acks.get(waiter)
        if a is not None and a.acker == acker:
            del self._acks[waiter]

    def next_release(self) -> int | None:
        """The medium tick the next hold ends without its ack (None: no hold); held
        transmissions should be admitted again then."""
        return min((a.until for a in self._acks.values()), default=None)

    def admit(self, cells: tuple[int, ...], sent: int, now: int, airtime: int, src: int = -1,
              ack_for: int = -1, acker: int = -1) -> int:
        """The tick (``now`` or later) at which the medium starts a transmission of
        ``airtime`` cycles on ``cells`` that ``src`` started at ``sent`` and the medium
        heard of at ``now`` (all ticks of the medium's clock), or :data:`HOLD`: it waits
        for an ack, admit it again when that ack is admitted or at :meth:`next_release`.
        Call it in arrival order, once per transmission (again for a held one).
        ``ack_for``: the bridge a LINK_ACK is addressed to (-1: not an ack); ``acker``: the
        bridge asked for a LINK_ACK by this frame (-1: none). From the frame's end until
        that ack is admitted (``ack_for=src``, from ``acker``), :meth:`no_ack`, or
        ``ack_guard`` after its end, transmissions that would start after it and reach
        ``src`` (share one of ``cells``) or are ``src``'s own are held; acks never are. A
        sender waits for one ack at a time: a newer frame's replaces it. A held
        transmission does not reserve its cells: one arriving later there that does not
        reach the waiting sender is not held, and may go first (a cell of three bridges or
        more)."""
        expected = None
        if self._acks:
            for waiter in [w for w, a in self._acks.items() if a.until <= now]:
                del self._acks[waiter]
                self.counters["ack_holds_expired"] += 1
            a = self._acks.get(ack_for)
            if a is not None and a.acker == src:
                expected = self._acks.pop(ack_for)
        start = self._start(cells, sent, now)
        if ack_for < 0 and self._acks:  # an ack goes SIFS after its frame, before anyone: never held
            for waiter, a in self._acks.items():
                if src != a.acker and start >= a.after and (src == waiter or not a.cells.isdisjoint(cells)):
                    self.counters["held_for_ack"] += 1
                    return HOLD
        if start > now:  # counted once it is admitted, not at each hold
            self.counters["deferred"] += 1
            self.counters["deferred_cycles"] += start - now
        if self._hearing and ack_for < 0:
            for waiter, (wcells, answering, end) in list(self._hearing.items()):
                if end <= now:
                    del self._hearing[waiter]
                elif src != answering and end > start and (src == waiter or not wcells.isdisjoint(cells)):
                    start = end  # it came after the ack: it starts after the ack here too
                    self.counters["after_ack"] += 1
        end = start + airtime
        if expected is not None:
            self._hearing[ack_for] = (expected.cells, src, end)
        if acker >= 0 and self.ack_guard > 0:
            self._acks[src] = _Ack(acker, frozenset(cells), end, end + self.ack_guard)
        for c in cells:
            x = self._on.get(c)
            if x is None or x[2] < end:
                self._on[c] = (sent, start, end)
        return start

    def _start(self, cells: tuple[int, ...], sent: int, now: int) -> int:
        """Carrier sense: ``now``, or DIFS after the cells are free for a transmission its
        sender's transceiver would have held back."""
        on = self._on
        busy_until = -1
        collides = False
        for c in cells:
            x = on.get(c)
            if x is not None and x[2] > now:
                # started together on the wire: a real collision. With one on air already, or
                # one starting at its own stamp (handed over early: it may start after
                # ``now``), not one deferred to after another (its stamp says nothing then)
                if abs(sent - x[0]) < self.cca and (x[1] <= now or x[1] == x[0]):
                    collides = True
                busy_until = max(busy_until, x[2])
        start = now
        if busy_until > now and not collides:
            start = busy_until + self.difs
        return start
