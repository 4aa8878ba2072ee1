"""The chip's cell transceiver: bit timing, carrier sense, random backoff (CSMA).

Sans-I/O: the owner hands it one frame at a time (``send``) with the cells to send
it on (a unicast goes on one cell shared with the next hop, a broadcast on all the
bridge's cells), tells it when the medium reports carrier on a cell (``carrier``),
and calls ``advance(tick)`` at or after ``next_tick``; ``advance`` returns the
bytes and cells of a transmission that starts at that tick. Time is in chip cycles.

The bridge has one transmitter (half duplex: it hears nothing while it sends) and a
receiver per cell. Carrier is detected ``cca_bits`` after another transmission starts,
so two bridges that start within that window collide, as on a real shared wire.

Access rule (CSMA/CA as in 802.11's distributed coordination): a data frame draws a
backoff of random slots from a contention window that doubles with each retransmission
and starts in proportion to the number of bridges sharing our cells (so a crowded cell
does not collide itself to a standstill, and a quiet one wastes no idle slots);
the backoff counts down only while the cell has been idle for DIFS, and a transmission
heard meanwhile freezes it (the slots already idle are kept). A link acknowledgement
goes out after the shorter SIFS with no backoff, so nobody else can grab the cell
between a frame and its acknowledgement.

An acknowledgement waits for a frame still arriving on another of the bridge's cells
(up to ``ack_defer``: one frame of the largest size), then goes SIFS after it. Sent at
once it would spoil that frame (half duplex): a bridge's children on different cells do
not hear each other, so a relay answering one of them while another's frame came in
lost that frame, and its sender retried after its whole ack wait. On a 4×4 skin at
100 Hz in virtual time without message latency this was nearly every loss (22 459–24 013
frames lost to half duplex in 25 s, seeds 0–2; 194–270 after), and one sample index
spread p99 42–50 ms across the bridges (24–32 ms after; ``bench/bench_latency.py
--virtual none``). Senders wait ``ack_defer`` longer for their acknowledgement
(:class:`~cellbridge.emulator.firmware.linklayer.LinkLayer`).
"""

from __future__ import annotations

import random
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from cellbridge.protocol import MAX_FRAME

PREAMBLE_BITS = 16  #: sync word before every frame on the cell
#: Acknowledgements waiting to be sent at most (frames ending together on all of a
#: bridge's cells, and a real-time bridge's wake reading several at once)
MAX_ACKS = 4
_BEACON = 2  # FrameType.BEACON, at byte 2 of a frame


@dataclass(frozen=True)
class TransceiverConfig:
    bit_cycles: int = 50  #: 1 Mbit/s at 50 MHz
    sifs_bits: int = 12  #: turnaround before an acknowledgement
    difs_bits: int = 40  #: idle time before contention starts
    slot_bits: int = 8  #: one backoff slot
    cw_min: int = 32  #: contention window (slots), first attempt
    cw_max: int = 4096
    slots_per_contender: int = 32  #: the window grows with the bridges sharing our cells
    cca_bits: int = 4  #: carrier detection delay


class Transceiver:
    """Half-duplex CSMA transmitter of one bridge (on all of its cells at once)."""

    def __init__(self, rng: random.Random, config: TransceiverConfig = TransceiverConfig()) -> None:
        self.config = config
        self._rng = rng
        self._busy: dict[int, tuple[int, int]] = {}  #: cell -> (carrier from, until)
        self.tx_until = 0  #: own transmission ends at this tick
        self._frame: bytes | None = None
        self._urgent = False  #: the pending frame is a scheduled one (no backoff, SIFS)
        self._cells: tuple[int, ...] = ()
        self._at = 0  #: planned start of the pending frame
        self._t0 = 0  #: when the backoff countdown began (cell idle for DIFS)
        self._slots = 0  #: backoff slots still to count down
        self._cw = config.cw_min
        #: acknowledgements to send, in order, as (bytes, cells, due): each was due SIFS after
        #: the frame it answers (its own deferral counts from there); the first at ``_urgent_at``
        self._acks: deque[tuple[bytes, tuple[int, ...], int]] = deque()
        self._urgent_at = 0
        #: cycles an acknowledgement waits at most for a frame arriving on another cell:
        #: one of the largest frames, and SIFS after it
        self.ack_defer = self.airtime(MAX_FRAME) + config.sifs_bits * config.bit_cycles
        self.cca_busy = 0  #: planned starts that found the cell busy and backed off again
        self.contenders = 0  #: bridges heard on our cells (set by the firmware from its neighbours)
        self.transmissions = 0
        self.bits_sent = 0
        self.acks_dropped = 0
        #: MAC-layer timestamping: called with a BEACON's bytes and the tick its
        #: transmission starts, returns the bytes to send (with the time of that instant)
        self.stamper: Callable[[bytes, int], bytes] | None = None

    def airtime(self, n_bytes: int) -> int:
        """Cycles one frame of ``n_bytes`` occupies the cell."""
        return (n_bytes * 8 + PREAMBLE_BITS) * self.config.bit_cycles

    @property
    def idle(self) -> bool:
        """No frame waiting for the cell (a new one may be handed over)."""
        return self._frame is None

    def contending(self, tick: int, horizon: int) -> bool:
        """Whether this transceiver needs to hear carrier at ``tick``: it holds a frame, other
        than a readout record (no random backoff) planned to go within ``horizon`` cycles.
        A real-time shell tells its medium only then: a carrier report takes longer than
        such a record's wait to come, and the medium starts a transmission that finds its
        cell busy when the cell is free, as carrier sense would have (so the two messages
        per record that saying "contending" cost the shell and the medium bought nothing)."""
        if self._frame is None:
            return False
        return not self._urgent or self._at - tick >= horizon

    def send(self, frame: bytes, cells: tuple[int, ...], tick: int, attempt: int = 0, urgent: bool = False,
             rank: int = 0) -> None:
        """Contend for ``cells`` with ``frame`` (the previous one must have gone out).
        ``attempt`` > 0 (a retransmission) starts with a wider contention window.
        ``urgent`` (a scheduled readout record): no random backoff but ``rank`` slots (the
        bridge's place among the neighbours that send records at the same depth: distinct
        on a shared cell, so their records follow each other instead of colliding), and it
        goes before the contending frames of its neighbours, whose backoff is random."""
        if self._frame is not None:
            raise RuntimeError("transceiver already holds a frame")
        self._frame = frame
        self._cells = cells
        self._urgent = urgent
        c = self.config
        if urgent:
            self._slots = rank
        else:
            base = max(c.cw_min, c.slots_per_contender * self.contenders)
            self._cw = min(base << min(attempt, 8), c.cw_max)
            self._slots = self._rng.randrange(self._cw)
        self._plan(tick)

    def cancel(self, frame: bytes) -> bool:
        """Withdraw ``frame`` if it still waits for the cell (its acknowledgement came
        late, after the retransmission was handed over); True when it was withdrawn."""
        if self._frame is frame:
            self._frame = None
            return True
        return False

    def send_ack(self, frame: bytes, cells: tuple[int, ...], tick: int) -> None:
        """Send an acknowledgement SIFS after ``tick`` (the end of the frame it answers).
        Two frames to acknowledge at once (on two cells, ending together; or read in one
        wake of a real-time bridge) get their ACKs one after the other, SIFS apart: the
        second once replaced the first, and that frame's sender, never acknowledged, sent
        it again after its ACK wait (nearly every retransmission of a 4x4 skin at 100 Hz).
        At most ``MAX_ACKS`` wait; one more is dropped and counted in ``acks_dropped``
        (its sender retries, as after a lost ACK)."""
        if len(self._acks) >= MAX_ACKS:
            self.acks_dropped += 1
            return
        due = max(tick, self.tx_until) + self.config.sifs_bits * self.config.bit_cycles
        if not self._acks:
            self._urgent_at = due
        self._acks.append((frame, cells, due))

    def carrier(self, cell: int, start: int, until: int) -> None:
        """The medium reports a transmission on ``cell`` over [start, until)."""
        c = self.config
        seen = start + c.cca_bits * c.bit_cycles
        old = self._busy.get(cell)
        if old is None or old[1] < seen:
            self._busy[cell] = (seen, until)
        elif until > old[1]:
            self._busy[cell] = (old[0], until)
        if self._frame is not None and cell in self._cells and seen <= self._at:
            # freeze the countdown: slots idle before the carrier are kept, the rest resume
            # DIFS after it ends
            slot = c.slot_bits * c.bit_cycles
            if seen > self._t0:
                self._slots = max(0, self._slots - (seen - self._t0) // slot)
            self._t0 = max(self._t0, until + c.difs_bits * c.bit_cycles)
            self._at = self._t0 + self._slots * slot

    def busy_until(self, cells: tuple[int, ...]) -> int:
        """When carrier on ``cells`` (or our own transmission) ends, as far as known."""
        end = self.tx_until
        busy = self._busy
        for c in cells:
            b = busy.get(c)
            if b is not None and b[1] > end:
                end = b[1]
        return end

    def _arriving_until(self, tick: int, limit: int) -> int:
        """The end of the latest frame arriving at ``tick`` on any of our cells that ends by
        ``limit``, as far as carrier says (``tick`` when none does). A carrier running past
        ``limit`` (overlapping transmissions reported as one, longer than any frame) is
        spoilt whatever the wait; it must not make the ack spoil a frame on another cell
        that ends in time as well."""
        end = tick
        cca = self.config.cca_bits * self.config.bit_cycles
        for seen, until in self._busy.values():
            if seen - cca <= tick < until and end < until <= limit:
                end = until
        return end

    def _last_busy(self, tick: int) -> tuple[int, int]:
        """(start, end) of the latest carrier sensed by ``tick`` on our cells (or own sending)."""
        best = (self.tx_until, self.tx_until)
        busy = self._busy
        for c in self._cells:
            b = busy.get(c)
            if b is not None and b[0] <= tick and b[1] > best[1]:
                best = b
        return best

    def _plan(self, tick: int) -> None:
        c = self.config
        self._t0 = max(tick, self._last_busy(tick)[1] + c.difs_bits * c.bit_cycles)
        self._at = self._t0 + self._slots * c.slot_bits * c.bit_cycles

    @property
    def next_tick(self) -> int | None:
        if self._acks:
            return self._urgent_at
        return self._at if self._frame is not None else None

    def advance(self, tick: int) -> tuple[bytes, tuple[int, ...]] | None:
        """(bytes, cells) to put on the cells now, if a transmission starts at ``tick``."""
        if self._acks:
            if tick < self._urgent_at:
                return None
            if tick < self.tx_until:  # still sending: go right after
                self._urgent_at = self.tx_until
                return None
            # it would be spoilt: wait, but no longer than ack_defer after this ack was due
            # (counted from its own frame, not from the ack before it: an ack queued behind
            # a deferred one deferred again came after its sender's ack wait)
            arriving = self._arriving_until(tick, self._acks[0][2] + self.ack_defer)
            if arriving > tick:
                self._urgent_at = arriving + self.config.sifs_bits * self.config.bit_cycles
                return None
            out, cells, _ = self._acks.popleft()
            sent = self._start(out, cells, tick)
            if self._acks:  # the next one SIFS after this one
                self._urgent_at = self.tx_until + self.config.sifs_bits * self.config.bit_cycles
            return sent
        if self._frame is None or tick < self._at:
            return None
        if tick < self.tx_until:  # our own acknowledgement went out meanwhile
            self._plan(self.tx_until)
            return None
        start, end = self._last_busy(tick)
        if start <= tick < end:  # reported late (a real-time medium): defer, keep the slots
            self.cca_busy += 1
            self._plan(end)
            return None
        out, self._frame = self._frame, None
        return self._start(out, self._cells, tick)

    def _start(self, data: bytes, cells: tuple[int, ...], tick: int) -> tuple[bytes, tuple[int, ...]]:
        if self.stamper is not None and len(data) > 2 and data[2] == _BEACON:
            data = self.stamper(data, tick)
        self.tx_until = tick + self.airtime(len(data))
        self.transmissions += 1
        self.bits_sent += len(data) * 8
        return data, cells
