"""The host's receive path for frames from any number of gateways.

Order matters: reassemble first, then filter duplicates of whole frames. Filtering
fragments one by one before reassembly loses a datagram whenever the faster gateway
lost its first fragment: its later fragments arrive first, find no open datagram
(``no_state``) and are marked seen, so the slower gateway's copies, which would
complete the datagram, are dropped as duplicates. Reassembling first lets every copy
of a fragment reach the :class:`Reassembler` (which drops repeats itself:
``duplicate_fragment``, ``late_duplicate``), and the :class:`DuplicateFilter` then
sees each whole frame once, as (origin, seq of its first fragment).

A BUNDLE is a hop's container, not a frame of its own to the host: two gateways may
bundle the same frames differently, so the frames inside are what is reassembled and
filtered.

A READOUT passes like DATA: reassembled when its record came fragmented, then filtered
by (origin, seq). Each part of a record is a frame of its own and is delivered on its
own; joining the parts, and the gateways' records of one skin frame, is the caller's.

A READOUT_SAME goes from a bridge to its parent only, numbered from the bridge's link
numbering, not the host's: one that reaches the host (forged, or relayed by a bridge that
could not read it; alone, fragmented or bundled) is counted (``readout_same``) and
dropped before the duplicate filter, where its (origin, seq) would have marked a real
frame of that bridge's as a duplicate.
"""

from __future__ import annotations

from cellbridge.protocol.dedupe import DuplicateFilter
from cellbridge.protocol.fragment import Reassembler
from cellbridge.protocol.frame import Frame
from cellbridge.protocol.messages import Bundle, Data, Hello, Readout, ReadoutSame


class HostReceiver:
    """``receive(frame, now)``: the frames to deliver, each once, from one decoded frame."""

    def __init__(self, dedupe: DuplicateFilter | None = None, reassembler: Reassembler | None = None) -> None:
        self.dedupe = dedupe if dedupe is not None else DuplicateFilter()
        self.reassembler = reassembler if reassembler is not None else Reassembler()
        self.readout_same = 0  #: READOUT_SAMEs dropped (a bridge-to-parent frame: none is the host's)

    def receive(self, frame: Frame, now: float) -> list[Frame]:
        """Frames completed by ``frame`` and not seen before (``now``: seconds, for reassembly)."""
        p = frame.payload
        if type(p) is Readout or type(p) is Data:  # (whole messages, most frames: nothing to reassemble)
            whole = frame
        else:
            if isinstance(p, Bundle):
                return [f for inner in p.frames for f in self.receive(inner, now)]
            got = self.reassembler.receive(frame, now)
            if got is None:
                return []
            whole = got
            p = whole.payload
            if type(p) is ReadoutSame:
                self.readout_same += 1
                return []
        hello = isinstance(p, Hello)
        if self.dedupe.is_duplicate(whole.origin, whole.seq, hello, p.boots or None if hello else None):  # type: ignore[union-attr]  # boots is read only when p is a Hello
            return []
        return [whole]

    def counters(self) -> dict[str, object]:
        return {"dedupe": self.dedupe.counters(), "reassembly": self.reassembler.counters(),
                "readout_same": self.readout_same}
