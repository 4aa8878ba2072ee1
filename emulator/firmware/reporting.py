"""Which samples a bridge reports: every one (periodic) or only changes (event-based).

Event-based reporting is how a large skin stays inside one shared 1 Mbit/s link: an
untouched element sends a heartbeat now and then; a sample goes out as soon as it
differs from the last one *sent* by more than the threshold on either channel, so a
press is never missed and a slow drift is reported once it adds up, and the sample after
a change goes out too (the change may have begun during the changed sample's gates).
After a change the bridge watches the reading settle: once ``SETTLE_SAMPLES`` samples in
a row agree within the *settle band* (an eighth of the threshold, at least one count),
the last of them goes out if it lies outside that band of the last sample sent. A press
sliding off an element changes it a little per sample; its last sent reading could stay
up to a threshold away from where it came to rest (still "touched" at the host) until
the heartbeat, up to a second later. Settling costs one sample per change at most.

On mesh time every bridge samples the same instants, so heartbeats timed only from the
last sample sent would leave all bridges in the same frame once a second: a burst that
contends for the cells, delays every heartbeat by tens of milliseconds and, through the
delivery delays the host learns from them, holds every skin frame back as long. Each
bridge therefore sends its heartbeat in its own *slot* of the heartbeat period (its
``phase``, spread by its id): the first sample after the last one sent whose index ≡ slot
modulo the heartbeat in samples, so never more than one heartbeat apart, and a change
costs at most one early heartbeat. Off mesh time (no shared index) a heartbeat is one
heartbeat after the last sample sent.

The command ``SET_REPORTING`` carries the choice in one u64 (docs/protocol.md):
0 = periodic; otherwise bits 0–31 are the threshold (counts or summed codes) and
bits 32–63 the heartbeat in milliseconds (0 = the default heartbeat).
"""

from __future__ import annotations

from dataclasses import dataclass

from cellbridge.protocol import Sample

DEFAULT_HEARTBEAT_MS = 1000
#: Samples in a row that must agree within the settle band for a reading to have settled.
SETTLE_SAMPLES = 3
MAX_HEARTBEAT_MS = 600_000


@dataclass(frozen=True)
class ReportingMode:
    #: None = periodic; otherwise event-based with this threshold (0: every change is sent)
    threshold: int | None = None
    heartbeat_ms: int = DEFAULT_HEARTBEAT_MS

    @property
    def periodic(self) -> bool:
        return self.threshold is None

    @classmethod
    def from_value(cls, value: int) -> ReportingMode:
        """Decode the SET_REPORTING value; ValueError for a heartbeat out of range."""
        threshold, heartbeat = value & 0xFFFF_FFFF, value >> 32
        if heartbeat > MAX_HEARTBEAT_MS:
            raise ValueError(f"heartbeat {heartbeat} ms exceeds {MAX_HEARTBEAT_MS}")
        if value == 0:
            return cls()
        return cls(threshold, heartbeat or DEFAULT_HEARTBEAT_MS)  # threshold 0: any change

    def to_value(self) -> int:
        return 0 if self.threshold is None else self.threshold | (self.heartbeat_ms << 32)


class Reporter:
    """Decides per sample whether it is sent; counts what it suppressed."""

    def __init__(self, mode: ReportingMode, cycles_per_ms: int, modulus: int = 1 << 16,
                 phase: float = 0.0) -> None:
        """``phase`` in [0, 1): the bridge's heartbeat slot as a fraction of the heartbeat
        period (see the module); 0 for every bridge puts all heartbeats in one frame."""
        if not 0.0 <= phase < 1.0:
            raise ValueError(f"phase {phase} must be in [0, 1)")
        self.mode = mode
        self._cpm = cycles_per_ms
        self._phase = phase
        self._mod = modulus
        self._last: Sample | None = None
        self._follow = False  #: the last sample sent was a change: send the next one too
        #: samples since a change, while the reading has not settled (None: not watching)
        self._settling: list[Sample] | None = None
        self.suppressed = 0

    def set_mode(self, mode: ReportingMode, counter_modulus: int) -> None:
        self.mode = mode
        self._mod = counter_modulus
        self._last = None  # the next sample is sent, so the host has a fresh reference
        self._follow = False
        self._settling = None

    def _moved(self, a: int, b: int) -> int:
        d = abs(a - b)
        return min(d, self._mod - d) if self._mod else d

    def _heartbeat(self, s: Sample, last: Sample, period_cycles: int, on_time: bool) -> bool:
        """Whether ``s`` is the heartbeat after ``last``: in the bridge's slot (on mesh time,
        where indices are shared), else one heartbeat on."""
        beat = self.mode.heartbeat_ms * self._cpm
        if s.cycle - last.cycle >= beat:
            return True
        if not on_time or period_cycles <= 0:
            return False
        per_beat = max(1, beat // period_cycles)
        return s.index % per_beat == int(self._phase * per_beat)

    def wants(self, s: Sample, period_cycles: int = 0, on_time: bool = False) -> bool:
        """Whether ``s`` is sent. Event-based, a sample sent for a change is followed by the
        next one as well: a press or release that began during the sample's gates left it
        part-way, and the clean sample after it may differ from it by less than the
        threshold; without it the host would hold the part-way reading as the element's
        value until the next change or heartbeat (up to a second: a corner press came out
        millimetres off and light for that long). ``period_cycles`` (the sampling period)
        and ``on_time`` (``s.index`` is the mesh-time sample index) place the heartbeat in
        the bridge's slot; without them it is one heartbeat after the last sample sent."""
        m = self.mode
        last = self._last
        if m.threshold is None or last is None:
            self._last = s
            return True
        changed = (self._moved(s.c1, last.c1) > m.threshold or self._moved(s.c2, last.c2) > m.threshold
                   or s.flags != last.flags)
        if changed or self._follow or self._heartbeat(s, last, period_cycles, on_time):
            self._last = s
            self._follow = changed
            if changed:
                self._settling = []
            return True
        if self._settling is not None and self._settled(s, last):
            return True
        self.suppressed += 1
        return False

    @property
    def reference(self) -> Sample | None:
        """The last sample sent: what an *unchanged* refers to (None: the next is sent)."""
        return self._last

    def sent(self, s: Sample) -> None:
        """``s`` went out although :meth:`wants` did not ask for it (the readout's refresh):
        it is the reference of what follows, as any sample sent is."""
        self._last = s

    def lost(self) -> None:
        """The last sample sent went nowhere (the readout's bridge had no route): it is no
        reference, so the next sample is sent. Without this the frames after it were
        *unchanged* from a reading no one got, and a parent that kept an older sample took
        them as unchanged from that one."""
        self._last = None
        self._follow = False
        self._settling = None

    def _settled(self, s: Sample, last: Sample) -> bool:
        """Watching a change settle: True when ``s`` completes ``SETTLE_SAMPLES`` samples
        that agree within the settle band and the first of them lies outside it from the
        last sample sent (then ``s`` is sent: the settled reading, a sample later)."""
        watch = self._settling
        assert watch is not None
        band = max(1, (self.mode.threshold or 0) // 8)
        watch.append(s)
        first = watch[0]
        if any(self._moved(x.c1, first.c1) > band or self._moved(x.c2, first.c2) > band for x in watch):
            del watch[:-1]  # still moving: start again from this sample
            return False
        if len(watch) < SETTLE_SAMPLES:
            return False
        self._settling = None
        if self._moved(s.c1, last.c1) > band or self._moved(s.c2, last.c2) > band:
            self._last = s
            return True
        return False
