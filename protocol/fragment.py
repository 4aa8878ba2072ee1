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

import bisect
from collections import Counter, OrderedDict
from dataclasses import dataclass, field

from cellbridge.protocol.errors import ProtocolError
from cellbridge.protocol.frame import (
    CRC_LEN,
    FRAG_LEN,
    HEADER_LEN,
    MAX_DATAGRAM,
    MAX_FRAME,
    Fragment,
    Frame,
)
from cellbridge.protocol.messages import pack_payload, unpack_payload


def fragment(frame: Frame, tag: int, max_frame: int = MAX_FRAME) -> list[Frame]:
    """Split ``frame`` into frames of at most ``max_frame`` bytes.

    A frame that fits is returned alone, unchanged. Otherwise fragment *i* gets
    sequence number ``frame.seq + i`` (mod 2**16): the caller advances its
    sequence counter by ``len(result)``. ``tag`` must be unique per origin among
    datagrams in flight.
    """
    if isinstance(frame.payload, Fragment):
        raise ProtocolError("fragment", "frame is already a fragment")
    body = pack_payload(frame.payload)
    if HEADER_LEN + len(body) + CRC_LEN <= max_frame:
        return [frame]
    if len(body) > MAX_DATAGRAM:
        raise ProtocolError("too_large", f"datagram of {len(body)} bytes exceeds {MAX_DATAGRAM}")
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
    head: Frame  # the first fragment: its header becomes the datagram's header
    started: float
    offsets: list[int] = field(default_factory=list)  # sorted
    pieces: dict[int, bytes] = field(default_factory=dict)
    received: int = 0


class Reassembler:
    """Sans-I/O reassembly: ``receive(frame, now)`` returns a whole frame or ``None``.

    Unfragmented frames pass straight through. ``drops`` counts by cause; fragment
    events: ``no_state`` (non-first fragment with no open slot), ``late_duplicate``
    (fragment of a datagram completed recently), ``duplicate_fragment`` (same slice
    again); datagram events: ``timeout``, ``evicted`` (slot limit reached, oldest
    given up), ``conflict`` (same offset with other bytes, or another total or type),
    ``overlap`` (slices that partly overlap), ``payload`` (reassembled bytes are not
    a valid payload).
    """

    def __init__(self, max_per_origin: int = 4, max_slots: int = 64, timeout: float = 2.0,
                 remember: int = 1024, remember_for: float = 10.0) -> None:
        if min(max_per_origin, max_slots, remember) < 1 or timeout <= 0 or remember_for <= 0:
            raise ValueError("limits must be positive")
        self.max_per_origin = max_per_origin
        self.max_slots = max_slots
        self.timeout = timeout
        self.remember = remember
        self.remember_for = remember_for
        self._slots: OrderedDict[tuple[int, int], _Slot] = OrderedDict()  # oldest first
        self._per_origin: Counter[int] = Counter()
        self._recent: OrderedDict[tuple[int, int], float] = OrderedDict()
        self.drops: Counter[str] = Counter()
        self.completed = 0

    @property
    def slot_count(self) -> int:
        return len(self._slots)

    @property
    def recent_count(self) -> int:
        return len(self._recent)

    def expire(self, now: float) -> None:
        """Give up datagrams older than ``timeout`` and forget old completions."""
        while self._slots:
            key, slot = next(iter(self._slots.items()))
            if now - slot.started < self.timeout:
                break
            self._drop(key, "timeout")
        while self._recent:
            key, when = next(iter(self._recent.items()))
            if now - when < self.remember_for and len(self._recent) <= self.remember:
                break
            del self._recent[key]

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
        key = (frame.origin, frag.tag)
        if key in self._recent:
            self.drops["late_duplicate"] += 1
            return None
        slot = self._slots.get(key)
        if slot is None:
            if frag.offset != 0:
                self.drops["no_state"] += 1
                return None
            self._make_room(frame.origin)
            slot = self._slots[key] = _Slot(frame, now)
            self._per_origin[frame.origin] += 1
        else:
            head = slot.head.payload
            assert isinstance(head, Fragment)
            if frag.total != head.total or frag.frame_type != head.frame_type:
                self._drop(key, "conflict")
                return None
        return self._insert(key, slot, frag)

    def _make_room(self, origin: int) -> None:
        if self._per_origin[origin] >= self.max_per_origin:
            oldest = next(k for k in self._slots if k[0] == origin)
            self._drop(oldest, "evicted")
        if len(self._slots) >= self.max_slots:
            self._drop(next(iter(self._slots)), "evicted")

    def _insert(self, key: tuple[int, int], slot: _Slot, frag: Fragment) -> Frame | None:
        start, end = frag.offset, frag.offset + len(frag.data)
        old = slot.pieces.get(start)
        if old is not None:
            if old == frag.data:
                self.drops["duplicate_fragment"] += 1
            else:
                self._drop(key, "conflict")
            return None
        i = bisect.bisect_left(slot.offsets, start)
        if i > 0:
            prev = slot.offsets[i - 1]
            if prev + len(slot.pieces[prev]) > start:
                self._drop(key, "overlap")
                return None
        if i < len(slot.offsets) and slot.offsets[i] < end:
            self._drop(key, "overlap")
            return None
        slot.offsets.insert(i, start)
        slot.pieces[start] = frag.data
        slot.received += len(frag.data)
        head = slot.head
        total = head.payload.total  # type: ignore[union-attr]
        if slot.received < total:
            return None
        # Complete: no gaps are possible, since slices do not overlap and sum to total.
        body = b"".join(slot.pieces[o] for o in slot.offsets)
        self._release(key)
        self._recent[key] = slot.started
        self._recent.move_to_end(key)
        while len(self._recent) > self.remember:
            self._recent.popitem(last=False)
        try:
            payload = unpack_payload(frag.frame_type, body)
        except ProtocolError:
            self.drops["payload"] += 1
            return None
        self.completed += 1
        return Frame(head.src, head.dst, head.origin, head.seq, payload, head.hops, head.cost, head.flags)

    def counters(self) -> dict[str, object]:
        return {"completed": self.completed, "open": len(self._slots), "drops": dict(self.drops)}

