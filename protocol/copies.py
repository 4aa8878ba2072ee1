"""A relay's memory of the frames it forwarded lately: copies are told from new frames by time.

A forwarding bridge sees a frame twice when its acknowledgement to the previous hop was
lost or late (the hop sends it again, perhaps via another neighbour) or when the frame
went round a routing loop. Both copies come soon: within the retries of one hop, or the
few hops of a loop. So a relay remembers each (origin, seq) it forwarded for
``max_age`` and drops what it sees again within that time; older copies go on and the
host's :class:`~cellbridge.protocol.DuplicateFilter` (the one with the whole window and
every gateway's view) drops them there.

Why not the host's window at every relay: a bridge that resets numbers from 0 again and
announces it with its HELLO (seq 0, its boot counter), but that HELLO travels one path.
A relay on another path (the bridge changed parent after its HELLO left, or moved to a
second gateway) never saw it; a numbering window there still held the last boot's
numbers and dropped the new boot's 1, 2, ... as duplicates until they passed the old
highest: seconds of a bridge's samples lost behind a healthy route. Memory by time
cannot mistake a new boot for an old one unless the old boot's same numbers passed
within ``max_age`` (a bridge reset within about ``max_age`` of its boot), and a HELLO
with a new boot counter clears its origin here anyway.

Sans-I/O: ``now`` is the caller's clock in any unit, ``max_age`` in the same unit.
Memory is bounded by ``capacity`` frames (oldest forgotten first, ``forgotten``).
"""

from __future__ import annotations

from collections import OrderedDict


class RecentFrames:
    """``first(origin, seq, hops, now)``: the hop count of the earlier copy of a frame
    forwarded within ``max_age``, or None for a frame to forward (then remembered)."""

    def __init__(self, max_age: int, capacity: int = 1024) -> None:
        if max_age <= 0 or capacity < 1:
            raise ValueError(f"max_age must be > 0 and capacity >= 1, got {max_age}, {capacity}")
        self.max_age = max_age
        self.capacity = capacity
        self._frames: OrderedDict[tuple[int, int], tuple[int, int]] = OrderedDict()  # key -> (when, hops)
        self._boots: OrderedDict[int, int] = OrderedDict()  # origin -> boot counter of its last HELLO
        self.copies = 0
        self.boots = 0
        self.forgotten = 0  #: frames forgotten for room before their time (capacity too small for the traffic)

    def __len__(self) -> int:
        return len(self._frames)

    def first(self, origin: int, seq: int, hops: int, now: int, boot: int | None = None) -> int | None:
        """None when (origin, seq) was not forwarded within ``max_age`` before ``now``: the
        caller forwards it, and it is remembered with ``hops``. Otherwise the hop count of
        its first copy (more hops now: it went round a loop). ``boot``: a HELLO's boot
        counter; a different one from the origin's last clears what is held of its frames,
        since its numbering began again."""
        frames = self._frames
        limit = now - self.max_age
        while frames:
            key, (when, _) = next(iter(frames.items()))
            if when >= limit:
                break
            del frames[key]
        if boot is not None:
            last = self._boots.pop(origin, None)
            self._boots[origin] = boot
            if len(self._boots) > self.capacity:
                self._boots.popitem(last=False)
            if last is not None and last != boot:
                self.boots += 1
                for key in [k for k in frames if k[0] == origin]:
                    del frames[key]
        key = (origin, seq)
        got = frames.get(key)
        if got is not None:
            self.copies += 1
            return got[1]
        frames[key] = (now, hops)
        if len(frames) > self.capacity:
            frames.popitem(last=False)
            self.forgotten += 1
        return None

    def remember(self, origin: int, seq: int, hops: int, now: int) -> None:
        """Hold (origin, seq) again as forwarded at ``now`` with ``hops`` (a relay that sends a
        frame on once more: its next copy is measured against this one)."""
        self._frames.pop((origin, seq), None)
        self._frames[(origin, seq)] = (now, hops)
        if len(self._frames) > self.capacity:
            self._frames.popitem(last=False)
            self.forgotten += 1

    def counters(self) -> dict[str, int]:
        return {"held": len(self._frames), "copies": self.copies, "boots": self.boots, "forgotten": self.forgotten}
