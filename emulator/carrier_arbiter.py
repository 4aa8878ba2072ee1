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
:class:`~cellbridge.emulator.medium.Medium`'s, unchanged. Virtual time without latency
never needs it (carrier reports arrive at once). Sans-I/O: ticks in, ticks out.
"""

from __future__ import annotations

from collections import Counter


class CarrierArbiter:
    """When the medium should start each transmission it hears of (``admit``)."""

    def __init__(self, bit_cycles: int, cca_bits: int = 4, difs_bits: int = 40) -> None:
        self.cca = cca_bits * bit_cycles
        self.difs = difs_bits * bit_cycles
        #: cell -> (sender's start tick, medium start, end) of the latest transmission admitted on it
        self._on: dict[int, tuple[int, int, int]] = {}
        self.counters: Counter[str] = Counter()

    def admit(self, cells: tuple[int, ...], sent: int, now: int, airtime: int) -> int:
        """The tick (``now`` or later) at which the medium starts a transmission of
        ``airtime`` cycles on ``cells`` that its sender started at ``sent`` and the medium
        heard of at ``now``. Call it in arrival order, once per transmission."""
        on = self._on
        busy_until = -1
        collides = False
        for c in cells:
            x = on.get(c)
            if x is not None and x[2] > now:
                if x[1] <= now and abs(sent - x[0]) < self.cca:
                    collides = True  # started together on the wire: a real collision
                busy_until = max(busy_until, x[2])
        start = now
        if busy_until > now and not collides:
            start = busy_until + self.difs
            self.counters["deferred"] += 1
            self.counters["deferred_cycles"] += start - now
        end = start + airtime
        for c in cells:
            x = on.get(c)
            if x is None or x[2] < end:
                on[c] = (sent, start, end)
        return start
