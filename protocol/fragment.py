"""Fragmentation of large datagrams and their bounded reassembly.

A datagram whose frame would exceed :data:`MAX_FRAME` travels as several fragment
frames. Each fragment is a frame of its own with its own sequence number (so
per-hop acknowledgement and duplicate filtering treat fragments like any other
frame); the fragment fields (tag, offset, total) tie it to its datagram.

Reassembly runs on the host, fed by links that lose, repeat and reorder frames
and that may carry garbage. Its state is therefore bounded in every dimension:
slots per origin, slots in all, bytes per slot (``total`` <= MAX_DATAGRAM), age
(``timeout``), and the memory of recently completed datagrams. The first
fragment (offset 0) opens a slot; a later fragment with no open slot is dropped,
so a stream of stray fragments cannot make the reassembler allocate anything.
"""

from __future__ import annotations

import math
from collections import Counter, OrderedDict
from dataclasses import dataclass, field

from cellbridge.protocol.crc import crc16
from cellbridge.protocol.errors import ProtocolError
from cellbridge.protocol.frame import (
    CRC_LEN,
    DATAGRAM_CRC_LEN,
    FRAG_LEN,
    HEADER_LEN,
    MAX_DATAGRAM,
    MAX_FRAME,
    Fragment,
    Frame,
    check_origin,
)
from cellbridge.protocol.messages import FrameType, pack_payload, unpack_payload


def fragment(frame: Frame, tag: int, max_frame: int = MAX_FRAME) -> list[Frame]:
    """Split ``frame`` into frames of at most ``max_frame`` bytes.

    A frame that fits is returned alone, unchanged. Otherwise the datagram is the
    payload followed by its CRC-16 (big-endian), cut into slices of equal length
    (the last may be shorter); fragment *i* gets sequence number ``frame.seq + i``
    (mod 2**16): the caller advances its sequence counter by ``len(result)``.
    ``tag`` must be unique per origin among datagrams in flight. The checksum and
    the consecutive numbers are what let the receiver refuse to splice fragments
    of two datagrams that share a tag. A BUNDLE is never fragmented.
    """
    if isinstance(frame.payload, Fragment):
        raise ProtocolError("fragment", "frame is already a fragment")
    body = pack_payload(frame.payload)
    if HEADER_LEN + len(body) + CRC_LEN <= max_frame:
        return [frame]
    if frame.type is FrameType.BUNDLE:
        raise ProtocolError("fragment", "a bundle must fit one frame; it is never fragmented")
    body += crc16(body).to_bytes(DATAGRAM_CRC_LEN, "big")
    if len(body) > MAX_DATAGRAM:
        raise ProtocolError("too_large", f"datagram of {len(body)} bytes (with checksum) exceeds {MAX_DATAGRAM}")
    step = max_frame - HEADER_LEN - FRAG_LEN - CRC_LEN
    if step < 1 or max_frame > MAX_FRAME:
        raise ProtocolError("fragment", f"max_frame must be in {HEADER_LEN + FRAG_LEN + CRC_LEN + 1}..{MAX_FRAME}")
    return [
        Frame(frame.src, frame.dst, frame.origin, (frame.seq + i) & 0xFFFF,
              Fragment(frame.type, tag, off, len(body), body[off:off + step]),
              frame.hops, frame.cost, frame.flags)
        for i, off in enumerate(range(0, len(body), step))
    ]


@dataclass(slots=True)
class _Slot:
    head: Frame  # the fragment at offset 0: its header becomes the datagram's header
    started: float
    step: int  # bytes in every fragment but the last (the head's slice length)
    pieces: dict[int, bytes] = field(default_factory=dict)  # offset -> slice
    received: int = 0


@dataclass(slots=True)
class _Done:
    """A completed datagram, remembered so that late copies of its fragments are recognised."""

    completed: float
    step: int
    head_crc: int  # CRC-16 of the head slice: a reset bridge may reuse (tag, head seq) for other bytes


class Reassembler:
    """Sans-I/O reassembly: ``receive(frame, now)`` returns a whole frame or ``None``.

    Unfragmented frames pass straight through. A datagram is named by (origin, tag)
    while in flight, and remembered after completion by (origin, tag, seq of its
    head fragment) with a CRC of the head's bytes, so a reset bridge that reuses a
    tag (even with the same head seq) starts a new datagram. A
    fragment belongs to an open datagram only if it proves it: the fragment at
    offset ``k * step`` has seq ``head.seq + k`` (mod 2**16), where ``step`` is the
    head's slice length, and every slice but the last is ``step`` bytes long.

    ``drops`` counts by cause; fragment events: ``no_state`` (non-first fragment
    with no open datagram), ``late_duplicate`` (fragment of a datagram completed
    recently), ``duplicate_fragment`` (same slice again), ``mismatch`` (a fragment
    with the datagram's tag that does not belong to it: the tail of another
    datagram); datagram events: ``timeout``, ``evicted`` (slot limit reached,
    oldest given up), ``replaced`` (a new head with the same tag but another seq
    abandons the incomplete datagram), ``reset`` (given up by ``reset(origin)``),
    ``conflict`` (same fragment with other bytes, or another total, type or version),
    ``checksum`` (the reassembled bytes fail the datagram's CRC-16: fragments of
    different datagrams), ``payload`` (reassembled bytes are not a valid payload).

    ``now`` must be finite. Times are kept on an internal clock that never goes back:
    a reading up to ``clock_jitter`` behind the latest (readers' timestamps merged out
    of order) is that same instant, so jitter never ages anything; a reading further
    back is a step of the clock (``clock_steps``), followed without going back, so
    ages are kept and nothing outlives its limit. Both cost O(1).
    """

    def __init__(self, max_per_origin: int = 4, max_slots: int = 64, timeout: float = 2.0,
                 remember: int = 32, remember_for: float = 10.0, remember_origins: int = 1024,
                 clock_jitter: float = 0.25) -> None:
        if min(max_per_origin, max_slots, remember, remember_origins) < 1 or not (
                0 < timeout < math.inf and 0 < remember_for < math.inf and 0 <= clock_jitter < math.inf):
            raise ValueError("limits must be positive and finite")
        self.max_per_origin = max_per_origin
        self.max_slots = max_slots
        self.timeout = timeout
        self.remember = remember  #: completed datagrams remembered per origin
        self.remember_for = remember_for
        self.remember_origins = remember_origins
        self.clock_jitter = clock_jitter
        self._slots: OrderedDict[tuple[int, int], _Slot] = OrderedDict()  # oldest first
        self._per_origin: Counter[int] = Counter()
        # origin -> (tag, head seq) -> completion, oldest first; origins least recently completed first
        self._recent: OrderedDict[int, OrderedDict[tuple[int, int], _Done]] = OrderedDict()
        self._now = -math.inf  # internal time: the caller's plus _offset, never decreasing
        self._offset = 0.0
        self.drops: Counter[str] = Counter()
        self.completed = 0
        self.clock_steps = 0
        self.forgotten = 0  #: completions forgotten before ``remember_for`` to keep memory bounded

    @property
    def slot_count(self) -> int:
        return len(self._slots)

    @property
    def recent_count(self) -> int:
        return sum(len(done) for done in self._recent.values())

    def _clock(self, now: float) -> float:
        """The internal time for the caller's ``now``."""
        if not math.isfinite(now):
            raise ValueError(f"now must be a finite time in seconds, got {now!r}")
        t = now + self._offset
        if t < self._now:
            if self._now - t > self.clock_jitter:  # a step back, not jitter: continue from here
                self._offset += self._now - t
                self.clock_steps += 1
            return self._now
        self._now = t
        return t

    def expire(self, now: float) -> None:
        """Give up datagrams older than ``timeout`` and forget old completions."""
        now = self._clock(now)
        while self._slots:
            key, slot = next(iter(self._slots.items()))
            if now - slot.started < self.timeout:
                break
            self._drop(key, "timeout")
        while self._recent:
            origin, done = next(iter(self._recent.items()))
            while done and now - next(iter(done.values())).completed >= self.remember_for:
                done.popitem(last=False)
            if done:
                break  # origins are ordered by their latest completion: the rest are younger
            del self._recent[origin]

    def _release(self, key: tuple[int, int]) -> _Slot:
        slot = self._slots.pop(key)
        self._per_origin[key[0]] -= 1
        if not self._per_origin[key[0]]:
            del self._per_origin[key[0]]
        return slot

    def _drop(self, key: tuple[int, int], cause: str) -> None:
        self._release(key)
        self.drops[cause] += 1

    def receive(self, frame: Frame, now: float) -> Frame | None:
        frag = frame.payload
        if not isinstance(frag, Fragment):
            return frame
        self.expire(now)
        origin = frame.origin
        key = (origin, frag.tag)
        slot = self._slots.get(key)
        if frag.offset == 0:
            if slot is not None and slot.head.seq != frame.seq:
                self._drop(key, "replaced")
                slot = None
            if slot is None:
                if self._is_done(origin, frag.tag, frame.seq, frag.data):
                    self.drops["late_duplicate"] += 1
                    return None
                self._make_room(origin)
                slot = self._slots[key] = _Slot(frame, self._now, len(frag.data))
                self._per_origin[origin] += 1
        elif slot is None:
            done = self._recent.get(origin)
            if done and any(t == frag.tag and self._fresh(d) and _belongs(frame, frag, s, d.step)
                            for (t, s), d in done.items()):
                self.drops["late_duplicate"] += 1
            else:
                self.drops["no_state"] += 1
            return None
        elif not _belongs(frame, frag, slot.head.seq, slot.step):
            self.drops["mismatch"] += 1
            return None
        head = slot.head.payload
        assert isinstance(head, Fragment)
        if frag.total != head.total or frag.frame_type != head.frame_type or frag.version != head.version:
            self._drop(key, "conflict")
            return None
        return self._insert(key, slot, frag)

    def reset(self, origin: int) -> None:
        """Forget ``origin``'s open and completed datagrams (it restarted: its tags and seqs begin again)."""
        for key in [k for k in self._slots if k[0] == origin]:
            self._drop(key, "reset")
        self._recent.pop(origin, None)

    def _is_done(self, origin: int, tag: int, seq: int, head: bytes) -> bool:
        done = self._recent.get(origin)
        d = done.get((tag, seq)) if done is not None else None
        return d is not None and self._fresh(d) and d.head_crc == crc16(head)

    def _fresh(self, done: _Done) -> bool:
        """Completed less than ``remember_for`` ago (expiry is lazy: ``expire`` stops early)."""
        return self._now - done.completed < self.remember_for

    def _make_room(self, origin: int) -> None:
        if self._per_origin[origin] >= self.max_per_origin:
            oldest = next(k for k in self._slots if k[0] == origin)
            self._drop(oldest, "evicted")
        if len(self._slots) >= self.max_slots:
            self._drop(next(iter(self._slots)), "evicted")

    def _insert(self, key: tuple[int, int], slot: _Slot, frag: Fragment) -> Frame | None:
        old = slot.pieces.get(frag.offset)
        if old is not None:
            if old == frag.data:
                self.drops["duplicate_fragment"] += 1
            else:
                self._drop(key, "conflict")
            return None
        # Slices at multiples of step, all step long but the last, which ends at total:
        # they cannot overlap, so once their lengths add up to total there is no gap.
        slot.pieces[frag.offset] = frag.data
        slot.received += len(frag.data)
        head = slot.head
        if slot.received < frag.total:
            return None
        body = b"".join(slot.pieces[o] for o in sorted(slot.pieces))
        self._release(key)  # (pieces stay readable on the released slot)
        self._remember(head.origin, (key[1], head.seq),
                       _Done(self._now, slot.step, crc16(slot.pieces[0])))
        body, check = body[:-DATAGRAM_CRC_LEN], body[-DATAGRAM_CRC_LEN:]
        if len(check) < DATAGRAM_CRC_LEN or crc16(body).to_bytes(DATAGRAM_CRC_LEN, "big") != check:
            self.drops["checksum"] += 1
            return None
        try:
            payload = unpack_payload(frag.frame_type, body, frag.version)
            check_origin(head.origin, payload)
        except ProtocolError:
            self.drops["payload"] += 1
            return None
        self.completed += 1
        return Frame(head.src, head.dst, head.origin, head.seq, payload, head.hops, head.cost, head.flags)

    def _remember(self, origin: int, name: tuple[int, int], done: _Done) -> None:
        per = self._recent.pop(origin, None)
        if per is None:
            per = OrderedDict()
            if len(self._recent) >= self.remember_origins:
                self.forgotten += len(self._recent.popitem(last=False)[1])
        self._recent[origin] = per  # most recently completed origin last
        per.pop(name, None)
        per[name] = done
        if len(per) > self.remember:
            per.popitem(last=False)
            self.forgotten += 1

    def counters(self) -> dict[str, object]:
        return {"completed": self.completed, "open": len(self._slots), "remembered": self.recent_count,
                "forgotten": self.forgotten, "clock_steps": self.clock_steps, "drops": dict(self.drops)}


def _belongs(frame: Frame, frag: Fragment, head_seq: int, step: int) -> bool:
    """Whether a non-head fragment is the one its datagram's head announces at its offset."""
    index, rest = divmod(frag.offset, step)
    n = len(frag.data)
    return (rest == 0 and frame.seq == (head_seq + index) & 0xFFFF
            and (n == step if frag.offset + n < frag.total else n <= step))
