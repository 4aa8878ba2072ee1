"""Duplicate filter over (origin, seq): the host's.

(A relay catches copies by time instead: :mod:`cellbridge.protocol.copies`. A restart's
HELLO reaches only the relays on its path, and a numbering window elsewhere would take
the new boot's frames for the last boot's.)

Frames reach the host twice when a link ACK is lost and the hop retransmits, or
when two gateways both hear a bridge (one path may run far behind the other). The
filter keeps, per origin, the highest sequence number seen and a bit mask of the
``window`` numbers below it, so its memory is ``max_origins`` small records
whatever arrives. Sequence numbers are 16-bit and wrap (serial-number arithmetic:
"ahead" means less than 2**15 ahead).

A number more than ``window`` behind the highest is **stale**: a late copy, dropped
and counted, never a reason to reopen the window. A bridge that resets starts
numbering at 0 again, so a restart is taken only from evidence:

- a HELLO (``is_duplicate(..., hello=True)``) numbered 0 whose number was already
  seen or is stale restarts the origin's window at 0, unless it repeats the last
  HELLO and that origin has sent fewer than ``hello_guard`` frames since (the same
  HELLO heard through a second gateway). A restarting bridge numbers from 0 and
  sends its HELLO first, so a HELLO with another number was sent on request: a
  late copy of it is a copy, however late. A HELLO that is ahead, or inside the
  window and unseen, is an ordinary new frame;
- ``restart_run`` stale frames in a row with consecutive numbers (gaps of at most
  ``_RUN_GAP``), the first below ``window``, with no accepted frame in between:
  a reset whose HELLO was lost. Those first frames are dropped as stale;
- a HELLO's boot counter (protocol version 2): a different one from the origin's last
  is a restart wherever its number falls; the same one marks a copy of that boot's
  HELLO (a late or repeated copy), never a restart;
- ``reset(origin)``, for a caller that knows better (a bridge replaced, a link
  re-plugged).

After a HELLO or run restart the old window is kept while the new numbering is
young (``window`` frames): a gateway running behind still replays the old numbering,
and those copies look *ahead* of the new one. A frame more than ``_NEAR`` ahead that
the old window saw is such a copy: a duplicate, not a reason to jump back.

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
_NEAR = 32  #: a numbering advances in small steps: a frame further ahead may be from before a restart


class _Origin:
    """Window of one origin plus the evidence gathered for a restart."""

    __slots__ = ("highest", "mask", "hello", "run_last", "run_mask", "run_len", "old_highest", "old_mask",
                 "since", "boot")

    def __init__(self, seq: int, hello: bool) -> None:
        self.highest = seq
        self.mask = 1
        self.hello = seq if hello else -1  #: seq of the HELLO that began this numbering
        self.run_len = 0  #: members of the current restart candidate run (0: none)
        self.run_last = 0
        self.run_mask = 0
        self.old_mask = 0  #: window of the numbering before the last restart (0: none kept)
        self.old_highest = 0
        self.since = 0  #: seq the window restarted at
        self.boot = -1  #: boot counter of the origin's last HELLO (-1: none known)


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

    def is_duplicate(self, origin: int, seq: int, hello: bool = False, boot: int | None = None) -> bool:
        """True when the frame (origin, seq) must be dropped; ``hello``: the frame is a HELLO,
        ``boot``: its boot counter (protocol version 2). A HELLO whose boot counter differs
        from the last one this origin announced is a restart, by evidence: the numbering
        begins again there, however close its number is to the last boot's. A HELLO numbered 0
        with the boot counter this origin last announced is a copy of that boot's HELLO (a
        late or repeated copy), however late: never a restart."""
        st = self._state.get(origin)
        if st is None:
            if len(self._state) >= self.max_origins:
                self._state.popitem(last=False)
                self.evicted_origins += 1
            st = self._state[origin] = _Origin(seq, hello)
            if hello and boot is not None:
                st.boot = boot
            return False
        self._state.move_to_end(origin)
        same_boot = False
        if hello and boot is not None:
            if st.boot >= 0 and boot != st.boot:
                st.boot = boot
                self._restart(st, seq, 1)
                st.hello = seq
                return False
            same_boot = st.boot == boot
            st.boot = boot
        ahead = (seq - st.highest) % _MOD
        if 0 < ahead < _HALF:  # newer: slide the window forward
            if st.old_mask:  # restarted lately: a lagging gateway may still replay the old numbering
                if (st.highest - st.since) % _MOD >= self.window:
                    st.old_mask = 0
                elif ahead > _NEAR and st.old_mask >> ((st.old_highest - seq) % _MOD) & 1:
                    self.duplicates += 1
                    return True
            st.mask = ((st.mask << ahead) | 1) & self._full
            st.highest = seq
            st.run_len = 0
            if hello:
                st.hello = seq
            elif st.hello >= 0 and (seq - st.hello) % _MOD >= self.hello_guard:
                st.hello = -1  # past the guard for good: after a wrap its number is the next boot's HELLO
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
        if hello and not seq and not same_boot and not (seq == st.hello and behind < self.hello_guard):
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
        st.old_highest, st.old_mask, st.since = st.highest, st.mask, seq
        st.highest, st.mask, st.run_len, st.hello = seq, mask, 0, -1
