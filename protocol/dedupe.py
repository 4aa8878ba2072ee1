"""Duplicate filter over (origin, seq).

Frames reach the host twice when a link ACK is lost and the hop retransmits, or
when two gateways both hear a bridge. The filter keeps, per origin, the highest
sequence number seen and a bit mask of the ``window`` numbers below it, so its
memory is ``max_origins`` small records whatever arrives. Sequence numbers are
16-bit and wrap; a number more than ``window`` behind the highest (a bridge that
reset and started again from 0) is taken as new and restarts that origin's window,
and counted as ``restarts``.
"""

from __future__ import annotations

from collections import OrderedDict

_HALF = 0x8000
_MOD = 0x10000


class DuplicateFilter:
    """``is_duplicate(origin, seq)`` is True for a repeat within the window, else records it."""

    def __init__(self, window: int = 256, max_origins: int = 4096) -> None:
        if not 1 <= window < _HALF or max_origins < 1:
            raise ValueError(f"window must be in 1..{_HALF - 1} and max_origins >= 1")
        self.window = window
        self.max_origins = max_origins
        self._state: OrderedDict[int, tuple[int, int]] = OrderedDict()  # origin -> (highest, mask)
        self.duplicates = 0
        self.restarts = 0
        self.evicted_origins = 0

    def __len__(self) -> int:
        return len(self._state)

    def is_duplicate(self, origin: int, seq: int) -> bool:
        state = self._state.get(origin)
        if state is None:
            if len(self._state) >= self.max_origins:
                self._state.popitem(last=False)
                self.evicted_origins += 1
            self._state[origin] = (seq, 1)
            return False
        self._state.move_to_end(origin)
        highest, mask = state
        ahead = (seq - highest) % _MOD
        if ahead == 0:
            self.duplicates += 1
            return True
        if ahead < _HALF:  # newer: slide the window forward
            mask = ((mask << ahead) | 1) & ((1 << self.window) - 1)
            self._state[origin] = (seq, mask)
            return False
        behind = _MOD - ahead
        if behind >= self.window:  # far behind: the origin restarted its numbering
            self.restarts += 1
            self._state[origin] = (seq, 1)
            return False
        bit = 1 << behind
        if mask & bit:
            self.duplicates += 1
            return True
        self._state[origin] = (highest, mask | bit)
        return False
