"""The scheduled readout of skin frames along the routing tree, sans-I/O.

On mesh time every bridge samples frame ``k`` at the same instant. After the frame's gates
close, the frame is read out towards the gateway *deepest first*: a bridge ``d`` hops from
its gateway owes its parent one record of frame ``k`` by its **slot**, the frame's gate
end plus ``(depths - d) * window`` cycles, so a relay's slot comes after its children's.
The slot is computed from the bridge's depth alone (no negotiation), and the gateway's
slot (depth 0) is the end of the readout: ``span`` = gates + ``depths * window``.

A record (protocol ``READOUT``) holds the bridge's own element and every element of its
subtree, each exactly once: a *sample* (periodic; event-based and changed), *unchanged*
(event-based, within the threshold of the last sample it sent) or *missing* (a child's
record did not come by the slot). A relay sends its record as soon as it is complete
(its own state is in and every child it expects has sent its record of ``k``), and at its
slot at the latest: the slot bounds the latency, the early send is what makes it short.
A child is expected while it sent a record within ``forget`` cycles; the bridges its last
record listed are its subtree, marked missing when its record of ``k`` does not come. It
is *waited for* only while it is heard: a child silent for ``quiet`` cycles (and two
frame periods, and the schedule's span and a period: a child held up for less may still
make its slot) is not waited for until its next record comes, so a frame goes as soon as
the rest of it is in. (A dead relay's parent waited for it until its slot in every frame,
and under the real-time shells' message delays its record then came after the next
level's slot: its siblings, and each ancestor's subtree in turn, went missing with it
until it was forgotten.)

A record that was lost on its way (its hop was not acknowledged after its retries) leaves
the host without that frame of the subtree, and an *unchanged* of the next frame would
then refer to a sample the host never got. So a bridge whose record failed sends its next
record with every unchanged element expanded to the last sample it passed on for that
element (a relay keeps the last sample of every element of its subtree), and the host
takes an unchanged element as known only when it knew the element's previous frame.

A record in which nothing changed may come as a READOUT_SAME (the link layer sends it so
when it repeats the record the parent last acknowledged: docs/time.md), which
:meth:`FrameReadout.child_same` rebuilds from the child's last whole record, or drops
when it has none that matches: then, as for silence, the child's elements are missing in
that frame, never unchanged. A lost one held no sample, so the references stay good
through it; and an element a bridge listed missing goes, the next time it passes it on
unchanged, as the sample it keeps of it, so the host knows it again at once.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from cellbridge.protocol import (
    CRC_LEN,
    HEADER_LEN,
    MAX_FRAME,
    Mode,
    ProtocolError,
    Readout,
    ReadoutSame,
    ReadoutSample,
)
from cellbridge.protocol.messages import SAME_REF_MASK, SAME_STEP_MAX, pack_payload

_UNCHANGED = "u"
_CLOCK_HZ = 50_000_000  #: chip cycles per second (``span_us`` and ``forget`` are in them)
_TIME_BACK = 10  #: a child's record this many ``forget`` older than the newest frame sent: time went back


def stagger(bridge: int, most: int) -> int:
    """The bridge's own offset in [0, most): spread by a multiplicative hash of its id, so
    neighbours (consecutive ids) land far apart (heartbeat and refresh phases, slots)."""
    return (bridge * 2_654_435_761 % 4_294_967_296) * most >> 32


#: An own or passed-on state of one element in one frame: a sample, or unchanged.
State = ReadoutSample | str


@dataclass(frozen=True)
class ReadoutConfig:
    """The schedule's parameters, in chip cycles; the same on every bridge of a skin."""

    #: Levels of the schedule: a bridge deeper than this sends in the deepest level's slot.
    depths: int = 8
    #: Cycles per level: a record, its acknowledgement and one retry (and, in the
    #: real-time shells, the processes' message latency). A record that went before its
    #: slot may be retried again while a retry can still reach the parent by the parent's
    #: slot (:meth:`FrameReadout.until`).
    window: int = 150_000
    #: A child silent this long (cycles) is no longer expected, nor its subtree listed.
    forget: int = 100_000_000
    #: 0: the levels' slots are spread evenly (a bridge ``d`` deep sends by ``(depths - d)
    #: * window``). Else the slots are packed at the end of the span, ``hop`` cycles apart
    #: (by ``depths * window - d * hop``): a relay then waits for a late child until just
    #: before its own parent's slot, so a record whose bridge's process was held up for
    #: tens of milliseconds (real-time shells on a loaded host) still makes its frame,
    #: while the span, and with it the host's deadline, stays the same. Records go as soon
    #: as they are complete either way; the slots only bound the wait for a missing one.
    hop: int = 0
    #: A child silent this long (cycles), for two periods of the frame's rate, and for the
    #: schedule's span (``depths * window``) and one period, is not waited for (its subtree
    #: is listed missing as soon as the rest of the frame is in) until it is heard again.
    #: Within the span a held-up child's record can still make its frame (the real-time
    #: shells' slots absorb a 4x4 leaf's process held up ~120 ms): silence that short is a
    #: child running late, not one that is gone. Far shorter than ``forget``.
    quiet: int = 5_000_000


@dataclass
class _Pending:
    """One frame being read out by this bridge."""

    index: int
    rate: int
    slot: int  #: the tick the record goes at the latest
    span: int  #: cycles from the frame's gate start to the gateway's slot
    own: tuple[Mode, int, State] | None = None
    #: the time root whose mesh time ``index`` counts: the bridge's own at its sample (else
    #: the first child record's), stamped on the record whatever root the bridge follows
    #: when it goes
    root: int = 0
    #: (mode, oversampling) -> bridge -> state, from the children's records
    got: dict[int, tuple[Mode, int, State]] | None = None
    heard: set[int] | None = None  #: children whose record of this frame came


class FrameReadout:
    """One bridge's part in the readout: its own states, its children's records, and the
    records it owes its parent (or, on a gateway, the host), each in time."""

    def __init__(self, me: int, config: ReadoutConfig, counters: Counter[str], room: int = 0,
                 refresh: int = 0) -> None:
        """``room``: bytes each record part leaves free (a gateway's age); ``refresh``: on a
        gateway, every element kept goes as its sample once every this many frames
        (0: never; see the module)."""
        if refresh < 0:
            raise ValueError(f"refresh {refresh} must be >= 0 frames")
        self.me = me
        self.refresh = refresh
        self.config = config
        self.counters = counters
        self.room = room  # bytes each part leaves free for what its writer adds (a gateway's age)
        self._pending: dict[tuple[int, int], _Pending] = {}  # (rate, index) -> frame
        self._members: dict[int, set[int]] = {}  # child -> the bridges its last record listed
        self._via: dict[int, int] = {}  # bridge -> the child it came through lately
        self._heard_at: dict[int, int] = {}  # child -> tick of its last record
        self._last: dict[int, tuple[Mode, int, ReadoutSample]] = {}  # bridge -> last sample passed on
        #: bridge -> (root, rate, index) of the newest frame through which ``_last`` is that
        #: bridge's reference: its sample's frame, or a later one every frame up to which
        #: said it unchanged here (:meth:`_note`)
        self._last_at: dict[int, tuple[int, int, int]] = {}
        #: bridge -> the frame of the sample ``_last`` holds: it is the reference of the frames
        #: from this one to ``_last_at``'s (:meth:`_refers`)
        self._last_from: dict[int, int] = {}
        self._expand = False  # the last record sent failed: expand unchanged states once
        #: bridges this one listed missing in a record it sent: passed on as unchanged later,
        #: each goes as the sample kept of it (the host knows an element again only from a
        #: sample once it was unknown in a frame; a child's lost READOUT_SAME leaves one so)
        self._owed: set[int] = set()
        #: child -> (seq, record): its last whole one-part record, what its READOUT_SAME refers to
        self._refs: dict[int, tuple[int, Readout]] = {}
        self._sent: set[tuple[int, int]] = set()  # frames already sent (late records are counted)
        self._sent_order: list[tuple[int, int]] = []
        self._until: dict[tuple[int, int], int] = {}  # frame sent -> its parent's slot (tick)
        #: (root, rate) -> the newest frame whose record went: a child's record of an older
        #: frame that is not waiting here is late however old (``_sent`` remembers only the
        #: last frames); per root, as two roots' indices count unrelated mesh times
        self._newest: dict[tuple[int, int], int] = {}
        #: take()'s fast path: nothing can be due before ``_due`` unless a state came
        #: (own, a child's record) or a child was forgotten since the last look
        self._changed = False
        self._due: int | None = None
        #: (child, rate) -> the newest frame it sent a record of: a child sends its records in
        #: frame order, so one that sent a later frame's record will not send this one's
        self._child_newest: dict[tuple[int, int], int] = {}
        self._expire_at = 0  # children are looked at for expiry at most this often
        self._root = 0  # the root this bridge followed at the last take()
        self._now = 0  # the tick of the bridge's current wake (:meth:`at`)
        self._slots: dict[int, int] = {}  # depth -> slot(depth)
        self._quiets: dict[int, int] = {}  # rate -> _quiet(rate)

    # -- inputs -----------------------------------------------------------------------
    def at(self, tick: int) -> None:
        """The bridge woke at ``tick``: which children are waited for is judged at it (the
        sampler asks :meth:`expects_children` before :meth:`take` runs)."""
        self._now = tick

    def own(self, index: int, rate: int, mode: Mode, oversampling: int, state: State, slot: int,
            span: int, root: int = 0) -> None:
        """This bridge's state of frame ``index`` (taken at its gate end), and the frame's
        ``slot`` (tick) and ``span`` (cycles) as this bridge's depth gives them; ``root``:
        the time root whose mesh time ``index`` counts (the one the bridge followed when it
        sampled: the frame's record names it even if the bridge follows another by then)."""
        p = self._frame(index, rate, slot, span, root)
        if p is None:
            return
        p.own = (mode, oversampling, state)
        p.root = root
        self._changed = True
        at = self._last_at.get(self.me)
        if isinstance(state, ReadoutSample):
            if at is None or at[:2] != (root, rate) or index >= at[2]:  # (not an older frame's, come late)
                self._last[self.me] = (mode, oversampling, state)
                self._last_at[self.me] = (root, rate, index)
                self._last_from[self.me] = index
        elif at is not None and (at[:2] != (root, rate) or index > at[2]):
            # unchanged from the reporter's reference: the sample kept, only while every frame
            # since it came here in turn. Frames that did not (the bridge off mesh time, its
            # samples in DATA frames; a state come after its frame went) may have held a newer
            # sample, and an expansion then sent the kept one as the bridge's reading
            if at[:2] == (root, rate) and index == at[2] + 1:
                self._last_at[self.me] = (root, rate, index)
            else:
                self._last.pop(self.me, None)
                self._last_from.pop(self.me, None)
                del self._last_at[self.me]

    def child(self, src: int, record: Readout, tick: int, seq: int | None = None, since: int | None = None) -> None:
        """A child's record (``src``: the neighbour that sent it). A late one (its frame's
        record already went) still says which bridges the child stands for. ``seq``: the
        frame's sequence number when it came whole (a READOUT_SAME of the child may refer
        to it: :meth:`child_same`); ``since``: the frame of the record a READOUT_SAME
        rebuilt this one from. A whole record's ``ref_step`` says the same of the record
        that many frames back, for the elements of the copy kept here when it is that
        record (else it is not used)."""
        only: frozenset[int] | None = None
        if since is None and record.ref_step:
            got = self._refs.get(src)
            r = got[1] if got is not None else None
            if r is not None and (r.root, r.rate, r.index) == (record.root, record.rate, record.index - record.ref_step):
                since = r.index
                only = frozenset((*(s.bridge for s in r.samples), *r.unchanged))
                self.counters["readout_ref_step"] += 1
        if seq is not None and record.parts == 1 and not self._older_ref(src, record, seq):
            self._refs.pop(src, None)
            self._refs[src] = (seq, record)
            if len(self._refs) > 64:  # (bounded: the least recently refreshed child's goes)
                del self._refs[next(iter(self._refs))]
        self._heard_at[src] = tick
        self._now = tick
        self._changed = True
        ck = (src, record.rate)
        if record.index > self._child_newest.get(ck, -1):
            self._child_newest[ck] = record.index
        mine = self._members.setdefault(src, set())
        for b in (*(s.bridge for s in record.samples), *record.unchanged):
            # a bridge whose state came through this child re-routed through it: it leaves its old branch
            old = self._via.get(b)
            if old is not None and old != src:
                self._members.get(old, set()).discard(b)
            self._via[b] = src
            mine.add(b)
        for b in record.missing:
            # listed missing: what the child last knew of its subtree (it lists a bridge that
            # left it until it forgets it, 2 s); the bridge stays with the branch its state
            # comes through. (Taken as a re-route, a relay's stale claim and the bridge's own
            # record took it from each other at every frame, and whenever the claim came
            # first the frame went without waiting for the bridge, its record late: after
            # the root gateway died, bridge 3 unknown in two frames of three for 2 s.)
            if self._via.setdefault(b, src) == src:
                mine.add(b)
        self._note(record, since, only)
        key = (record.rate, record.index)
        p = self._pending.get(key)
        nk = (record.root, record.rate)
        newest = self._newest.get(nk)
        if newest is not None and (newest - record.index) * _CLOCK_HZ > _TIME_BACK * self.config.forget * record.rate:
            # far older than any relay holds a record: the skin's time went back (a new root
            # numbering from 0; this bridge's own frames follow at its next sample)
            del self._newest[nk]
            self.counters["readout_time_back"] += 1
        if key in self._sent or (p is None and record.index <= self._newest.get(nk, -1)):
            # its frame's record went (or a newer one did: records go oldest frame first):
            # passed on now it would only reach the host after the frame was given out
            self.counters["readout_late"] += 1
            return
        if p is None:
            # a frame this bridge has not sampled (yet): its slot is planned when the own
            # state comes; until then the record waits here
            # (a record of a rate this bridge does not sample at goes on alone a window later)
            p = self._pending[key] = _Pending(record.index, record.rate, tick + self.config.window, 0,
                                              root=record.root)
            if len(self._pending) > 64:  # a hostile or confused child: bounded
                self._evict()
                if key not in self._pending:
                    return
        if p.got is None:
            p.got, p.heard = {}, set()
        assert p.heard is not None
        p.heard.add(src)
        m, o = record.mode, record.oversampling
        for s in record.samples:
            p.got[s.bridge] = (m, o, s)
        for b in record.unchanged:
            p.got[b] = (m, o, _UNCHANGED)
        for b in record.missing:
            p.got.setdefault(b, (m, o, "m"))

    def unreadable(self, src: int) -> None:
        """A whole record of ``src`` came but could not be read. Its hop acknowledged it
        (before reading it), so the child refers to it from now on: the older record kept
        of it is dropped, else a READOUT_SAME whose ``ref`` happened to match that one's
        (128 frames on) was rebuilt from it, another element set and another frame."""
        self._refs.pop(src, None)

    def child_same(self, src: int, same: ReadoutSame, tick: int) -> bool:
        """A child's READOUT_SAME: its record rebuilt from the record it refers to, and taken
        as :meth:`child` takes a whole one. False (counted) when no record of that child
        here matches its ``ref`` (this bridge restarted, or the frame is forged: a child
        refers only to a record of its that this bridge acknowledged): the frame then goes
        as if nothing came, its elements missing, never unchanged."""
        got = self._refs.get(src)
        if got is None or got[0] & SAME_REF_MASK != same.ref:
            self.counters["readout_same_unknown"] += 1
            return False
        self.counters["readout_same"] += 1
        self.child(src, same.rebuild(got[1]), tick, since=got[1].index)
        return True

    def _older_ref(self, src: int, record: Readout, seq: int) -> bool:
        """Whether ``record`` (frame ``seq``) is an older record of ``src`` than the whole one
        kept for it: of the same root and rate, at most :data:`SAME_STEP_MAX` frames before,
        and numbered at most :data:`SAME_REF_MASK` before it (a child numbers its frames in
        order): a retry come late (its acknowledgements lost, the child's next whole record
        went past it and was acknowledged). The child refers to the newer one: replaced by
        the retry, every READOUT_SAME after it was unmatched, its elements missing until its
        next whole record. (Further back it is a new numbering, of the frames or of the
        child's seq after a restart: taken.)"""
        got = self._refs.get(src)
        if got is None:
            return False
        kept_seq, kept = got
        return ((record.root, record.rate) == (kept.root, kept.rate)
                and kept.index - SAME_STEP_MAX <= record.index < kept.index
                and 0 < (kept_seq - seq) & 0xFFFF <= SAME_REF_MASK)

    def _note(self, record: Readout, since: int | None = None, only: frozenset[int] | None = None) -> None:
        """Keep, per bridge of a child's record, the sample that is its reference (what an
        *unchanged* of it refers to), for the expansion after a failed record. A sample
        counts only when it is not older than the state kept (a retry whose first attempt
        got through, its acknowledgement lost, comes after the next frame's record: taken,
        its old sample replaced the newer one, and a later expansion sent that old reading
        as the bridge's sample). An *unchanged* keeps the reference only when it follows
        the frame kept: a frame of the bridge that did not come here (missing, or sent up
        another route) may have held a new sample, so the one kept is forgotten and an
        *unchanged* then stays one (the host knows it only if it knew the frame before).

        ``since``: ``record`` was rebuilt from a READOUT_SAME referring to the child's record
        of frame ``since``. Everything the child sent after that record was a READOUT_SAME
        (a whole record sent after it would be its reference now), which carries no sample:
        one lost on the way lost nothing, so a sample kept through frame ``since`` or later
        is still the reference, whatever frames went missing here since. ``only``: the
        elements ``since`` holds for (None: all; a whole record's ``ref_step`` holds only
        for the elements of the record it names)."""
        chain = (record.root, record.rate)
        at_of = self._last_at.get
        k = record.index
        for s in record.samples:
            if s.bridge == self.me:  # (a confused child's word on this bridge: its own state is kept)
                continue
            at = at_of(s.bridge)
            if at is None or at[:2] != chain or k >= at[2]:
                self._last[s.bridge] = (record.mode, record.oversampling, s)
                self._last_at[s.bridge] = (chain[0], chain[1], k)
                self._last_from[s.bridge] = k
        for b in record.unchanged:
            if b == self.me:
                continue
            at = at_of(b)
            if at is not None and at[:2] == chain and at[2] <= k and (
                    k <= at[2] + 1 or (since is not None and since <= at[2] and (only is None or b in only))):
                self._last_at[b] = (chain[0], chain[1], k)
            elif at is None or at[:2] != chain or k > at[2]:
                self._last.pop(b, None)
                self._last_at.pop(b, None)
                self._last_from.pop(b, None)

    def _refers(self, b: int, p: _Pending) -> bool:
        """Whether the sample kept of ``b`` is what its *unchanged* in frame ``p`` refers to:
        a sample of a frame not after ``p``, kept through ``p`` or later, of ``p``'s time root
        and rate. A bridge running late builds a record after the next frame's state came (its
        own, or a child's record): a sample of that frame is no reading of ``p``'s, and the
        state then stays unchanged; the next frame *unchanged* leaves the sample kept the
        reference of ``p`` (taken for none, a frame waiting for a relay's retried record
        while a leaf's of the next frame came neither refreshed nor paid an owed element)."""
        at = self._last_at.get(b)
        return (at is not None and at[:2] == (p.root, p.rate)
                and self._last_from.get(b, at[2]) <= p.index <= at[2])

    def sent(self, ok: bool) -> None:
        """The outcome of the last record handed to the link (acknowledged or given up)."""
        if not ok:
            self.counters["readout_failed"] += 1
            self._expand = True

    # -- schedule -----------------------------------------------------------------------
    def slot(self, depth: int) -> int:
        """Cycles from a frame's gate end to the slot of a bridge ``depth`` hops from its gateway."""
        got = self._slots.get(depth)
        if got is None:  # (a function of the config and the depth: kept, as it is asked at every look)
            c = self.config
            if c.hop:
                got = c.depths * c.window - min(depth, c.depths) * min(c.hop, c.window)
            else:
                got = (c.depths - min(depth, c.depths)) * c.window
            if len(self._slots) < 64:
                self._slots[depth] = got
        return got

    def expects_children(self, rate: int) -> bool:
        """Whether a frame's record at ``rate`` waits for children's records (some child is
        expected and heard lately: :attr:`ReadoutConfig.quiet`): then it cannot go at the
        bridge's own gate end."""
        if not self._members:
            return False
        heard_at = self._heard_at
        quiet = self._quiet(rate)
        now = self._now
        for c, m in self._members.items():
            if m:
                at = heard_at.get(c)
                if at is not None and now - at <= quiet:  # (_waited, inline: asked at every look)
                    return True
        return False

    def _quiet(self, rate: int) -> int:
        """Cycles of silence after which a child is not waited for in a frame at ``rate``:
        ``quiet``, two of the frame's periods (a slow rate's records are that far apart), and
        the schedule's span and a period (a child held up for less may still make its
        parent's slot: its silence is its last record's period and the hold)."""
        got = self._quiets.get(rate)
        if got is None:
            period = _CLOCK_HZ // max(1, rate)
            got = max(self.config.quiet, 2 * period, self.slot(0) + period)
            if len(self._quiets) < 64:
                self._quiets[rate] = got
        return got

    def _waited(self, child: int, rate: int, tick: int) -> bool:
        """Whether a frame at ``rate`` waits for ``child`` at ``tick``: it was heard within
        :meth:`_quiet` cycles."""
        at = self._heard_at.get(child)
        return at is not None and tick - at <= self._quiet(rate)

    def child_came_first(self, index: int, rate: int) -> bool:
        """Whether a child's record of frame ``index`` came before this bridge's own state
        of it (a child whose gates end earlier: a shorter gate, another mode): the wake
        that record brought has passed, so the own state is wanted at its gate end."""
        p = self._pending.get((rate, index))
        return p is not None and p.own is None and bool(p.heard)

    def _step(self) -> int:
        """Cycles from a bridge's slot to its parent's (one level up)."""
        c = self.config
        return min(c.hop, c.window) if c.hop else c.window

    def until(self, record: Readout) -> int:
        """The tick of the parent's slot for the frame of ``record`` (one :meth:`take` just
        gave; -1: not known): the parent passes that frame on by then, and a record of it
        that comes later is dropped there as late, so a retransmission that cannot end by
        then is not worth the cell's time (nor the wait of the next frame's record)."""
        return self._until.get((record.rate, record.index), -1)

    @property
    def next_tick(self) -> int | None:
        """The earliest slot among the frames waiting (None: nothing waits)."""
        if self._changed:
            return self._next_due()
        return self._due

    def take(self, tick: int, root: int = 0) -> list[Readout]:
        """The records due now, oldest frame first: complete (and every older frame of
        its root and rate gone), or at their slot. Each is one or more READOUT payloads
        that each fit a frame, naming the root its index counts.

        ``root``: the time root this bridge follows now (0: none, or not said). A frame
        only its children's records make up, of another root, is dropped at its slot and
        counted (``readout_other_root``): a gateway that is its own root for its first
        second, its children already on the skin's root, passed their frames on between
        its own, and the host saw its line switch roots at every record. The bridge's own
        frames go with the root they were sampled on, so its records switch root once, at
        the frame where its own sampling did (a child's record of a frame this bridge
        sampled joins it: at a failover the new root carries the old one's time on)."""
        self._now = tick
        if tick >= self._expire_at:
            self._expire_at = tick + max(1, self.config.forget // 16)
            self._expire(tick)
        if not self._changed and (self._due is None or tick < self._due):
            return []  # a bridge wakes for much else (its link, beacons): nothing of ours changed
        self._changed = False
        self._root = root
        out = self._take(tick, root)
        self._due = self._next_due()
        return out

    def _next_due(self) -> int | None:
        """The earliest slot a waiting frame can go at: the oldest frame's of each root and
        rate (a later frame goes after it, though its own slot may be earlier: a frame a
        child's record began, or one planned at another depth; taken for due, it woke the
        bridge at every tick until the older one's slot); or, before it, the tick a child
        it waits for stops being waited for (:attr:`ReadoutConfig.quiet`)."""
        first: dict[tuple[int, int], _Pending] = {}
        for p in self._pending.values():
            q = first.get((p.root, p.rate))
            if q is None or p.index < q.index:
                first[(p.root, p.rate)] = p
        if self._before_switch(self._root):  # the root followed now waits for them
            first = {c: p for c, p in first.items() if c[0] != self._root}
        due = min((p.slot for p in first.values()), default=None)
        if due is not None:
            now = self._now
            for p in first.values():
                heard = p.heard or ()
                quiet = self._quiet(p.rate)
                for c, m in self._members.items():
                    at = self._heard_at.get(c)
                    if m and at is not None and c not in heard:
                        end = at + quiet + 1
                        if now < end < due:
                            due = end
        return due

    def _before_switch(self, root: int) -> bool:
        """Whether own frames sampled on another root than ``root`` (the one followed now)
        still wait: the records switch root once, after them."""
        if not root:
            return False
        for p in self._pending.values():  # (a loop, not any() over a generator: asked at every look)
            if p.own is not None and p.root and p.root != root:
                return True
        return False

    def _take(self, tick: int, root: int) -> list[Readout]:
        # In frame order: a frame complete early waits for the older ones of its rate. Sent
        # before them, it tells the parent (whose cell keeps each child's order) that their
        # records were lost: a parent gives a child's record up once a later one came, and
        # theirs would then come after, late.
        out: list[Readout] = []
        blocked: set[tuple[int, int]] = set()  # (root, rate) with an older frame not due yet
        # (frames of other roots first: those sampled before a switch of root go before the
        # frames of the root followed now, which wait for them)
        for key in sorted(self._pending, key=lambda k: (self._pending[k].root == root, k)):
            p = self._pending[key]
            chain = (p.root, p.rate)
            if chain in blocked:
                continue
            if root and p.root == root and self._before_switch(root):
                blocked.add(chain)
                continue
            if tick < p.slot and (p.own is None or not self._complete(p, tick)):
                blocked.add(chain)
                continue
            del self._pending[key]
            if p.own is None and p.root and root and p.root != root:
                self.counters["readout_other_root"] += 1
                continue
            self._sent.add(key)
            self._sent_order.append(key)
            if key[1] > self._newest.get(chain, -1):
                self._newest[chain] = key[1]
            self._until[key] = p.slot + self._step()
            if len(self._sent_order) > 256:
                old = self._sent_order.pop(0)
                self._sent.discard(old)
                self._until.pop(old, None)
            out.extend(self._records(p, tick))
        return out

    def _complete(self, p: _Pending, tick: int) -> bool:
        """Every expected child sent its record of the frame, or a later frame's (then this
        one's was lost on its way: it is listed missing now rather than at the slot), or is
        not waited for (silent: :attr:`ReadoutConfig.quiet`)."""
        heard = p.heard or set()
        newest = self._child_newest
        rate, index = p.rate, p.index
        for c, m in self._members.items():  # (a loop, not all() over a generator: asked at every look)
            if m and c not in heard and newest.get((c, rate), -1) <= index and self._waited(c, rate, tick):
                return False
        return True

    def _expire(self, tick: int) -> None:
        forget = self.config.forget
        for c, at in list(self._heard_at.items()):
            if tick - at > forget:
                del self._heard_at[c]
                for ck in [ck for ck in self._child_newest if ck[0] == c]:
                    del self._child_newest[ck]
                for b in self._members.pop(c, set()):
                    if self._via.get(b) == c:
                        del self._via[b]
                        self._last.pop(b, None)
                        self._last_at.pop(b, None)
                        self._last_from.pop(b, None)
                        self._owed.discard(b)
                # (its last whole record stays: a child back after it was forgotten may still
                # refer to it, and the record says exactly what it said)
                self.counters["readout_children_forgotten"] += 1
                self._changed = True  # a frame that waited for this child may be complete now

    def _evict(self) -> None:
        oldest = min(self._pending, key=lambda k: (self._pending[k].own is not None, k[1]))
        del self._pending[oldest]
        self.counters["readout_evicted"] += 1

    def _frame(self, index: int, rate: int, slot: int, span: int, root: int) -> _Pending | None:
        key = (rate, index)
        if key in self._sent:
            self.counters["readout_own_late"] += 1
            return None
        if index < self._newest.get((root, rate), -1) - 1:  # the skin's time went back (a new root)
            del self._newest[(root, rate)]
            self.counters["readout_time_back"] += 1
        p = self._pending.get(key)
        if p is None:
            p = self._pending[key] = _Pending(index, rate, slot, span)
            if len(self._pending) > 64:
                self._evict()
        else:
            p.slot, p.span = slot, span
        return p

    # -- records ------------------------------------------------------------------------
    def _records(self, p: _Pending, tick: int) -> list[Readout]:
        states: dict[int, tuple[Mode, int, State]] = dict(p.got or {})
        if p.own is not None:
            states[self.me] = p.own
            expected = set().union(*self._members.values()) if self._members else set()
            for b in expected:
                if b not in states:
                    states[b] = (p.own[0], p.own[1], "m")
        else:  # a frame of another rate than this bridge's: its children's states, passed on
            self.counters["readout_passed_on"] += 1
        expand, self._expand = self._expand, False
        owed = self._owed
        refresh = self.refresh
        phase = p.index % refresh if refresh else -1
        groups: dict[tuple[Mode, int], tuple[list[ReadoutSample], list[int], list[int]]] = {}
        for b in sorted(states):
            mode, over, st = states[b]
            if st == _UNCHANGED and b in self._last:
                if (expand or b in owed) and self._refers(b, p):
                    mode, over, st = self._last[b]
                    self.counters["readout_expanded"] += 1
                elif phase >= 0 and stagger(b, refresh) == phase and self._refers(b, p):
                    mode, over, st = self._last[b]
                    self.counters["readout_serial_refreshed"] += 1
            g = groups.setdefault((mode, over), ([], [], []))
            if isinstance(st, ReadoutSample):
                g[0].append(st if st.bridge == b else st._replace(bridge=b))
                owed.discard(b)
            elif st == _UNCHANGED:
                g[1].append(b)
                owed.discard(b)  # (no sample kept to send: the host knows it again at its next)
            else:
                g[2].append(b)
                owed.add(b)
        missing = sum(len(g[2]) for g in groups.values())
        if missing:
            self.counters["readout_missing"] += missing
        span_us = (p.span if p.span else self.config.window * (self.config.depths + 1)) * 1_000_000 // _CLOCK_HZ
        out = record_parts(p.index, p.rate, groups, span_us, p.root or 0, self.room)
        n = len(out)
        self.counters["readout_records"] += 1
        self.counters["readout_frames"] += n
        return out

    def waiting(self) -> int:
        """Frames whose record has not gone yet (a power-off loses them)."""
        return len(self._pending)


#: Bytes a gateway's ``age_us`` takes at most (a msgpack uint32): what each part of a record
#: it writes on its serial line leaves free, its age being stamped as it goes out.
AGE_ROOM = 5


def record_parts(index: int, rate: int,
                 groups: dict[tuple[Mode, int], tuple[list[ReadoutSample], list[int], list[int]]],
                 span_us: int, root: int = 0, room: int = 0) -> list[Readout]:
    """One record of frame ``index`` on ``root``'s mesh time: per (mode, oversampling) its
    samples, unchanged and missing bridges (each list increasing by bridge id), as READOUT
    payloads that each fit a frame with ``room`` bytes to spare (:data:`AGE_ROOM` for a
    gateway's), numbered ``part`` of ``parts`` when there are several."""
    out: list[Readout] = []
    for (mode, over), (samples, unchanged, miss) in groups.items():
        out.extend(_split(Readout(index, rate, mode, over, tuple(samples), tuple(unchanged), tuple(miss),
                                  min(span_us, 0xFFFF_FFFF), 0, 1, root), room))
    n = len(out)
    if n > 1:
        out = [Readout(r.index, r.rate, r.mode, r.oversampling, r.samples, r.unchanged, r.missing, r.span_us,
                       i, n, root) for i, r in enumerate(out)]
    return out


#: Bytes a READOUT payload takes at most besides its entries: the outer array's header,
#: nine scalars of at most 9 bytes each (msgpack's largest number form) and three list
#: headers of at most 5 (array 32) ...
_MOST_FIXED = 1 + 9 * 9 + 3 * 5
#: ... a sample at most (an array of four numbers), an unchanged or missing id at most
_MOST_SAMPLE, _MOST_ID = 1 + 4 * 9, 9


def _fits(r: Readout, room: int = 0) -> bool:
    """Whether ``r`` packs into one frame with ``room`` bytes to spare. A record whose
    largest possible encoding fits (every leaf's, a small relay's) is not packed here:
    the link packs it once, when it builds the frame."""
    most = _MOST_FIXED + _MOST_SAMPLE * len(r.samples) + _MOST_ID * (len(r.unchanged) + len(r.missing))
    if HEADER_LEN + CRC_LEN + most + room <= MAX_FRAME:
        return True
    return HEADER_LEN + CRC_LEN + len(pack_payload(r)) + room <= MAX_FRAME


def _split(r: Readout, room: int = 0) -> list[Readout]:
    """``r`` as payloads that each fit one frame with ``room`` bytes to spare, each filled
    before the next is begun: a relay near the gateway carries most of the skin's samples,
    and its records' headers and frames are the cells' overhead (halving a record of 20
    samples sent four frames of 5 to 10 samples where two do).

    Each part is the longest run of the entries left that fits (one entry at least): what
    adding entries one by one until the next would not fit gives, since a payload only
    grows with its entries. The run is found by bisection, a few packings a part instead
    of one per entry (a gateway splits its record every frame)."""
    if _fits(r, room):
        return [r]
    items: list[tuple[str, object]] = [("s", s) for s in r.samples]
    items += [("u", b) for b in r.unchanged] + [("m", b) for b in r.missing]
    if len(items) <= 1:
        raise ProtocolError("too_large", "one readout entry does not fit a frame")
    out: list[Readout] = []
    n = len(items)
    first = 0
    whole_fits = False  # whether items[first:] fits (not for the whole record: checked above)
    while first < n:
        if first and _fits(_part(r, items[first:]), room):
            whole_fits = True
            end = n
        else:
            lo, hi = first + 1, n - 1  # items[first:lo] is taken even when it does not fit
            while lo < hi:
                mid = (lo + hi + 1) // 2
                if _fits(_part(r, items[first:mid]), room):
                    lo = mid
                else:
                    hi = mid - 1
            end = lo
        out.append(_part(r, items[first:end]))
        first = end
    if not whole_fits and not _fits(out[-1], room):
        raise ProtocolError("too_large", "one readout entry does not fit a frame")
    return out


def _part(r: Readout, items: list[tuple[str, object]]) -> Readout:
    return Readout(r.index, r.rate, r.mode, r.oversampling,
                   tuple(x for k, x in items if k == "s"),  # type: ignore[misc]
                   tuple(x for k, x in items if k == "u"),  # type: ignore[misc]
                   tuple(x for k, x in items if k == "m"), r.span_us, 0, 1, r.root)  # type: ignore[misc]


__all__ = ["AGE_ROOM", "FrameReadout", "ReadoutConfig", "State", "record_parts"]
