"""Link layer of the firmware: bounded queues, aggregation, per-hop ACK and retries.

Frames climbing toward the sink wait in one bounded FIFO (a full queue refuses the
newest frame and counts it). When the cell is free, the head frame and every queued
frame that still fits go to the parent in one BUNDLE transmission, which the parent
acknowledges with one LINK_ACK; without the acknowledgement the transmission is
repeated with a wider backoff up to ``max_retries`` times. Its frames then go back to
the head of the queue for the next parent the routing picks (a dead parent is
evicted after a few such failures), at most ``max_rounds`` times, then are given up
(counted as ``frames_failed``).

A parent change while a transmission waits for its acknowledgement does not send its
frames to the new parent while the old next hop is still a neighbour: the old one has
most likely received them (its acknowledgement is late or lost), and a second copy
sent up another path is a duplicate that meets the first one higher up with more hops,
which looks like a routing loop there (and costs the cells twice). The retries go to the
old next hop; only when it is gone (evicted from the neighbour table) or the retries
are spent do the frames go back to the queue for the new parent. For the same reason a
LINK_ACK that arrives after the deadline, while the retransmission still waits for the
cell (message latency of a real-time mesh), is taken: the retransmission is withdrawn.
Broadcasts (beacons, command floods) have their own small queue, go first and are
never acknowledged.

A readout record in which nothing changed, and which repeats the newest record the same
parent acknowledged but for its frame, goes as a READOUT_SAME: three payload bytes, no
acknowledgement, no retry (:attr:`LinkLayer.same_records`, docs/time.md).
"""

from __future__ import annotations

from collections import Counter, OrderedDict, deque
from collections.abc import Container
from dataclasses import dataclass, replace

import msgpack
from cellbridge.emulator.firmware.transceiver import Transceiver
from cellbridge.protocol import CRC_LEN, HEADER_LEN, MAX_FRAME, Flags, FrameType, Raw, Readout, ReadoutSame, reframe
from cellbridge.protocol.messages import SAME_REF_MASK, SAME_STEP_MAX, pack_payload

_ACK = int(Flags.ACK_REQUEST)
_BUNDLE = int(FrameType.BUNDLE)
_SAME = int(FrameType.READOUT_SAME)
_FRAGMENT = int(Flags.FRAGMENT)
_HANDED_MEMORY = 512  # frames whose acknowledging neighbour is kept
_BUNDLE_OVERHEAD = HEADER_LEN + CRC_LEN + 3  # header, CRC, msgpack array header (<= 3 bytes)


@dataclass
class _InFlight:
    data: bytes
    key: tuple[int, int]  #: (origin, seq) the LINK_ACK must name
    frames: list[Raw]
    next_hop: int
    attempts: int = 0
    deadline: int = -1  #: ack deadline once on the cell; -1 while still contending
    missed: int = -1  #: the deadline that passed without an acknowledgement (last one)
    urgent: bool = False  #: a readout record: sent without backoff, retried within its frame's slots, never requeued
    rank: int = 0  #: a readout record's backoff slots
    #: a readout record's use-by tick (its parent's slot: a retransmission ending later is
    #: dropped there as late); -1: not known, bounded by ``urgent_retries`` alone
    until: int = -1
    frame: object = None  #: a readout record's frame (records of a later frame wait for it)
    record: Readout | None = None  #: a readout record's content (what a READOUT_SAME may refer to once acknowledged)


class LinkLayer:
    def __init__(self, me: int, cells: tuple[int, ...], radio: Transceiver, queue_len: int = 32,
                 max_retries: int = 5, ack_bytes: int = 24, ack_slack: int = 0, max_rounds: int = 3) -> None:
        self.me = me
        self.max_rounds = max_rounds
        self._rounds: dict[tuple[int, int], int] = {}  # frames sent back to the queue, and how often
        self.cells = cells
        self.radio = radio
        self.queue_len = queue_len
        self.max_retries = max_retries
        self.queue: deque[Raw] = deque()
        #: (origin, seq) -> the neighbour that acknowledged it, for the last frames handed on:
        #: a copy coming back from that neighbour went round a loop, not up
        self.handed: OrderedDict[tuple[int, int], int] = OrderedDict()
        self.broadcasts: deque[bytes] = deque()
        #: Readout records (:mod:`.readout`): each goes alone, before anything else, without
        #: backoff, and is retried at most ``urgent_retries`` times, each retry only while its
        #: transmission can still end before the record's use-by tick (its parent's slot):
        #: the window of a level holds a record, its acknowledgement and one retry, and a
        #: record sent as soon as it was complete, before its own slot, has room for more
        #: (tick queued, record's frame, rank, until, frame, record)
        self.urgent: deque[tuple[int, Raw, int, int, object, Readout | None]] = deque()
        self.urgent_retries = 3
        #: Whether a record asks for a per-hop acknowledgement (and gets its retry). Without,
        #: a lost record is listed missing by the relay above it all the same; the real-time
        #: shells send records so, since an acknowledgement there crosses two processes.
        self.urgent_acks = True
        #: Whether a record whose every element is unchanged goes as a READOUT_SAME (a 19-byte
        #: frame, unacknowledged) when it differs from the last record the same parent
        #: acknowledged only in its frame index (docs/protocol.md §4). An idle leaf's record
        #: was a 35-byte frame and a 24-byte LINK_ACK every frame: ~60 % of it the header,
        #: the record's own fields and the acknowledgement, for one id. A lost one leaves its
        #: elements missing at the parent for that frame: nothing else was in it.
        self.same_records = True
        #: parent -> (seq, record): the newest whole record sent, once the parent it went to
        #: acknowledged it (a READOUT_SAME refers to it); none while a newer one waits for its
        #: acknowledgement, and never a record of another parent than the newest one's (the
        #: parent reads a READOUT_SAME as "nothing but READOUT_SAMEs since my copy")
        self._refs: dict[int, tuple[int, Readout]] = {}
        self._newest_full: tuple[int, int] | None = None  # (parent, seq) of the newest whole record sent
        #: a record still queued this long after it was (no parent meanwhile) is given up:
        #: its frame's slots are over, and the relays above listed it missing already
        self.urgent_ttl = 200 * 50_000
        #: outcomes of readout records not yet read by the firmware (True: acknowledged)
        self.urgent_results: list[bool] = []
        #: Readout records sent and waiting for their acknowledgement, by (origin, seq), each
        #: retried at its deadline. The parts of one frame's record go back to back; a later
        #: frame's record waits until the earlier frame's are acknowledged or given up: the
        #: parent reads a child's record of a later frame as the loss of the earlier one (it
        #: lists it missing and sends on at once), so a retry that came after it was dropped
        #: as late, its subtree unknown in that frame though the retry got through.
        self.outstanding: dict[tuple[int, int], _InFlight] = {}
        self._on_radio: _InFlight | None = None  #: the record the radio holds, not yet on the cell
        self._preempted = False  #: the normal frame in flight was taken off the radio for a record
        self._parent: int | None = None  #: the parent at the last advance (records wait without one)
        self.inflight: _InFlight | None = None
        c = radio.config
        # SIFS, a slot, the acknowledgement; before it, at most one frame its sender may
        # wait for (the receiver hearing another on another cell) and one more
        # acknowledgement due first (Transceiver.ack_defer), each SIFS after the one before
        # (three SIFS in all: with one, an ack queued behind a fully deferred one ended
        # 16 bits after its sender gave up, and the frame was sent again)
        self._ack_wait = ((3 * c.sifs_bits + c.slot_bits) * c.bit_cycles + radio.ack_defer
                          + 2 * radio.airtime(ack_bytes) + ack_slack)
        # Extra wait learnt from acknowledgements that came after their deadline (message
        # latency of a real-time mesh: a fixed allowance is too short when the host is busy,
        # and every retransmission it causes loads the cells further). Late ACKs raise it,
        # timely ones let it decay; it stays 0 where ACKs are never late (virtual time).
        self.extra_wait = 0
        self._max_extra = 4 * self._ack_wait
        self.counters: Counter[str] = Counter()
        self.results: list[tuple[int, int, bool]] = []  #: (next hop, attempts, ok) not yet read

    def enqueue(self, frame: Raw) -> bool:
        """Queue a frame for the parent; False (and counted) when the queue is full."""
        if len(self.queue) >= self.queue_len:
            self.counters["queue_drops"] += 1
            return False
        self.queue.append(frame)
        return True

    def enqueue_urgent(self, frame: Raw, tick: int, rank: int = 0, until: int = -1, of: object = None,
                       record: Readout | None = None) -> None:
        """Queue a readout record for the parent (bounded like the queue; counted when full);
        ``rank``: its backoff in slots (:meth:`Transceiver.send`); ``until``: the tick after
        which a retransmission is of no use (its parent's slot; -1: not known); ``of``: the
        frame it belongs to (any hashable value; None: not said, it then waits for no other
        record), so a record of a later frame waits until the earlier frame's records are
        acknowledged or given up; ``record``: the READOUT ``frame`` carries (None: not said,
        it then always goes whole), so one that only repeats an acknowledged record's
        unchanged elements goes as a READOUT_SAME (:attr:`same_records`)."""
        if len(self.urgent) >= self.queue_len:
            self.counters["urgent_drops"] += 1
            self.urgent_results.append(False)
            self._no_ref()
            return
        self.urgent.append((tick, frame, rank, until, of, record))

    def _same(self, record: Readout, parent: int) -> ReadoutSame | None:
        """``record`` as a READOUT_SAME to ``parent``, when that says exactly the same: every
        element unchanged, and the elements, rate, mode, oversampling, span and root those
        of the newest record ``parent`` acknowledged, at most :data:`SAME_STEP_MAX` frames
        before (a parent that lost its copy is without this child's elements that long at
        most). The parent rebuilds ``record`` from its copy; else None (it goes whole)."""
        ref = self._refs.get(parent)
        if ref is None or record.samples or record.missing or record.parts != 1:
            return None
        seq, r = ref
        step = record.index - r.index
        if not 1 <= step <= SAME_STEP_MAX or record.root != r.root or record.rate != r.rate:
            return None
        same = ReadoutSame(step, seq & SAME_REF_MASK)
        return same if same.rebuild(r) == record else None

    def _ref_step(self, record: Readout, parent: int) -> int:
        """Frames from the newest record ``parent`` acknowledged to ``record``, when all
        that went since were READOUT_SAMEs and ``record`` may say so (one part, of that
        record's root and rate, within :data:`SAME_STEP_MAX`); else 0. The parent that
        lost some of those READOUT_SAMEs still holds the samples they stood for
        (:attr:`Readout.ref_step`). Said only where it can help: the record has unchanged
        elements, and at least one frame lies between it and its reference (a periodic
        skin's records, all samples, and a record right after its reference stay as they
        were, two bytes shorter)."""
        ref = self._refs.get(parent)
        if ref is None or record.parts != 1 or not record.unchanged:
            return 0
        r = ref[1]
        step = record.index - r.index
        return step if 2 <= step <= SAME_STEP_MAX and (record.root, record.rate) == (r.root, r.rate) else 0

    def _no_ref(self) -> None:
        """A record was given up unsent (the queue full, or expired without a parent): what
        it said (a sample, perhaps) no parent got, and the records queued behind it, built
        before its loss was known, are unchanged from it. None of them may go as a
        READOUT_SAME over it (the parent would keep its older sample as the reference
        through it), nor may a late acknowledgement of an older record make one."""
        self._refs.clear()
        self._newest_full = None

    def broadcast(self, data: bytes) -> None:
        if len(self.broadcasts) >= 16:
            self.counters["broadcast_drops"] += 1
            return
        self.broadcasts.append(data)

    def acked(self, origin: int, seq: int, src: int, tick: int = -1) -> bool:
        """A LINK_ACK from ``src`` naming (origin, seq): True when it ends the transmission
        in flight. One that comes after the deadline, while the retransmission still waits
        for the cell, counts (late, not lost): the retransmission is withdrawn."""
        u = self.outstanding.get((origin, seq))
        if u is not None and src == u.next_hop:
            if u is self._on_radio:  # its retry still waits for the cell: not needed any more
                self.radio.cancel(u.data)
                self._on_radio = None
            del self.outstanding[(origin, seq)]
            if u.record is not None and u.record.parts == 1 and self._newest_full == (src, seq):
                self._refs[src] = (seq, u.record)  # (the newest whole record the parent holds)
            self.urgent_results.append(True)
            self.counters["frames_acked"] += 1
            return True
        f = self.inflight
        if f is None or f.attempts == 0 or (origin, seq) != f.key or src != f.next_hop:
            return False
        if f.deadline < 0:  # a retransmission is contending: it is not needed any more
            self.radio.cancel(f.data)
            self.counters["late_acks"] += 1
            if tick >= f.missed >= 0:
                late = tick - f.missed
                self.extra_wait = min(self._max_extra, max(self.extra_wait, 2 * late))
        elif f.attempts == 1:
            self.extra_wait -= self.extra_wait // 16
        self.results.append((f.next_hop, f.attempts, True))
        self.counters["frames_acked"] += len(f.frames)
        for x in f.frames:
            self.handed[(x.origin, x.seq)] = f.next_hop
        while len(self.handed) > _HANDED_MEMORY:
            self.handed.popitem(last=False)
        if self._rounds:
            for x in f.frames:
                self._rounds.pop((x.origin, x.seq), None)
        self.inflight = None
        return True

    def _give_back(self, f: _InFlight) -> None:
        """Frames of a failed transmission go back to the head of the queue (bounded rounds)."""
        for x in reversed(f.frames):
            key = (x.origin, x.seq)
            n = self._rounds.get(key, 0) + 1
            if n > self.max_rounds:
                self._rounds.pop(key, None)
                self.counters["frames_failed"] += 1
            else:
                self._rounds[key] = n
                self.queue.appendleft(x)
                self.counters["frames_requeued"] += 1
        while len(self.queue) > self.queue_len:
            x = self.queue.pop()
            self._rounds.pop((x.origin, x.seq), None)
            self.counters["queue_drops"] += 1

    def _reframe(self, parent: int, seq: int, cost_add: int) -> tuple[_InFlight, bool]:
        """Take queued frames for ``parent``; True in the result when a bundle seq was used."""
        first = self.queue.popleft()
        taken = [first]
        encoded = [reframe(first._replace(cost=min(0xFFFF, first.cost + cost_add)), self.me, parent)]
        size = _BUNDLE_OVERHEAD + len(encoded[0]) + 2
        while self.queue:
            f = self.queue[0]
            if size + HEADER_LEN + CRC_LEN + len(f.body) + 2 > MAX_FRAME:
                break
            taken.append(self.queue.popleft())
            encoded.append(reframe(f._replace(cost=min(0xFFFF, f.cost + cost_add)), self.me, parent))
            size += len(encoded[-1]) + 2
        if len(taken) == 1:
            data = reframe(first._replace(cost=min(0xFFFF, first.cost + cost_add)), self.me, parent, _ACK)
            return _InFlight(data, (first.origin, first.seq), taken, parent), False
        bundle = Raw(_BUNDLE, 0, self.me, seq, 0, 0, msgpack.packb(encoded, use_bin_type=True))
        self.counters["bundles"] += 1
        self.counters["bundled_frames"] += len(taken)
        return _InFlight(reframe(bundle, self.me, parent, _ACK), (self.me, seq), taken, parent), True

    def advance(self, tick: int, parent: int | None, next_seq: int, cost_add: int,
                neighbours: Container[int] = ()) -> tuple[tuple[bytes, tuple[int, ...]] | None, bool]:
        """((bytes, cells) to put on the cells now, or None; whether ``next_seq`` was used).
        ``neighbours``: the bridges still in the routing table; a transmission whose next
        hop is no longer the parent keeps retrying it while it is one of them."""
        used = False
        f = self.inflight
        radio = self.radio
        self._parent = parent
        self._urgent_due(tick, parent, neighbours)
        if f is not None and 0 <= f.deadline <= tick and radio.idle:  # no acknowledgement in time
            if f.attempts > self.max_retries or (parent != f.next_hop and f.next_hop not in neighbours):
                if f.attempts > self.max_retries:
                    self.counters["tx_failed"] += 1
                    self.results.append((f.next_hop, f.attempts, False))
                self._give_back(f)
                self.inflight = f = None
            elif not self._urgent_waiting(parent):  # (while a record is only held, it waits no deadline away)
                self.counters["retries"] += 1
                f.missed, f.deadline = f.deadline, -1
                radio.send(f.data, self.cells, tick, f.attempts)
        if self._urgent_waiting(parent):
            self._hand_urgent(tick, parent, cost_add)
        elif f is None and not self._held():
            used = self._hand_over(tick, parent, next_seq, cost_add)
        out = radio.advance(tick)
        if out is not None:
            u = self._on_radio
            f = self.inflight
            if u is not None and out[0] is u.data:
                u.attempts += 1
                u.deadline = radio.tx_until + self._ack_wait + self.extra_wait
                self._on_radio = None
                if not self.urgent_acks:
                    self.counters["urgent_sent"] += 1
            elif f is not None and out[0] is f.data and f.deadline < 0:
                f.attempts += 1
                f.deadline = radio.tx_until + self._ack_wait + self.extra_wait
            elif f is None and not self._records_first(parent):
                # a broadcast just went out: the next frame contends for the cell after it
                # now, not at the bridge's next wake (a relay held a child's frame until its
                # next gate or batch then, and lazy and gate-by-gate sampling sent different frames)
                used = self._hand_over(tick, parent, next_seq, cost_add) or used
        if radio.idle and f is not None and f.deadline < 0 and out is None and self._on_radio is None \
                and not self._records_first(parent) and f is self.inflight and self._preempted:
            self._preempted = False
            radio.send(f.data, self.cells, tick, f.attempts)  # the frame a record went before
        return out, used

    def _urgent_waiting(self, parent: int | None) -> bool:
        """A readout record (new, or a retry) waits for the radio."""
        if self._on_radio is not None:
            return False
        if parent is not None and self.urgent and not self._held():
            return True
        return any(u.deadline == -2 for u in self.outstanding.values())

    def _records_first(self, parent: int | None) -> bool:
        """A readout record waits for the radio, or for an earlier frame's acknowledgement:
        no other frame takes the cell meanwhile (one that did held the record up by its
        airtime and its acknowledgement when the acknowledgement came)."""
        return self._urgent_waiting(parent) or self._held()

    def _held(self) -> bool:
        """The next queued record is of another frame than a record still waiting for its
        acknowledgement: it goes when that one is acknowledged or given up (in frame order
        at the parent, which reads a later frame's record as the earlier one's loss)."""
        if not self.outstanding or not self.urgent:
            return False
        of = self.urgent[0][4]
        # (only towards the same parent: a new parent has none of the old one's records)
        # (nor behind a record past its first retry: a parent that died would hold every
        # record behind each one's last retry, and the backlog outlived the re-route)
        return of is not None and any(u.frame is not None and u.frame != of and u.next_hop == self._parent
                                      and u.attempts <= 1 for u in self.outstanding.values())

    def _urgent_due(self, tick: int, parent: int | None, neighbours: Container[int]) -> None:
        """Records whose acknowledgement did not come by their deadline: retried (marked to
        be sent, deadline -2) while retries are left and one can still end before the
        record's use-by tick, else given up; expired queued records are given up too."""
        while self.urgent and tick - self.urgent[0][0] > self.urgent_ttl:
            self.urgent.popleft()
            self.counters["urgent_expired"] += 1
            self.urgent_results.append(False)
            self._no_ref()
        for key, u in list(self.outstanding.items()):
            if 0 <= u.deadline <= tick:
                useless = 0 <= u.until < tick + self.radio.airtime(len(u.data))  # after the parent's slot
                gone = parent != u.next_hop and u.next_hop not in neighbours
                if u.attempts > self.urgent_retries or useless or gone:
                    del self.outstanding[key]
                    self.counters["urgent_failed"] += 1
                    self.urgent_results.append(False)
                    if u.attempts > self.urgent_retries and not gone:
                        # every retry spent without an acknowledgement (1 % loss per hop:
                        # about 1 in 10^7 records) is a lost link, as a normal frame's last
                        # retry is: fed to the routing. Else, where records are most of what
                        # a bridge sends (250 Hz), the cell went to them and not to frames
                        # whose failures evict a parent that died, and its beacons' timeout
                        # found it seconds later, its subtree unknown meanwhile. (A record
                        # given up for its slot is not: its retries were cut short.)
                        self.results.append((u.next_hop, u.attempts, False))
                else:
                    u.deadline = -2  # to be sent again

    def _hand_urgent(self, tick: int, parent: int | None, cost_add: int) -> bool:
        """Give the radio a readout record (a retry first, then the oldest new one); a normal
        frame still waiting for the cell is taken back and goes after it."""
        radio = self.radio
        f = self.inflight
        if not radio.idle:
            if f is not None and f.deadline < 0 and radio.cancel(f.data):
                self._preempted = True
            else:
                return False
        retry = next((u for u in self.outstanding.values() if u.deadline == -2), None)
        if retry is not None:
            retry.deadline = -1
            self.counters["retries"] += 1
            self._on_radio = retry
            radio.send(retry.data, self.cells, tick, retry.attempts, urgent=True, rank=retry.rank)
            return True
        if parent is None or not self.urgent or self._held():
            return False
        _, first, rank, until, of, record = self.urgent.popleft()
        same = self._same(record, parent) if record is not None and self.same_records and self.urgent_acks else None
        if same is not None:  # unacknowledged: its loss leaves its elements missing above, nothing more
            data = reframe(Raw(_SAME, 0, first.origin, first.seq, first.hops, first.cost, pack_payload(same)),
                           self.me, parent)
            self._on_radio = _InFlight(data, (first.origin, first.seq), [first], parent, urgent=True, rank=rank,
                                       until=until, frame=of)
            self.counters["urgent_same"] += 1
            radio.send(data, self.cells, tick, urgent=True, rank=rank)
            return True
        step = self._ref_step(record, parent) if record is not None and self.same_records and self.urgent_acks else 0
        if step and record is not None:
            body = pack_payload(replace(record, ref_step=step))
            if HEADER_LEN + len(body) + CRC_LEN <= MAX_FRAME and not first.flags & _FRAGMENT:
                first = first._replace(body=body)
                self.counters["urgent_ref_step"] += 1
        data = reframe(first._replace(cost=min(0xFFFF, first.cost + cost_add)), self.me, parent,
                       _ACK if self.urgent_acks else 0)
        u = _InFlight(data, (first.origin, first.seq), [first], parent, urgent=True, rank=rank, until=until,
                      frame=of, record=record)
        if record is not None:  # the parent's copy to refer to is this one once acknowledged, none till then
            # (nor any other parent's: its copy is older than what went here, and a READOUT_SAME
            # to it after a route change and back told it "nothing but READOUT_SAMEs since",
            # so it kept a sample from before the change as the element's reference, and
            # sent that stale reading as the element's sample when it owed one)
            self._refs.clear()
            self._newest_full = (parent, first.seq)
        if not self.urgent_acks:
            self._on_radio = u
            radio.send(data, self.cells, tick, urgent=True, rank=rank)
            return True
        if len(self.outstanding) >= 16:  # bounded: the oldest is given up
            old = next(iter(self.outstanding))
            del self.outstanding[old]
            self.counters["urgent_failed"] += 1
            self.urgent_results.append(False)
        self.outstanding[u.key] = u
        self._on_radio = u
        radio.send(data, self.cells, tick, urgent=True, rank=rank)
        return True

    def _hand_over(self, tick: int, parent: int | None, next_seq: int, cost_add: int) -> bool:
        """Give the radio the next frame if it holds none (broadcasts first); whether
        ``next_seq`` was used."""
        radio = self.radio
        if not radio.idle:
            return False
        if self.broadcasts:
            radio.send(self.broadcasts.popleft(), self.cells, tick)
        elif parent is not None and self.queue:
            self.inflight, used = self._reframe(parent, next_seq, cost_add)
            radio.send(self.inflight.data, self.cells, tick)
            return used
        return False

    @property
    def next_tick(self) -> int | None:
        t = self.radio.next_tick
        f = self.inflight
        if f is not None and f.deadline >= 0:
            t = f.deadline if t is None else min(t, f.deadline)
        for u in self.outstanding.values():
            if u.deadline >= 0 and (t is None or u.deadline < t):
                t = u.deadline
        if self.urgent and self._parent is not None and self._on_radio is None and self.radio.idle \
                and not self._held():
            # records queued behind the one that just went (a backlog after the bridge was
            # held up, a record in parts): the next goes when the cell is ours again, not at
            # the bridge's next gate. Without this wake a bridge that fell behind sent one
            # record per frame and never caught up: every record it sent came after its
            # parent's slot and was dropped as late, its element unknown for seconds.
            tx = self.radio.tx_until
            t = tx if t is None else min(t, tx)
        elif (self._preempted and f is not None and f.deadline < 0 and self._on_radio is None
              and self.radio.idle and not self._records_first(self._parent)):
            # the frame a record went before contends again once the record is on the cell:
            # then, not at whatever wake comes next (a relay's next gate, or with its sample
            # computed at its children's records, a frame later)
            tx = self.radio.tx_until
            t = tx if t is None else min(t, tx)
        elif (f is None and (self.broadcasts or (self.queue and self._parent is not None))
              and self._on_radio is None and self.radio.idle and not self._records_first(self._parent)):
            # a frame queued while a record went first contends once the record is on the
            # cell: a relay that computes its sample at its children's records wakes only for
            # them, each makes a record, and the queue waited for a wake of another kind.
            # (Not while a record is held for an earlier one's acknowledgement: nothing else
            # goes then, and that wake, past, woke the bridge at every cycle until the
            # acknowledgement or its deadline, which the outstanding record's wake covers.)
            tx = self.radio.tx_until
            t = tx if t is None else min(t, tx)
        return t

    def has_work(self) -> bool:
        return bool(self.queue or self.broadcasts or self.urgent)

