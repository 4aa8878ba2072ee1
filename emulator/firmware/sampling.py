"""The bridge's measurement schedule and the DATA frames it fills.

One sample is a C1 gate then a C2 gate on the counter (or two bursts of ADC
conversions), repeated at the sampling rate. With mesh time (:mod:`.meshtime`) sample
``k`` starts its C1 gate at global time ``k / rate`` on every bridge, so one index is one
instant of the whole skin; without it (booting, cut off) the bridge samples on its own
crystal and flags its samples ``NO_MESH_TIME``. The next gate is planned when a sample is
taken, with the mesh clock as it is then; the firmware takes every sample due before it
changes the clock (:meth:`Sampler.advance`), so lazy and gate-by-gate sampling agree.

Samples the reporter keeps are batched into one DATA payload: fewer, larger frames carry
more samples per bit of air time. Periodic samples on mesh time go in *aligned batches*
(``aligned``: ``FirmwareConfig.aligned_batches``, on by default): indices ``[j·n, (j+1)·n)``
share a frame, with ``n`` the samples that fit in ``max_latency`` (and in a frame). Every
bridge closes the same batch at the same global instant, so one index waits as long on
every bridge; the closed batch then leaves in the bridge's slot (``slot``, asked at each
close: the firmware's depth-ordered slots, deepest first), while the next batch fills.
With batches closed at each bridge's own phase, one bridge's sample of an index could
trail another's by a whole ``max_latency``, and the host waits for the slowest before it
has a skin frame. Any other sample (no mesh time, event-based reporting) waits until the batch is
full (255-byte frame, ``batch_max`` samples) or its oldest sample is ``max_latency`` old
(``event_latency`` under event-based reporting).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

import msgpack
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.meshtime import Timebase
from cellbridge.emulator.firmware.reporting import Reporter
from cellbridge.protocol import CRC_LEN, HEADER_LEN, MAX_FRAME, Data, Mode, Sample, SampleFlags
from cellbridge.protocol.messages import packed_sample

# header, CRC, DATA array, mode, oversampling (<= 3 bytes), samples array header (<= 3 bytes),
# rate (<= 3 bytes), period (u32, <= 5 bytes)
_DATA_OVERHEAD = HEADER_LEN + CRC_LEN + 1 + 1 + 3 + 3 + 3 + 5
# msgpack of a frame's first sample, [element, cycle, c1, c2, flags, index], at the widest
_MAX_SAMPLE_BYTES = 1 + 3 + 9 + 5 + 5 + 2 + 9
_NO_MESH_TIME = int(SampleFlags.NO_MESH_TIME)
_HELD = int(SampleFlags.HELD)
_COUNTER_MODULUS = 1 << 16


def _uint_bytes(value: int) -> int:
    """msgpack bytes of a non-negative integer up to ``value``."""
    return 1 if value < 128 else 2 if value <= 0xFF else 3 if value <= 0xFFFF else 5 if value <= 0xFFFF_FFFF else 9


class Sampler:
    def __init__(self, settings: Settings, chip: object, sense: Callable[[int], tuple[float, float]],
                 first_start: int, clock_hz: int, batch_max: int, max_latency: int, lazy: bool,
                 counters: Counter[str], timebase: Timebase, event_latency: int | None = None,
                 slot: Callable[[], int] = lambda: 0, aligned: bool = True, heartbeat_phase: float = 0.0,
                 readout: Callable[[Sample, bool, int], None] | None = None,
                 readout_wait: Callable[[], int] = lambda: 0) -> None:
        self.settings = settings
        self.chip = chip
        self.sense = sense
        self.clock_hz = clock_hz
        self.batch_max = batch_max
        self.max_latency = max_latency
        #: the same bound under event-based reporting: few samples travel, so a short wait
        #: costs little air time, and the sample that shows a press's onset goes at once
        self.event_latency = max_latency if event_latency is None else event_latency
        self.lazy = lazy
        self.counters = counters
        self.reporter = Reporter(settings.reporting, clock_hz // 1000, phase=heartbeat_phase)
        self.batch: list[Sample] = []
        self.batch_bytes = 0
        self.flush_at = -1
        self._batch_aligned = False  #: the open batch is an aligned one
        #: closed aligned batches waiting for their slot, as (tick they leave, payload), in order
        self._leaving: list[tuple[int, Data]] = []
        #: How long an aligned batch waits after its last sample before it leaves (asked at
        #: each close: the bridge's depth may have changed): bridges sharing a cell get
        #: different slots, so they do not all contend for it at the same instant
        self.slot = slot
        self.aligned = aligned  #: periodic samples on mesh time go in aligned batches
        self.timebase = timebase
        self.start = first_start
        self.index = 0  #: index of the sample whose gate starts at ``start``
        self.on_time = False  #: whether that gate is on mesh time
        #: the time root whose mesh time ``index`` counts (its clock's when the gate was
        #: planned: the clock may follow another root by the gate's end)
        self.root = 0
        self.ready = first_start + settings.measure_cycles()
        #: The scheduled readout (:mod:`.readout`): a sample on mesh time goes there, with
        #: whether the reporter keeps it (False: unchanged) and its gate start tick, instead
        #: of into a DATA frame. None: every sample goes in DATA frames.
        self.readout = readout
        self._sensed: tuple[float, float] | None = None  #: the capacitances of the last sample's gate
        #: With ``lazy``: how long after its gate end a sample on the readout schedule may
        #: wait to be computed (cycles, asked at each look): until its frame's record can go.
        #: A relay's record waits for its children's records, each of which wakes it, so its
        #: own sample is computed at the wake of the last of them (or at its slot) instead
        #: of at a wake of its own; a leaf's record goes at its gate end (0).
        self.readout_wait = readout_wait

    @property
    def next_tick(self) -> int:
        """When sampling next needs the bridge's attention. Samples change nothing outside
        the bridge until a DATA frame is due (full, or its oldest sample ``max_latency``
        old), so with ``lazy`` the samples in between are computed then, all at once, with
        the same cycles and values: invisible on the cell, and a bridge wakes once per
        frame instead of once per gate. Event-based reporting too: the wake is planned as
        if every sample were kept (the earliest a frame can be due), and a sample kept
        there waits ``max_latency`` for company anyway. The capacitance a lazily computed
        sample sees is the one at its gate (``sense`` is called with the gate's tick)."""
        leave = self._leaving[0][0] if self._leaving else self.ready
        if self.lazy and self.readout is not None and self.on_time:
            # on the readout schedule a sample is due when its frame's record can go: at its
            # gate end, or (a relay) when its children's records are in, at its slot at the
            # latest (``readout_wait``); every child's record wakes the bridge meanwhile. Not
            # while samples taken before mesh time wait in a batch: this one sends them.
            due = self.ready if self.batch else self.ready + self.readout_wait()
            if self._leaving and self._leaving[0][0] < due:
                due = self._leaving[0][0]
            return due if self.flush_at < 0 else min(due, self.flush_at)
        if not self.lazy or (self.readout is not None and self.on_time):
            return min(self.ready if self.flush_at < 0 else min(self.ready, self.flush_at), leave)
        if self.batch and self._batch_aligned != self._aligned():
            # the next sample closes the batch (aligned or timed, never both), unless its
            # ``max_latency`` comes first
            return min(self.ready, self.flush_at, leave)
        room = max(1, min(self.batch_max - len(self.batch), self._fit(self.batch_bytes, bool(self.batch))))
        if self._aligned():  # the ready tick of the batch's last index, at the latest
            room = min(room, self.aligned_batch() - self.index % self.aligned_batch())
        # planned a little early (a crystal 0.1 % fast at most): a wake too early costs
        # nothing, one too late would send the frame later than gate-by-gate sampling does
        period = self.settings.period_cycles(self.clock_hz)
        full = self.ready + (room - 1) * (period - period // 1000)
        return min(full, self.flush_at if self.batch else self.ready + self.latency, leave)

    def prefetch(self, n: int) -> bool:
        """Have the chip compute the counts of the next ``n`` samples on mesh time now
        (:meth:`Chip.prefetch <cellbridge.emulator.chip.chip.Chip.prefetch>`), at the gates
        the mesh clock plans now and the capacitances sensed at the next gate; a sample
        whose gate or capacitance turns out otherwise (the clock corrected meanwhile, a
        press) is computed when it is taken, as ever. Only when the next sample's counts
        are not computed ahead already, the element is steady (the next gate senses what
        the last one did: at rest, not while pressed, when every gate senses anew), in
        counter mode on mesh time, and when the chip model can; True when it computed.
        Changes nothing the bridge sends: a real-time shell calls it after a wake's work,
        so the chip's next gates run while its code is warm."""
        chip = self.chip
        st = self.settings
        if not self.on_time or st.mode is not Mode.COUNTER or n <= 0 or not hasattr(chip, "prefetch"):
            return False
        c1, c2 = self.sense(self.start)
        gate = st.gate_cycles
        if (c1, c2) != self._sensed or chip.computed(0, c1, self.start, gate):  # type: ignore[attr-defined]  # has a prefetch
            return False
        tb, rate = self.timebase, st.rate_hz
        gates = []
        for k in range(self.index, self.index + n):
            t = self.start if k == self.index else tb.gate_tick(k, rate)
            gates += [(0, c1, t, gate), (1, c2, t + gate, gate)]
        chip.prefetch(gates)
        return True

    def aligned_batch(self) -> int:
        """Samples per aligned batch: as many sample periods as fit in ``max_latency``,
        at least one, and never more than a frame holds (a batch that overflowed its frame
        would close early and lose its alignment)."""
        fit = self._fit(0, False)
        per = self.max_latency * self.settings.rate_hz // self.clock_hz
        return max(1, min(per, self.batch_max, fit))

    def _fit(self, used: int, started: bool) -> int:
        """How many more samples a DATA frame holding ``used`` bytes of samples takes, as the
        planner counts them: a frame's first sample at its widest, every later one packed
        (protocol version 3: :func:`~cellbridge.protocol.messages.packed_sample`) with its
        values at the widest this mode gives (element and flags below 128), its index step
        below 128 and its cycle residual within 16 bits (a crystal's drift and mesh-time
        corrections over one period; 655 µs at 50 MHz). A sample packed wider than that (an
        index jump when mesh time is taken, a clock step) is still counted exactly when it
        is batched: its frame then only fills sooner than planned."""
        free = MAX_FRAME - _DATA_OVERHEAD - used
        n = 0
        if not started:
            if free < _MAX_SAMPLE_BYTES:
                return 0
            free -= _MAX_SAMPLE_BYTES
            n = 1
        st = self.settings
        code = 3 if st.mode is Mode.COUNTER else _uint_bytes(255 * st.oversampling)
        return n + free // (1 + 1 + 3 + 2 * code + 1 + 1)

    def _aligned(self) -> bool:
        """Whether the sample planned next goes in an aligned batch (periodic, on mesh time)."""
        return self.aligned and self.on_time and self.settings.reporting.periodic

    @property
    def latency(self) -> int:
        """How long a sample waits at most for company in a DATA frame, in this reporting mode."""
        return self.max_latency if self.settings.reporting.periodic else self.event_latency

    def advance(self, tick: int) -> list[Data]:
        """Take every sample due by ``tick``; the DATA payloads that are complete."""
        out: list[Data] = []
        while self.ready <= tick:
            self._sample(out)
        if 0 <= self.flush_at <= tick:
            self._flush(out)
        while self._leaving and self._leaving[0][0] <= tick:
            self._emit(out, self._leaving.pop(0)[1])
        return out

    @property
    def unsent(self) -> int:
        """Samples taken and kept but not yet handed on in a DATA payload (what a power-off
        loses): the open batch and closed aligned batches waiting for their slot."""
        return len(self.batch) + sum(len(d.samples) for _, d in self._leaving)

    def apply(self, new: Settings, tick: int) -> list[Data]:
        """New settings from a command; a schedule change closes the current batch."""
        # Samples due before the command were taken before it on the chip; with lazy
        # sampling they may not be computed yet, and must be under the old settings.
        out = self.advance(tick - 1)
        old = self.settings
        schedule = (new.period_cycles(self.clock_hz) != old.period_cycles(self.clock_hz)
                    or new.measure_cycles() != old.measure_cycles() or new.mode != old.mode)
        if schedule:
            # one DATA payload holds one mode (and one rate): the open batch leaves labelled
            # with the settings its samples were taken under (labelled with the new rate, a
            # 100 Hz index read as a 50 Hz one: seconds off on mesh time)
            self._flush(out)
        self.settings = new
        if new.reporting != old.reporting or new.mode != old.mode:
            self.reporter.set_mode(new.reporting, _COUNTER_MODULUS if new.mode is Mode.COUNTER else 0)
        if schedule:
            at = max(tick, self.start)
            self._plan(at, at, new.rate_hz != old.rate_hz)
        return out

    def _plan(self, earliest: int, free: int, restart: bool = False) -> None:
        """Plan the next gate at or after ``earliest`` (a tick): on mesh time, the next index
        whose global instant this bridge has not passed; else at ``free`` (the bridge's own
        schedule). Indices on mesh time only grow (``restart``: a new rate, new indices)."""
        st = self.settings
        rate = st.rate_hz
        tb = self.timebase
        if tb.synced(earliest):
            # At the gate limit a sample fills its whole period; a crystal slower than the
            # root's overruns it by its offset (<= 0.1 %): the next gate starts on time.
            slack = st.measure_cycles() // 1000
            k = tb.first_index(earliest - slack, rate)
            if self.on_time and not restart and k <= self.index:
                k = self.index + 1
            t = tb.gate_tick(k, rate)
            while t < earliest - slack:  # the fit moved between the two calls: the next one
                k += 1
                t = tb.gate_tick(k, rate)
            if self.on_time and not restart and k > self.index + 1:
                self.counters["frames_skipped"] += k - self.index - 1
            self.start, self.index, self.on_time = t, k, True
            self.root = tb.clock.root or 0
        else:
            if self.on_time or restart:
                self.index = 0
            else:
                self.index += 1
            self.start = free
            self.on_time = False
        self.ready = self.start + st.measure_cycles()

    def _sample(self, out: list[Data]) -> None:
        st = self.settings
        start = self.start
        ready = self.ready
        aligned = self._aligned()
        if self.batch and aligned != self._batch_aligned:
            self._flush(out)  # a batch is either aligned or timed, never both
        self._batch_aligned = aligned
        c1, c2 = self._sensed = self.sense(start)
        if st.mode is Mode.COUNTER:
            v1, o1 = self.chip.count(0, c1, start, st.gate_cycles)  # type: ignore[attr-defined]  # the chip model is pluggable (tests pass their own); count/convert are its interface
            v2, o2 = self.chip.count(1, c2, start + st.gate_cycles, st.gate_cycles)  # type: ignore[attr-defined]  # the chip model is pluggable (tests pass their own); count/convert are its interface
            flags = (SampleFlags.OVERFLOW_C1 if o1 else 0) | (SampleFlags.OVERFLOW_C2 if o2 else 0)
        else:
            v1, took = self.chip.convert(0, c1, start, st.oversampling)  # type: ignore[attr-defined]  # the chip model is pluggable (tests pass their own); count/convert are its interface
            v2, _ = self.chip.convert(1, c2, start + took, st.oversampling)  # type: ignore[attr-defined]  # the chip model is pluggable (tests pass their own); count/convert are its interface
            flags = 0
        if not self.on_time:
            flags |= _NO_MESH_TIME
        if not st.reporting.periodic:
            flags |= _HELD
        s = Sample(0, self.timebase.local(start), v1, v2, int(flags), self.index)
        self.counters["samples"] += 1
        period = st.period_cycles(self.clock_hz)
        if self.readout is not None and self.on_time:
            if self.batch:
                self._flush(out)  # samples taken before mesh time leave first
            self.readout(s, self.reporter.wants(s, period, True), start)
            self._plan(start + st.measure_cycles(), self.timebase.after_local(start, period))
            return
        if self.reporter.wants(s, period, self.on_time):
            size = len(msgpack.packb(packed_sample(self.batch[-1] if self.batch else None, s, period)))
            if self.batch and _DATA_OVERHEAD + self.batch_bytes + size > MAX_FRAME:
                self._flush(out)
                size = len(msgpack.packb(packed_sample(None, s, period)))  # now the first of its frame
            self.batch.append(s)
            self.batch_bytes += size
            if self.flush_at < 0:
                self.flush_at = self.ready + self.latency
            if len(self.batch) >= self.batch_max:
                self._flush(out)
        index = self.index
        self._plan(start + st.measure_cycles(), self.timebase.after_local(start, st.period_cycles(self.clock_hz)))
        if aligned and self.batch:
            per = self.aligned_batch()
            # the batch's last index is taken, or the next sample is in a later batch (indices
            # skipped) or off mesh time: the batch is closed, as on every other bridge, and
            # leaves in this bridge's slot; the next batch fills meanwhile
            if not self._aligned() or self.index // per != index // per:
                wait = self.slot()
                if wait == 0:
                    self._flush(out)
                else:
                    self._leaving.append((ready + wait, self._take()))

    def _take(self) -> Data:
        """The open batch as a DATA payload; the batch starts empty."""
        st = self.settings
        data = Data(st.mode, tuple(self.batch), st.oversampling if st.mode is Mode.ADC else 1, st.rate_hz,
                    st.period_cycles(self.clock_hz))
        self.batch = []
        self.batch_bytes = 0
        self.flush_at = -1
        return data

    def _emit(self, out: list[Data], data: Data) -> None:
        out.append(data)
        self.counters["data_frames"] += 1
        self.counters["samples_sent"] += len(data.samples)

    def _flush(self, out: list[Data]) -> None:
        """Hand on the open batch now; closed batches still waiting for their slot go first
        (a bridge's frames leave in the order of their samples)."""
        while self._leaving:
            self._emit(out, self._leaving.pop(0)[1])
        if self.batch:
            self._emit(out, self._take())
        self.flush_at = -1
