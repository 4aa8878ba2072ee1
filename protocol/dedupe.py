"""Duplicate filter over (origin, seq).

Frames reach the host twice when a link ACK is lost and the hop retransmits, or
when two gateways both hear a bridge (one path may run far behind the other). The
filter keeps, per origin, the highest sequence number seen and a bit mask of the
``window`` numbers below it, so its memory is ``max_origins`` small records
whatever arrives. Sequence numbers are 16-bit and wrap (serial-number arithmetic:
"ahead" means less than 2**15 ahead).

A number more than ``window`` behind the highest is **stale**: a late copy, dropped
and counted, never a reason to reopen the window. A bridge that resets starts
numbering at 0 again, so a restart is taken only from evidence:

- a HELLO (``is_duplicate(..., hello=True)``) whose number was already seen or is
  stale restarts the origin's window at its number, unless it repeats the last
  HELLO and that origin has sent fewer than ``hello_guard`` frames since (the same
  HELLO heard through a second gateway). A HELLO that is ahead, or inside the
  window and unseen, is an ordinary new frame;
- ``restart_run`` stale frames in a row with consecutive numbers (gaps of at most
  ``_RUN_GAP``), the first below ``window``, with no accepted frame in between:
  a reset whose HELLO was lost. Those first frames are dropped as stale;
- ``reset(origin)``, for a caller that knows better (a bridge replaced, a link
  re-plugged).

A reset seen without its HELLO while the old numbering is still inside the window
replays numbers the window holds: those frames are dropped as duplicates until
the new numbering passes the old highest (at most ``window`` frames). The same
(origin, seq, HELLO) events can also come from a HELLO copy that lags by more
than ``hello_guard`` frames: that copy is taken as a restart.
"""

from __future__ import annotations

from collections import OrderedDict

_HALF = 0x8000
_MOD = 0x10000
_RUN_GAP = 4  #: lost frames tolerated between two members of a restart run


class _Origin:
    """Window of one origin plus the evidence gathered for a restart."""

    __slots__ = ("highest", "mask", "hello", "run_last", "run_mask", "run_len")

    def __init__(self, seq: int, hello: bool) -> None:
        self.highest = seq
        self.mask = 1
        self.hello = seq if hello else -1  #: seq of the HELLO that began this numbering
        self.run_len = 0  #: members of the current restart candidate run (0: none)
        self.run_last = 0
        self.run_mask = 0


class DuplicateFilter:
    """``is_duplicate(origin, seq)`` is True for a frame to drop (a repeat or stale), else records it."""

    def __init__(self, window: int = 256, max_origins: int = 4096, restart_run: int = 8,
                 hello_guard: int = 16) -> None:
        if not 1 <= window < _HALF or max_origins < 1:
            raise ValueError(f"window must be in 1..{_HALF - 1} and max_origins >= 1")
        if restart_run < 2 or hello_guard < 0:
            raise ValueError(f"restart_run must be >= 2 and hello_guard >= 0, got {restart_run}, {hello_guard}")
        self.window = window
        self.max_origins = max_origins
        self.restart_run = restart_run
        self.hello_guard = hello_guard
        self._full = (1 << window) - 1
        self._state: OrderedDict[int, _Origin] = OrderedDict()  # least recently heard first
        self.duplicates = 0
        self.stale = 0
        self.restarts = 0
        self.evicted_origins = 0

    def __len__(self) -> int:
        return len(self._state)

    def reset(self, origin: int) -> None:
        """Forget ``origin``: its next frame starts a new window, whatever its number."""
        self._state.pop(origin, None)

    def counters(self) -> dict[str, int]:
        return {"origins": len(self._state), "duplicates": self.duplicates, "stale": self.stale,
                "restarts": self.restarts, "evicted_origins": self.evicted_origins}

    def is_duplicate(self, origin: int, seq: int, hello: bool = False) -> bool:
        """True when the frame (origin, seq) must be dropped; ``hello``: the frame is a HELLO."""
        st = self._state.get(origin)
        if st is None:
            if len(self._state) >= self.max_origins:
                self._state.popitem(last=False)
                self.evicted_origins += 1
            self._state[origin] = _Origin(seq, hello)
            return False
        self._state.move_to_end(origin)
        ahead = (seq - st.highest) % _MOD
        if 0 < ahead < _HALF:  # newer: slide the window forward
            st.mask = ((st.mask << ahead) | 1) & self._full
            st.highest = seq
            st.run_len = 0
            if hello:
                st.hello = seq
            return False
        behind = (_MOD - ahead) % _MOD
        bit = 1 << behind if behind < self.window else 0
        if bit and not st.mask & bit:  # inside the window, not seen yet: new (a HELLO reordered)
            st.mask |= bit
            st.run_len = 0
            if hello:
                st.hello = seq
            return False
        # Seen or stale: a repeat, unless a HELLO says the origin numbers again.
        if hello and not (seq == st.hello and behind < self.hello_guard):
            self._restart(st, seq, 1)
            st.hello = seq
            return False
        if not bit:
            return self._stale(st, seq)
        self.duplicates += 1
        return True

    def _stale(self, st: _Origin, seq: int) -> bool:
        """Count a stale frame, and restart the origin once stale frames form a run."""
        self.stale += 1
        if st.run_len:
            step = (seq - st.run_last) % _MOD
            if 0 < step <= _RUN_GAP:
                st.run_mask = ((st.run_mask << step) | 1) & self._full
                st.run_last = seq
                st.run_len += 1
                if st.run_len >= self.restart_run:
                    self.stale -= 1  # this one is delivered
                    self._restart(st, seq, st.run_mask)
                    return False
                return True
            if (st.run_last - seq) % _MOD < self.window and st.run_mask >> ((st.run_last - seq) % _MOD) & 1:
                return True  # a copy of a run member: neither extends nor breaks the run
        if seq < self.window:
            st.run_len, st.run_last, st.run_mask = 1, seq, 1
        else:
            st.run_len = 0
        return True

    def _restart(self, st: _Origin, seq: int, mask: int) -> None:
        self.restarts += 1
        st.highest, st.mask, st.run_len, st.hello = seq, mask, 0, -1
