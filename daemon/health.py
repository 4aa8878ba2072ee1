"""Health bookkeeping, sans-I/O: per bridge, per element channel and per link.

Users of a skin that runs for days need the daemon to *tell the truth*: which bridge
went quiet, how much was lost and where, which channel is stuck or saturated. Every
number here is counted from the traffic itself; nothing is estimated that could be
counted.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

_SEQ_MOD = 0x10000
_SEQ_HALF = 0x8000


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

