"""Health bookkeeping, sans-I/O: per bridge, per element channel and per link.

Users of a skin that runs for days need the daemon to *tell the truth*: which bridge
went quiet, how much was lost and where, which channel is stuck or saturated. Every
number here is counted from the traffic itself; nothing is estimated that could be
counted.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from cellbridge.daemon.core.messages import LogEvent
from numpy.typing import NDArray

_SEQ_MOD = 0x10000
_SEQ_HALF = 0x8000
#: Bridges the layout does not place are listed one by one up to this many, beyond it only
#: counted. One corrupt frame in ~65 536 passes CRC-16 with a random origin, so a noisy line
#: makes thousands of phantoms; each would cost ~240 bytes in every health message (15 MB at
#: 65 530) until forgotten, and a log event each when they go quiet together.
UNPLACED_SHOWN = 64
#: ids -> (those the layout places, the others), in their order
Split = Callable[[Iterable[int]], tuple[list[int], list[int]]]


@dataclass(slots=True)
class BridgeHealth:
    """One bridge as seen from the host."""

    first_seen: float
    last_seen: float = 0.0
    link: str = ""
    frames: int = 0
    samples: int = 0
    lost: int = 0  # frames missing from the sequence (gaps), less those that arrived late
    late: int = 0
    seq_restarts: int = 0
    last_seq: int | None = None
    clock_resets: int = 0
    last_cycle: int = 0
    clock_hz: float = 0.0
    unmapped_samples: int = 0  # samples of elements the layout does not place
    index_rejected: int = 0  # mesh-time samples whose index put them after their own arrival
    rate: float = 0.0  # samples/s since the health before
    _samples_at_tick: int = 0
    silent: bool = False

    def tick(self, now: float, elapsed: float, timeout: float) -> bool:
        """A health tick ``elapsed`` s after the one before: the sample rate since then, and
        silent when not heard for ``timeout`` s. True when that silence changed."""
        self.rate = (self.samples - self._samples_at_tick) / elapsed
        self._samples_at_tick = self.samples
        silent = now - self.last_seen > timeout
        changed = silent != self.silent
        self.silent = silent
        return changed

    def frames_seen(self, seqs: list[int], window: int, boot: bool = False) -> None:
        """``boot``: the bridge's HELLO numbered 0 is among them (it restarted)."""
        for seq in seqs:
            self.frames += 1
            if self.last_seq is None:
                self.last_seq = seq
                continue
            ahead = (seq - self.last_seq) % _SEQ_MOD
            if ahead < _SEQ_HALF:
                self.lost += ahead - 1
                self.last_seq = seq
            elif _SEQ_MOD - ahead >= window or (boot and seq == 0):  # the bridge restarted its numbering
                self.seq_restarts += 1
                self.last_seq = seq
            else:  # an earlier gap filled in late
                self.late += 1
                self.lost = max(0, self.lost - 1)

    def report(self, now: float) -> dict[str, Any]:
        expected = self.frames + self.lost
        return {
            "link": self.link, "first_seen": self.first_seen, "last_seen": self.last_seen,
            "age": now - self.last_seen, "silent": self.silent, "frames": self.frames,
            "samples": self.samples, "sample_rate": self.rate, "lost": self.lost, "late": self.late,
            "loss": self.lost / expected if expected else 0.0, "seq_restarts": self.seq_restarts,
            "clock_resets": self.clock_resets, "t_bridge": self.last_cycle / self.clock_hz if self.clock_hz else None,
            "cycle": self.last_cycle, "unmapped_samples": self.unmapped_samples,
            "index_rejected": self.index_rejected,
        }


class ChannelHealth:
    """Stuck and saturated channels of the layout's elements, vectorised over a batch.

    A counter or ADC reading always jitters by a count or so; the same raw value for
    ``stuck_after`` seconds means a dead front end or a firmware that stopped sampling
    but keeps sending. Saturation: counter overflow with nothing plausible to unwrap, a
    dead oscillator, an ADC mean at a rail.
    """

    def __init__(self, n: int) -> None:
        self.last_raw = np.full((n, 2), -1, dtype=np.int64)
        self.changed_at = np.full((n, 2), np.nan)
        self.seen_at = np.full((n, 2), np.nan)
        self.saturated = np.zeros((n, 2), dtype=bool)
        self.saturated_samples = np.zeros((n, 2), dtype=np.int64)

    def adopt(self, old: ChannelHealth, rows: NDArray[np.int64], old_rows: NDArray[np.int64]) -> None:
        for name in ("last_raw", "changed_at", "seen_at", "saturated", "saturated_samples"):
            getattr(self, name)[rows] = getattr(old, name)[old_rows]

    def update(self, rows: NDArray[np.int64], raw: NDArray[np.int64], sat: NDArray[np.bool_],
               groups: tuple[NDArray[np.int64], NDArray[np.int64]], now: float) -> None:
        """``raw``, ``sat``: (k, 2) for the k samples of layout rows ``rows``; ``groups``:
        the distinct rows and the index of each one's newest sample."""
        uniq, last = groups
        if sat.any():  # rare; ufunc.at is slow enough to matter on every read
            np.add.at(self.saturated_samples, rows, sat.astype(np.int64))
        if uniq.shape[0] == rows.shape[0]:  # each row once (a skin frame): uniq is rows, each sample its newest
            moved = np.zeros(self.last_raw.shape, dtype=bool)
            moved[rows] = raw != self.last_raw[rows]
            self.last_raw[rows] = raw
            self.saturated[rows] = sat
            self.changed_at[moved] = now
            self.seen_at[rows] = now
            return
        newest = np.empty_like(self.last_raw)
        newest[uniq] = raw[last]
        moved = np.zeros(self.last_raw.shape, dtype=bool)
        moved[uniq] = newest[uniq] != self.last_raw[uniq]
        if uniq.shape[0] != rows.shape[0]:  # several samples of an element: any change among them
            varied = raw != newest[rows]
            if varied.any():
                r, c = np.nonzero(varied)
                moved[rows[r], c] = True
        self.last_raw[uniq] = newest[uniq]
        self.saturated[uniq] = sat[last]
        self.changed_at[moved] = now
        self.seen_at[uniq] = now

    def stuck(self, after: float) -> NDArray[np.bool_]:
        with np.errstate(invalid="ignore"):
            # Still reporting (seen since), yet unchanged for ``after``: a silent bridge is not "stuck".
            return (self.seen_at - self.changed_at >= after) & np.isfinite(self.changed_at)


@dataclass(slots=True)
class LinkHealth:
    url: str
    connected: bool = False
    connects: int = 0
    reconnects: int = 0
    last_error: str = ""
    connected_since: float | None = None
    last_data: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def set_state(self, connected: bool, now: float, error: str = "") -> None:
        if connected and not self.connected:
            self.connects += 1
            if self.connects > 1:
                self.reconnects += 1
            self.connected_since = now
        if not connected:
            self.connected_since = None
        self.connected = connected
        if error:
            self.last_error = error


def link_report(h: LinkHealth, counters: dict[str, Any]) -> dict[str, Any]:
    dropped = counters.get("frames_dropped", {})
    assert isinstance(dropped, dict)
    crc = int(dropped.get("crc", 0))
    framing = sum(int(v) for k, v in dropped.items() if k != "crc")
    return {
        "url": h.url, "connected": h.connected, "reconnects": h.reconnects, "last_error": h.last_error,
        "connected_since": h.connected_since, "last_data": h.last_data,
        "bytes": counters.get("bytes_in", 0), "frames": counters.get("frames_ok", 0),
        "crc_errors": crc, "framing_errors": framing, "frames_dropped": dropped,
        "bytes_dropped": counters.get("bytes_dropped", {}), "duplicates": counters.get("duplicates", 0),
        **h.extra,
    }



class HealthBook:
    """Every bridge and link the host heard from, as ``health`` reports them.

    The pipeline tells it what arrived (frames, samples, readout records speaking for a
    bridge, clock resets, links going up and down) and asks it, on a health tick, for the
    bridges gone silent or back (:meth:`tick`) and for those to forget (:meth:`forget`);
    :meth:`bridges_report` and :meth:`links_report` are the message's fields. All times
    are the pipeline's time base; the wall-clock offset is applied only to what is
    reported. Bridges the layout does not place (phantoms of a noisy line, strangers)
    cost a tick nothing once silent, and are forgotten after a while.
    """

    def __init__(self, clock_hz: float, links: Iterable[tuple[str, str]] = ()) -> None:
        self.clock_hz = clock_hz
        self.bridges: dict[int, BridgeHealth] = {}
        self.links: dict[str, LinkHealth] = {name: LinkHealth(url) for name, url in links}
        self.forgotten = 0
        self.started: float | None = None
        # Bridges whose rate or silence a health tick must look at: heard since, or not yet
        # silent with a rate of 0. A silent bridge costs the tick nothing (65 530 phantoms).
        self._awake: set[int] = set()
        self._forget_floor = -math.inf  # no bridge nor gateway id forget() could drop was last heard before this
        # bridges the readout records spoke for (a sample or unchanged) since the last fold:
        # when and on which link (the newest record's), and how many samples; folded into
        # their health when it is read (fold). Dicts filled in C (dict.fromkeys): a record
        # part costs no array operation
        self._heard: dict[int, tuple[float, int]] = {}
        self._heard_samples: dict[int, int] = {}
        self._link_index: dict[str, int] = {}

    def _bridge(self, bid: int, now: float) -> BridgeHealth:
        b = self.bridges.get(bid)
        if b is None:
            b = self.bridges[bid] = BridgeHealth(first_seen=now, clock_hz=self.clock_hz)
            self._forget_floor = min(self._forget_floor, now)  # it may be due to be forgotten some day
        self._awake.add(bid)
        return b

    # -- what arrived ---------------------------------------------------------------------
    def frames_seen(self, bid: int, seqs: list[int], window: int, boot: bool, link: str, now: float) -> bool:
        """Frames of ``bid`` numbered ``seqs`` came on ``link`` (``window``: the duplicate
        filter's, ``boot``: its HELLO numbered 0 is among them). True when its numbering
        restarted."""
        b = self._bridge(bid, now)
        restarts = b.seq_restarts
        b.frames_seen(seqs, window, boot)
        b.last_seen, b.link = now, link
        return b.seq_restarts != restarts

    def clock_reset(self, bid: int, now: float) -> None:
        """``bid``'s clock restarted (a reset, or a restart after a HELLO numbered 0)."""
        self._bridge(bid, now).clock_resets += 1

    def clock_rate(self, bid: int, hz: float, now: float) -> bool:
        """``bid``'s HELLO says its clock runs at ``hz``: True when that is news (0: unknown, ignored)."""
        b = self._bridge(bid, now)
        if b.clock_hz == hz or hz <= 0:
            return False
        b.clock_hz = float(hz)
        return True

    def sampled(self, newest: dict[int, int], origin: NDArray[np.int64], cycle: NDArray[np.uint64],
                now: float) -> None:
        """A read's DATA samples came (each one's bridge and cycle count); ``newest``: each
        bridge's newest sample's index, in the order its bridges were first met."""
        counts = Counter(origin.tolist())
        for bid, i in newest.items():
            b = self._bridge(bid, now)
            b.samples += counts[bid]
            b.last_cycle = int(cycle[i])

    def rejected(self, bids: NDArray[np.int64], now: float) -> None:
        """Mesh-time samples of ``bids`` (one entry each) whose index was not believed."""
        for bid, n in Counter(bids.tolist()).items():
            self._bridge(bid, now).index_rejected += n

    def unmapped(self, bids: NDArray[np.int64], now: float) -> None:
        """Samples of ``bids`` (one entry each) of elements the layout does not place. Such
        a bridge may be known by nothing else yet: its samples came in a readout record
        (folded into health only when it is read) before its HELLO."""
        for bid, n in Counter(bids.tolist()).items():
            self._bridge(bid, now).unmapped_samples += n

    def spoken_for(self, link: str, sampled: Sequence[int], unchanged: Sequence[int], now: float) -> None:
        """A readout record on ``link`` at ``now`` accounts for ``sampled`` (a sample each) and
        ``unchanged`` bridges (ids, 0..65535): heard. Folded in when health is read
        (:meth:`fold`), not per record: a thousand bridges a frame, a hundred frames a second.
        Each id is stored once in the loops below (``dict.fromkeys`` and ``update`` hashed and
        stored each twice, through a dict built for one record: twice the time)."""
        said = (float(now), self._link_index.setdefault(link, len(self._link_index)))
        heard, counts = self._heard, self._heard_samples
        for bid in unchanged:
            heard[bid] = said
        for bid in sampled:
            heard[bid] = said
            counts[bid] = counts.get(bid, 0) + 1

    def fold(self) -> None:
        """The bridges readout records spoke for since the last fold into their health:
        heard then, on that link, their samples counted."""
        heard, counts = self._heard, self._heard_samples
        if not heard:
            return
        self._heard, self._heard_samples = {}, {}
        names = list(self._link_index)
        for bid in sorted(heard):  # (by id: the order bridges are first seen in)
            at, via = heard[bid]
            b = self._bridge(bid, at)
            if at > b.last_seen:
                b.last_seen, b.link = at, names[via]
            b.samples += counts.get(bid, 0)

    def link_of(self, bid: int) -> str:
        """The link ``bid`` was last heard on ("" if never)."""
        b = self.bridges.get(bid)
        return "" if b is None else b.link

    def may_forget_from(self, t: float) -> None:
        """Something :meth:`forget` may have to drop was last heard at ``t`` (a new gateway
        id; ``-inf``: the layout changed, a bridge it no longer places may be due)."""
        self._forget_floor = min(self._forget_floor, t)

    # -- links ----------------------------------------------------------------------------
    def _link(self, link: str) -> LinkHealth:
        lh = self.links.get(link)
        if lh is None:
            lh = self.links[link] = LinkHealth(link)
        return lh

    def link_data(self, link: str, now: float) -> None:
        """A read of ``link`` (a link not configured is taken as a new one)."""
        if self.started is None:
            self.started = now
        self._link(link).last_data = now

    def link_state(self, link: str, connected: bool, now: float, error: str = "") -> None:
        self._link(link).set_state(connected, now, error)

    def link_stats(self, link: str, stats: dict[str, Any]) -> None:
        """The shell's own counters of a configured ``link``, shown in its health."""
        lh = self.links.get(link)
        if lh is not None:
            lh.extra = stats

    def link_names(self) -> list[str]:
        return list(self.links)

    # -- ticks ----------------------------------------------------------------------------
    def tick(self, now: float, elapsed: float, timeout: float, split: Split) -> list[LogEvent]:
        """A health tick ``elapsed`` s after the one before: each awake bridge's rate and
        silence (``timeout``); the log events of bridges gone silent or back: each placed
        bridge by itself, of the others the first :data:`UNPLACED_SHOWN` and one summary
        with the count (65 530 phantoms going quiet at once must not make 65 530 events)."""
        went_silent: list[int] = []
        came_back: list[int] = []
        for bid in list(self._awake):
            b = self.bridges[bid]
            if b.tick(now, elapsed, timeout):
                (went_silent if b.silent else came_back).append(bid)
            if b.silent and not b.rate:
                self._awake.discard(bid)
        events: list[LogEvent] = []
        for bids, level, what in ((went_silent, "warning", "went silent"), (came_back, "info", "are back")):
            placed, others = split(bids)
            for bid in placed + others[:UNPLACED_SHOWN]:
                events.append(LogEvent(level, f"no data from bridge {bid} for {now - self.bridges[bid].last_seen:.1f} s"
                                       if bids is went_silent else f"bridge {bid} is back"))
            if len(others) > UNPLACED_SHOWN:
                events.append(LogEvent(level, f"{len(others) - UNPLACED_SHOWN} more bridges the layout does not "
                                              f"place {what} (not logged one by one)"))
        return events

    def forget(self, before: float, split: Split) -> list[int] | None:
        """Drop the bridges the layout does not place last heard ``before``: phantoms of a
        noisy line or strangers would otherwise grow health and every tick forever. The ids
        dropped (their other owners forget them too), or None when nothing can be due: no
        scan of every origin per tick. Last-heard times only grow (a step back resets
        this), so until the oldest one left is due a scan forgets nothing; the caller
        lowers that bound for what else it forgets (:meth:`may_forget_from`)."""
        if before < self._forget_floor:
            return None
        gone = [b for b in split(self.bridges)[1] if self.bridges[b].last_seen < before]
        for bid in gone:
            del self.bridges[bid]
            self._awake.discard(bid)
        self.forgotten += len(gone)
        _, others = split(self.bridges)
        self._forget_floor = min((self.bridges[b].last_seen for b in others), default=math.inf)
        return gone

    def clock_stepped_back(self, now: float) -> None:
        """The host clock went back: last-heard times in the future are taken as ``now``, so a
        dead bridge is reported silent ``bridge_timeout`` after the step, not hours later."""
        self._awake.update(self.bridges)
        self._forget_floor = -math.inf
        for b in self.bridges.values():
            b.last_seen = min(b.last_seen, now)
            b.first_seen = min(b.first_seen, now)
        # (and nothing else reported lies in the future: uptime went negative, a link came up "tomorrow")
        if self.started is not None:
            self.started = min(self.started, now)
        for lh in self.links.values():
            if lh.connected_since is not None:
                lh.connected_since = min(lh.connected_since, now)
            if lh.last_data is not None:
                lh.last_data = min(lh.last_data, now)

    # -- what is reported -------------------------------------------------------------------
    def alive(self) -> set[int]:
        """The bridges not silent (as of the last tick)."""
        self.fold()
        return {b for b, bh in self.bridges.items() if not bh.silent}

    def summary(self) -> str:
        """Links up, bridges alive: one line for the service manager's status."""
        alive = len(self.alive())
        up = sum(1 for h in self.links.values() if h.connected)
        return f"{up}/{len(self.links)} links up, {alive}/{len(self.bridges)} bridges alive"

    def uptime(self, now: float) -> float:
        return 0.0 if self.started is None else now - self.started

    def links_report(self, counters: Callable[[str], dict[str, Any]], wall: float) -> dict[str, Any]:
        """Each link's health, with its decoder's ``counters``; times moved by ``wall`` s."""
        out = {}
        for name, lh in self.links.items():
            rep = link_report(lh, counters(name))
            for key in ("connected_since", "last_data"):
                rep[key] = _moved(rep[key], wall)
            out[name] = rep
        return out

    def bridges_report(self, now: float, split: Split, reassembly_drops: Callable[[int], int],
                       wall: float) -> dict[str, Any]:
        """The bridge fields of ``health``: every placed bridge, of the others (phantoms,
        strangers, bridges not yet placed by a HELLO) the lowest ids up to
        :data:`UNPLACED_SHOWN`, the rest only counted; times moved by ``wall`` s."""
        self.fold()
        placed, others = split(self.bridges)
        others.sort()
        unplaced = [b for b in others if self.bridges[b].unmapped_samples]
        shown = sorted(placed + others[:UNPLACED_SHOWN])
        bridges = {}
        for b in shown:
            rep = self.bridges[b].report(now)
            for key in ("first_seen", "last_seen"):
                rep[key] = _moved(rep[key], wall)
            rep["reassembly_drops"] = reassembly_drops(b)
            bridges[str(b)] = rep
        return {
            "bridges": bridges,
            "bridges_not_shown": len(self.bridges) - len(shown),
            "silent": sorted(b for b in shown if self.bridges[b].silent),
            # a bridge not awake is silent: counted without walking every origin
            "silent_count": len(self.bridges) - sum(1 for b in self._awake if not self.bridges[b].silent),
            "unplaced": unplaced[:UNPLACED_SHOWN],
            "unplaced_count": len(unplaced),
            "forgotten_bridges": self.forgotten,
        }


def _moved(t: float | None, by: float) -> float | None:
    return None if t is None else t + by
